"""Per-image metric records -> mean ± standard error tables in the shape of the paper's Table I.

Per-image CSV (one per run, ``<run_dir>/metrics_per_image.csv``), columns in this order:

    method, protocol, record_id, dssim, mse, lpips, seconds[, rule][, <extra metrics>][, <strata>][, status]

``protocol`` is ``same`` ((i) target light estimated from the same person) or ``different``
((ii) from a different person); other names are allowed and sort after these. ``seconds`` is the
wall time spent relighting that image (empty if unknown). Metric values are those of
:mod:`difareli.evaluation.metrics` (``[0, 1]`` images) under the metric rule in the ``rule`` column (``paper`` or
``composite``, :data:`difareli.evaluation.metrics.RULES`); a CSV without that column predates the rules and was scored
with ``composite``. One table never mixes rules, and every rendering states its rule.

Statistics per (method, protocol) and metric: mean and standard error
``SE = std(ddof=1) / sqrt(n)`` (sample standard deviation; SE is NaN when n < 2). Every rendered table
shows the n each mean is over.

An optional last column ``status`` marks rows whose relight ``failed`` (a non-finite result):
they have no scores, count as failed in the table and never enter a mean. Reading checks every row: a
malformed row (wrong field count, a cut last line), a non-finite or empty metric of a scored row, or a file
with no rows is a :class:`TableError` naming the file and line, or with ``drop_bad_rows`` the row is left out
and the count is shown under the table.

Issue 43 added optional columns, each present only when the run computed it: the metrics of
:data:`EXTRA_METRICS` (identity cosines, lighting error, shadow adherence; empty where undefined, e.g. a target
shadow too small to score: such cells are counted apart, ``(n=k)`` in the table) and the strata of :data:`STRATA`
(the target light's category, the target shadow's share of the face) that ``difareli-table strata=`` groups by.

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

import numpy as np

from difareli.errors import UserError
from difareli.evaluation.metrics import DEFAULT_RULE, RULES, describe

PER_IMAGE_CSV = "metrics_per_image.csv"
COLUMNS = ("method", "protocol", "record_id", "dssim", "mse", "lpips", "seconds")
#: The rule of a per-image CSV without a ``rule`` column: every score before the paper rule became the default was composited.
LEGACY_RULE = "composite"
METRICS = ("dssim", "mse", "lpips")
METRIC_LABELS = {"dssim": "DSSIM", "mse": "MSE", "lpips": "LPIPS"}
#: Optional per-image metrics, in table order: identity cosine of the relit face vs the input and vs the
#: ground truth, the lighting error of the relit image (degrees, relative SH), shadow adherence (ratio, raw, IoU).
EXTRA_METRICS = ("identity_input", "identity_gt", "light_angle", "light_rel_error", "shadow_adherence",
                 "shadow_darkening", "shadow_iou")
METRIC_LABELS.update({"identity_input": "ID vs input", "identity_gt": "ID vs GT", "light_angle": "light angle (deg)",
                      "light_rel_error": "light SH rel. err", "shadow_adherence": "shadow darkening ratio",
                      "shadow_darkening": "shadow darkening", "shadow_iou": "shadow IoU"})
#: Which way is better: "low", "high", "one" (closest to 1); metrics absent here are never marked best.
BETTER = {"dssim": "low", "mse": "low", "lpips": "low", "identity_input": "high", "identity_gt": "high",
          "light_angle": "low", "light_rel_error": "low", "shadow_adherence": "one", "shadow_iou": "high"}
#: Optional per-image strata columns (text): the target light's category, the target shadow's share of the face.
STRATA = ("light_category", "shadow_share")
PROTOCOL_LABELS = {"same": "(i) same subject", "different": "(ii) different subject"}


@dataclass(frozen=True)
class Record:
    """One relit image's scores."""

    method: str
    protocol: str
    record_id: str
    dssim: float
    mse: float
    lpips: float
    seconds: float = math.nan
    status: str = "ok"  # "failed": the relight was invalid (no scores)
    rule: str = DEFAULT_RULE  # the metric rule the scores were computed under (difareli.evaluation.metrics.RULES)
    #: scores of :data:`EXTRA_METRICS` this run computed (NaN: undefined for this pair)
    extra: dict = field(default_factory=dict, hash=False)
    #: values of :data:`STRATA` (text) this run recorded
    info: dict = field(default_factory=dict, hash=False)

    def value(self, metric: str) -> float:
        """The score of ``metric`` (a base one or an extra one; NaN when this row lacks it)."""
        return float(getattr(self, metric)) if metric in METRICS else float(self.extra.get(metric, math.nan))


@dataclass(frozen=True)
class Stat:
    """Mean and standard error of one metric over n finite values."""

    mean: float
    se: float
    n: int


def mean_se(values: Iterable[float]) -> Stat:
    """Mean and SE = sample std (ddof=1) / sqrt(n), over the finite values."""
    v = np.asarray([float(x) for x in values], dtype=np.float64)
    v = v[np.isfinite(v)]
    n = int(v.size)
    if n == 0:
        return Stat(math.nan, math.nan, 0)
    se = float(v.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return Stat(float(v.mean()), se, n)


# ---------------------------------------------------------------------------------------- CSV I/O


class TableError(UserError):
    """A per-image CSV that cannot be summarised honestly (names the file and line)."""


def _num(s: str) -> float:
    return math.nan if s.strip() == "" else float(s)


def _row_problem(row: list[str], header: list[str], last: bool, cut: bool) -> tuple[str, Record | None]:
    """(problem, None) for a bad row, else ("", Record)."""
    if len(row) != len(header):
        why = " (the file ends inside it: cut?)" if last and cut else ""
        return f"{len(row)} fields, the header has {len(header)}{why}", None
    if last and cut:
        return "the file ends inside this row (no line end): cut?", None
    d = dict(zip(header, row))
    status = d.get("status", "ok").strip() or "ok"
    if status not in ("ok", "failed"):
        return f"status {status!r} is neither 'ok' nor 'failed'", None
    rule = d.get("rule", LEGACY_RULE).strip() or LEGACY_RULE
    if rule not in RULES:
        return f"rule {rule!r} is not one of {', '.join(RULES)}", None
    if not all(d[k].strip() for k in ("method", "protocol", "record_id")):
        return "empty method, protocol or record_id", None
    vals = {}
    extra = {}
    for k in (k for k in EXTRA_METRICS if k in d):  # empty: undefined for this pair (counted apart)
        try:
            extra[k] = _num(d[k])
        except ValueError:
            return f"{k}={d[k]!r} is not a number", None
    for k in (*METRICS, "seconds"):
        try:
            vals[k] = _num(d[k])
        except ValueError:
            return f"{k}={d[k]!r} is not a number", None
        if d[k].strip() and not math.isfinite(vals[k]):
            return f"{k}={d[k]!r} is not finite", None
        if k != "seconds" and status == "ok" and not d[k].strip():
            return f"{k} is empty in a scored row", None
    return "", Record(d["method"], d["protocol"], d["record_id"], *(vals[k] for k in (*METRICS, "seconds")),
                      status=status, rule=rule, extra=extra, info={k: d[k] for k in STRATA if k in d})


#: The fix a bad row's message names where the caller has no drop_bad_rows option (difareli-ablate, rescore).
BAD_ROW_FIX = "fix or remove the row, or rerun the benchmark that wrote it"
#: difareli-table's (it has the option).
TABLE_BAD_ROW_FIX = ("fix or remove the row, or pass drop_bad_rows=true to leave bad rows out (the table then "
                     "shows how many)")


def read_records_checked(path: str | Path, drop_bad_rows: bool = False, *,
                         bad_row_fix: str = BAD_ROW_FIX) -> tuple[list[Record], list[str]]:
    """Read a per-image CSV, checking every row; returns (records, "file:line: problem" of dropped rows).

    Without ``drop_bad_rows`` the first bad row (its message ends with ``bad_row_fix``), a file without rows, or
    a file that is not a text CSV raises :class:`TableError`."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            text = f.read()
        rows = list(csv.reader(io.StringIO(text)))
    except (UnicodeDecodeError, csv.Error) as e:
        raise TableError(f"{path}: not a text CSV ({str(e)[:80]}); is it a {PER_IMAGE_CSV} written by "
                         "difareli-benchmark? rerun the benchmark for this run dir or leave it out") from None
    header = rows[0] if rows else []
    missing = set(COLUMNS) - set(header)
    if missing:
        raise TableError(f"{path}: missing columns {sorted(missing)} (header: {header}); is it a "
                         f"{PER_IMAGE_CSV} written by difareli-benchmark?")
    cut = not text.endswith(("\n", "\r"))
    records, dropped = [], []
    for i, row in enumerate(rows[1:], start=2):
        problem, rec = _row_problem(row, header, i == len(rows), cut)
        if rec is not None:
            records.append(rec)
        elif not drop_bad_rows:
            raise TableError(f"{path}:{i}: {problem}; {bad_row_fix}")
        else:
            dropped.append(f"{path}:{i}: {problem}")
    if not records:
        raise TableError(f"{path}: no usable rows ({len(rows) - 1} row(s), {len(dropped)} bad); rerun the "
                         "benchmark for this run dir or leave it out of runs=[...]")
    return records, dropped


def extra_columns(records: Iterable[Record]) -> list[str]:
    """The :data:`EXTRA_METRICS` then :data:`STRATA` columns any of ``records`` carries, in that order."""
    have = set()
    for r in records:
        have |= set(r.extra) | set(r.info)
    return [k for k in (*EXTRA_METRICS, *STRATA) if k in have]


def header(extra: Sequence[str] = (), status: bool = True) -> list[str]:
    """A per-image CSV's header: :data:`COLUMNS`, ``rule``, the ``extra`` columns, (``status``) ``status``."""
    return [*COLUMNS, "rule", *extra] + (["status"] if status else [])


def record_row(r: Record, status: bool = True, extra: Sequence[str] = ()) -> list[str]:
    """One CSV row of ``r``: :data:`COLUMNS`, ``rule``, the ``extra`` columns and (``status``) its status, floats at
    full precision (an undefined extra score is empty)."""
    def num(x):
        return "" if math.isnan(x) else repr(float(x))

    return ([r.method, r.protocol, r.record_id] + [num(x) for x in (r.dssim, r.mse, r.lpips, r.seconds)]
            + [r.rule] + [num(r.value(k)) if k in EXTRA_METRICS else str(r.info.get(k, "")) for k in extra]
            + ([r.status] if status else []))


def write_records(path: str | Path, records: Iterable[Record]) -> Path:
    """Write per-image records to a CSV with :data:`COLUMNS` and ``rule`` (full float precision)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    records = list(records)
    # The status column only when a row failed: runs without failures keep the original format.
    status = any(r.status != "ok" for r in records)
    extra = extra_columns(records)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header(extra, status))
        for r in records:
            w.writerow(record_row(r, status, extra))
    return path


def read_records(path: str | Path) -> list[Record]:
    """Read a per-image CSV, strictly (see :func:`read_records_checked`)."""
    return read_records_checked(path)[0]


# ------------------------------------------------------------------------------------- the table


def _protocol_key(p: str) -> tuple[int, str, str]:
    # A stratified protocol is "<protocol> | <stratum>" (difareli.evaluation.paired.stratify): by protocol first.
    base, _, stratum = p.partition(" | ")
    order = list(PROTOCOL_LABELS)
    return (order.index(base), "", stratum) if base in order else (len(order), base, stratum)


def protocol_label(p: str) -> str:
    """A protocol's printed label (a stratified one keeps its stratum)."""
    base, sep, stratum = p.partition(" | ")
    return PROTOCOL_LABELS.get(base, base) + (f" | {stratum}" if sep else "")


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
        header = ["method"]
        failed = any(self.failed.values())  # the column only when a relight failed: otherwise unchanged
        for p in self.protocols:
            header += [f"{p}_{k}_{s}" for k in self.metrics for s in ("mean", "se")] + [f"{p}_n"]
            header += [f"{p}_failed"] if failed else []
        header += ["seconds_per_image", "rule", "source"]
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(header)
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
            Path(path).write_text(text)
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


def summarize(records: Sequence[Record], methods: Sequence[str] | None = None) -> Table:
    """Group records by method × protocol and compute mean ± SE of each metric and seconds/image.

    ``methods`` fixes the row order (default: first appearance). Protocols: ``same``,
    ``different``, then others alphabetically.
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
    names = [*METRICS, *(k for k in EXTRA_METRICS if k in extra_columns(records))]
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
               bins: Sequence[float] | None = None, with_records: bool = False):
    """Read each run's per-image CSV (checked row by row, see :func:`read_records_checked`) and summarise
    them as one table; ``strata`` breaks it down (:func:`difareli.evaluation.paired.stratify`); ``with_records``
    returns ``(table, the rows it summarises)``.

    The same (method, protocol, record_id) appearing twice (e.g. a run listed twice) is an error:
    it would silently double-count an image.
    """
    records: list[Record] = []
    dropped: list[str] = []
    where: dict[tuple[str, str, str], Path] = {}
    for d in run_dirs:
        path = Path(d) / filename
        if not path.is_file():
            raise FileNotFoundError(f"no {filename} in run dir {d}")
        rows, bad = read_records_checked(path, drop_bad_rows, bad_row_fix=TABLE_BAD_ROW_FIX)
        dropped += bad
        for r in rows:
            key = (r.method, r.protocol, r.record_id)
            if key in where:
                raise TableError(f"duplicate record {key} in {where[key]} and {path}; list each run once and "
                                 "remove repeated rows")
            where[key] = path
            records.append(r)
    _one_rule(records, where)  # names a run dir of each rule
    if strata not in (None, "protocol"):
        from difareli.evaluation import paired

        records = paired.stratify(records, strata, paired.SHADOW_BINS if bins is None else bins)
    table = summarize(records, methods)
    table.dropped = dropped
    if strata not in (None, "protocol"):
        edges = list(bins) if bins is not None else list(paired.SHADOW_BINS)
        table.remarks.append(f"Broken down by {strata}" + (f" (bins {edges})" if strata == "shadow_share" else "")
                             + ": each protocol column group is one stratum.")
    return (table, records) if with_records else table

