"""Per-image metric records -> mean ± standard error tables in the shape of the paper's Table I.

The records and their per-image CSV (``<run_dir>/metrics_per_image.csv``) are :mod:`difareli.evaluation.records`;
every name there stays importable from here (``tables.Record``, ``tables.read_records``, ...).

Statistics per (method, protocol) and metric: mean and standard error
``SE = std(ddof=1) / sqrt(n)`` (sample standard deviation; SE is NaN when n < 2). Every rendered table
shows the n each mean is over. One table never mixes metric rules, and every rendering states its rule. Failed
relights (``status`` ``failed``) count as failed in the table and never enter a mean; rows left out by
``drop_bad_rows`` are counted under the table. Undefined extra-metric cells are counted apart (``(n=k)``).

:func:`merge_runs` merges run dirs; two runs of one method (two checkpoints, two step counts) are told apart by a
label per run dir (``labels``, ``difareli-table label=[...]``), and refused without one rather than merged.
``difareli-table strata=`` breaks a table down by the :data:`STRATA` columns.

Rows quoted from a paper (:attr:`Table.published`, e.g. ``difareli.evaluation.published``) are marked as such in
every rendering and never take part in the bold "best" marks, which compare what was measured here.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

from difareli.errors import UserError
from difareli.evaluation.metrics import DEFAULT_RULE, describe
# Re-exported: callers read and write per-image CSVs through ``tables`` (tables.Record, tables.read_records, ...).
from difareli.evaluation.records import (  # noqa: F401
    BAD_ROW_FIX, BETTER, COLUMNS, EXTRA_METRICS, LEGACY_RULE, METRIC_LABELS, METRICS, PER_IMAGE_CSV, STRATA,
    TABLE_BAD_ROW_FIX, Record, Stat, TableError, extra_columns, header, mean_se, read_records, read_records_checked,
    read_runs, record_row, write_records)
from difareli.evaluation.records import PROTOCOL_LABELS, _protocol_key, protocol_label  # noqa: F401
from difareli.evaluation import paired
from difareli.utils.fileio import write_text_atomic


@dataclass
class Table:
    """Summary statistics: ``cells[(method, protocol)][metric] -> Stat``; ``seconds[method] -> Stat``."""

    methods: list[str]
    protocols: list[str]
    cells: dict[tuple[str, str], dict[str, Stat]]
    seconds: dict[str, Stat]
    #: failed relights per (method, protocol): counted, never averaged
    failed: dict[tuple[str, str], int] = field(default_factory=dict)
    #: "file:line: problem" of rows left out by ``drop_bad_rows``
    dropped: list[str] = field(default_factory=list)
    #: the metric rule every measured row was scored under (difareli.evaluation.metrics.RULES)
    rule: str = DEFAULT_RULE
    #: rows quoted from a paper: method -> where the figures come from (rendered as published, never bold)
    published: dict[str, str] = field(default_factory=dict)
    #: the metric columns, in order: :data:`METRICS` then the :data:`EXTRA_METRICS` the records carry
    metrics: list[str] = field(default_factory=lambda: list(METRICS))
    #: lines saying why a metric is absent or how a breakdown was made (printed under the table)
    remarks: list[str] = field(default_factory=list)
    #: the run dirs each measured method's rows came from (:func:`merge_runs`)
    runs: dict[str, list[Path]] = field(default_factory=dict)

    def add_published(self, rows: dict[tuple[str, str], dict[str, Stat]], source: str) -> None:
        """Append rows quoted from ``source`` (``{(method, protocol): {metric: Stat}}``) after the measured ones."""
        for (m, p), stats in rows.items():
            if m in self.methods and m not in self.published:
                raise UserError(f"published row {m!r} has the name of a measured method; rename one of them")
            if m not in self.methods:
                self.methods.append(m)
            self.published[m] = source
            self.cells[(m, p)] = dict(stats)
            if p not in self.protocols:
                self.protocols = sorted([*self.protocols, p], key=_protocol_key)

    # -- formatting helpers
    def _best(self) -> dict[tuple[str, str], float]:
        """Best mean per (protocol, metric) over the measured rows, in :data:`BETTER`'s sense (stored as the value
        whose printed form is compared)."""
        best: dict[tuple[str, str], float] = {}
        for (m, p), stats in self.cells.items():
            if m in self.published:
                continue
            for k, s in stats.items():
                if math.isfinite(s.mean) and k in BETTER:
                    have = best.get((p, k))
                    if have is None or _badness(k, s.mean) < _badness(k, have):
                        best[(p, k)] = s.mean
        return best

    def _cell(self, method: str, protocol: str, metric: str, digits: int, latex: bool, bold: bool) -> str:
        s = self.cells.get((method, protocol), {}).get(metric)
        if s is None or s.n == 0:
            return "--" if latex else "–"
        pm = r" \pm " if latex else " ± "
        se = f"{s.se:.{digits}f}" if math.isfinite(s.se) else "n/a"
        # A metric over fewer images than its protocol's n column says so in the cell.
        group_n = max(x.n for x in self.cells[(method, protocol)].values())
        se += f" (n={s.n})" if s.n != group_n else ""
        body = f"{s.mean:.{digits}f}{pm}{se}"
        if latex:
            return f"$\\mathbf{{{s.mean:.{digits}f}}}{pm}{se}$" if bold else f"${body}$"
        return f"**{body}**" if bold else body

    def _n(self, method: str, protocol: str) -> str:
        """The n of the protocol's means, with failed relights counted next to it."""
        stats = self.cells.get((method, protocol), {})
        if not stats and method in self.published:
            return "–"  # not in that protocol's published table
        n = max((s.n for s in stats.values()), default=0)
        k = self.failed.get((method, protocol), 0)
        return f"{n} (+{k} failed)" if k else str(n)

    def label(self, method: str) -> str:
        """The row label: published rows end in ``[published]``."""
        return f"{method} [published]" if method in self.published else method

    def notes(self) -> list[str]:
        """Lines to print under a table: the metric rule, published rows, failed relights and rows left out."""
        out = [f"Metrics {describe(self.rule)}."] + list(self.remarks)
        if any(k not in METRICS for k in self.metrics):
            out.append("A cell's (n=k) counts the images where that metric is defined (e.g. shadow metrics need a "
                       "target shadow covering 5-95% of the face); the others are counted apart, never averaged.")
        for src in dict.fromkeys(self.published.values()):
            names = ", ".join(m for m, s in self.published.items() if s == src)
            out.append(f"[published]: {names}: figures quoted from {src}; not measured here, never marked best.")
        fails = sum(self.failed.values())
        if fails:
            out.append(f"{fails} relight(s) failed (non-finite result): counted in n as '+k failed', not averaged.")
        if self.dropped:
            out.append(f"{len(self.dropped)} bad row(s) dropped (drop_bad_rows=true): " + "; ".join(self.dropped[:5])
                       + (" ..." if len(self.dropped) > 5 else ""))
        return out

    def _time(self, method: str) -> str:
        # 3 significant digits: spans 0.07 s (DiFaReli++) to minutes (DiFaReli) without leading zeros; trailing
        # zeros kept (3.00, not 3, which reads as a rounded figure).
        s = self.seconds.get(method)
        return f"{s.mean:#.3g}".rstrip(".") if s is not None and s.n else "–"

    def _is_best(self, best, method, protocol, metric, digits) -> bool:
        s = self.cells.get((method, protocol), {}).get(metric)
        b = best.get((protocol, metric))
        # Compare at the printed precision so ties print bold together.
        return (s is not None and b is not None and s.n > 0
                and round(_badness(metric, s.mean), digits) == round(_badness(metric, b), digits))

    # -- renderers
    def to_markdown(self, digits: int = 4, bold_best: bool = True) -> str:
        """GitHub Markdown: one row per method, columns ``<protocol> <metric>`` and ``<protocol> n``, then
        ``s/img``; notes (failed relights, dropped rows) follow the table."""
        best = self._best()
        head = ["Method"] + [f"{protocol_label(p)} {c}" for p in self.protocols
                             for c in [*(METRIC_LABELS[k] for k in self.metrics), "n"]] + ["s/img"]
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" + "---:|" * (len(head) - 1)]
        for m in self.methods:
            row = [self.label(m)]
            for p in self.protocols:
                row += [self._cell(m, p, k, digits, False, bold_best and self._is_best(best, m, p, k, digits))
                        for k in self.metrics] + [self._n(m, p)]
            lines.append("| " + " | ".join(row + [self._time(m)]) + " |")
        return "\n".join(lines) + "\n\n" + "\n".join(self.notes()) + "\n"

    def to_markdown_long(self, digits: int = 4, bold_best: bool = True) -> str:
        """GitHub Markdown with one row per protocol (and stratum) and method, columns the metrics and n: for tables
        with many column groups (a breakdown by stratum); the notes follow, as under :meth:`to_markdown`."""
        best = self._best()
        split = {p: p.partition(" | ") for p in self.protocols}
        strata = any(sep for _, sep, _ in split.values())
        head = ["Protocol", *(["Stratum"] if strata else []), "Method", *(METRIC_LABELS[k] for k in self.metrics), "n"]
        lead = len(head) - len(self.metrics) - 1
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * lead + "---:|" * (len(head) - lead)]
        for p, (base, _, stratum) in split.items():
            for m in (m for m in self.methods if (m, p) in self.cells):
                row = [protocol_label(base), *([stratum] if strata else []), self.label(m)]
                row += [self._cell(m, p, k, digits, False, bold_best and self._is_best(best, m, p, k, digits))
                        for k in self.metrics]
                lines.append("| " + " | ".join(row + [self._n(m, p)]) + " |")
        return "\n".join(lines) + "\n\n" + "\n".join(self.notes()) + "\n"

    def to_latex(self, digits: int = 4, bold_best: bool = True, caption: str | None = None) -> str:
        """Booktabs table: a column group per protocol (DSSIM, MSE, LPIPS), then seconds/image."""
        best = self._best()
        out = [r"\begin{table}[t]", r"\centering"]
        out.append(f"% metrics {describe(self.rule)}")
        out += [f"% [published] {m}: {src}" for m, src in self.published.items()]
        if caption:
            out.append(f"\\caption{{{_tex_escape(caption)} (metrics rule: {self.rule})}}")
        k = len(self.metrics) + 1
        out += [r"\begin{tabular}{l" + ("c" * (k - 1) + "r") * len(self.protocols) + "c}", r"\toprule"]
        groups = " & ".join(f"\\multicolumn{{{k}}}{{c}}{{{_tex_escape(protocol_label(p))}}}"
                            for p in self.protocols)
        out.append(f" & {groups} & \\\\")
        out.append("".join(f"\\cmidrule(lr){{{2 + k * i}-{1 + k * (i + 1)}}}" for i in range(len(self.protocols))))
        out.append("Method & " + " & ".join(c for _ in self.protocols for c in
                                             [*(_tex_escape(METRIC_LABELS[x]) for x in self.metrics), "$n$"])
                   + r" & s/img \\")
        out.append(r"\midrule")
        for m in self.methods:
            cells = []
            for p in self.protocols:
                cells += [self._cell(m, p, k, digits, True, bold_best and self._is_best(best, m, p, k, digits))
                          for k in self.metrics] + [_tex_escape(self._n(m, p))]
            out.append(" & ".join([_tex_escape(self.label(m))] + cells + [self._time(m)]) + r" \\")
        out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
        return "\n".join(out) + "\n"

    def to_csv(self, path: str | Path | None = None) -> str:
        """Wide CSV, full precision: ``method, <protocol>_<metric>_{mean,se}, <protocol>_n, seconds_per_image,
        rule, source`` (``source``: ``measured``, or where a published row's figures come from)."""
        cols = ["method"]
        failed = any(self.failed.values())  # the column only when a relight failed: otherwise unchanged
        for p in self.protocols:
            cols += [f"{p}_{k}_{s}" for k in self.metrics for s in ("mean", "se")] + [f"{p}_n"]
            cols += [f"{p}_failed"] if failed else []
        cols += ["seconds_per_image", "rule", "source"]
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(cols)
        for m in self.methods:
            row: list[str] = [m]
            for p in self.protocols:
                stats = self.cells.get((m, p), {})
                for k in self.metrics:
                    s = stats.get(k, Stat(math.nan, math.nan, 0))
                    row += [_fmt(s.mean), _fmt(s.se)]
                row.append(str(max((s.n for s in stats.values()), default=0)))
                row += [str(self.failed.get((m, p), 0))] if failed else []
            row.append(_fmt(self.seconds[m].mean) if m in self.seconds else "")
            row += [self.rule, self.published.get(m, "measured")]
            w.writerow(row)
        text = buf.getvalue()
        if path is not None:
            write_text_atomic(path, text)
        return text


def _badness(metric: str, mean: float) -> float:
    """Lower is better: the mean, its negative, or its distance from 1 (:data:`BETTER`)."""
    way = BETTER.get(metric, "low")
    return -mean if way == "high" else abs(mean - 1.0) if way == "one" else mean


def _fmt(x: float) -> str:
    return "" if not math.isfinite(x) else repr(float(x))


_TEX = {"\\": r"\textbackslash{}", "_": r"\_", "%": r"\%", "&": r"\&", "#": r"\#", "$": r"\$",
        "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def _tex_escape(s: str) -> str:
    # One pass per character so escapes are never re-escaped.
    return "".join(_TEX.get(c, c) for c in s)


def summarize(records: Sequence[Record], methods: Sequence[str] | None = None,
              metrics: Sequence[str] | None = None) -> Table:
    """Group records by method × protocol and compute mean ± SE of each metric and seconds/image.

    ``methods`` fixes the row order (default: first appearance). Protocols: ``same``,
    ``different``, then others alphabetically. ``metrics``: the columns (default: :data:`METRICS` then the
    :data:`EXTRA_METRICS` the records carry).
    """
    keys: dict[tuple[str, str], list[Record]] = {}
    failed: dict[tuple[str, str], int] = {}
    for r in records:
        keys.setdefault((r.method, r.protocol), [])
        if r.status != "ok":  # failed relights are counted, never averaged
            failed[(r.method, r.protocol)] = failed.get((r.method, r.protocol), 0) + 1
        else:
            keys[(r.method, r.protocol)].append(r)
    seen = list(dict.fromkeys(r.method for r in records))
    order = list(methods) + [m for m in seen if m not in methods] if methods else seen
    protocols = sorted({p for _, p in keys}, key=_protocol_key)
    names = list(metrics) if metrics else [*METRICS, *(k for k in EXTRA_METRICS if k in extra_columns(records))]
    cells = {k: {m: mean_se(r.value(m) for r in rs) for m in names} for k, rs in keys.items()}
    seconds = {m: mean_se(r.seconds for r in records if r.method == m and r.status == "ok") for m in order}
    return Table(order, protocols, cells, seconds, failed, rule=_one_rule(records), metrics=names)


def _one_rule(records: Sequence[Record], where: dict | None = None) -> str:
    """The metric rule shared by ``records``; scores under different rules in one table are an error."""
    rules = sorted({r.rule for r in records})
    if len(rules) > 1:
        by = {}
        for r in records:
            by.setdefault(r.rule, (where or {}).get((r.method, r.protocol, r.record_id), r.method))
        raise TableError("records scored under different metric rules (" + "; ".join(
            f"{k}: e.g. {v}" for k, v in sorted(by.items())) + "); rerun the benchmark with one metrics.rule for "
            "every run (a CSV without a rule column was scored with 'composite'), or make one table per rule")
    return rules[0] if rules else DEFAULT_RULE


def merge_runs(run_dirs: Iterable[str | Path], filename: str = PER_IMAGE_CSV,
               methods: Sequence[str] | None = None, drop_bad_rows: bool = False, *, strata: str | None = None,
               bins: Sequence[float] | None = None, with_records: bool = False,
               labels: Sequence[str] | None = None):
    """Read each run's per-image CSV (:func:`difareli.evaluation.records.read_runs`: checked row by row, two runs
    of one method refused unless ``labels`` name each run dir) and summarise them as one table; ``strata`` breaks it
    down (:func:`difareli.evaluation.paired.stratify`); ``with_records`` returns ``(table, the rows it summarises)``.
    """
    records, dropped, named, where = read_runs(run_dirs, filename, drop_bad_rows, labels)
    _one_rule(records, where)  # names a run dir of each rule
    if strata not in (None, "protocol"):
        records = paired.stratify(records, strata, paired.SHADOW_BINS if bins is None else bins)
    table = summarize(records, methods)
    table.dropped = dropped
    for (m, _, _), csv_path in where.items():
        table.runs.setdefault(m, [])
        if csv_path.parent not in table.runs[m]:
            table.runs[m].append(csv_path.parent)
    if named:
        table.remarks.append("Rows labelled per run dir (label=): " + "; ".join(named) + ".")
    if strata not in (None, "protocol"):
        edges = list(bins) if bins is not None else list(paired.SHADOW_BINS)
        table.remarks.append(f"Broken down by {strata}" + (f" (bins {edges})" if strata == "shadow_share" else "")
                             + ": each protocol column group is one stratum.")
    return (table, records) if with_records else table
