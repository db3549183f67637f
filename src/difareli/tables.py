"""Per-image metric records -> mean ± standard error tables in the shape of the paper's Table I.

Per-image CSV (one per run, ``<run_dir>/metrics_per_image.csv``), columns in this order:

    method, protocol, record_id, dssim, mse, lpips, seconds

``protocol`` is ``same`` ((i) target light estimated from the same person) or ``different``
((ii) from a different person); other names are allowed and sort after these. ``seconds`` is the
wall time spent relighting that image (empty if unknown). Metric values are those of
:mod:`difareli.metrics` (``[0, 1]`` images).

Statistics per (method, protocol) and metric: mean and standard error
``SE = std(ddof=1) / sqrt(n)`` (sample standard deviation; SE is NaN when n < 2). Non-finite values
(e.g. an empty face mask) are left out of that metric's statistics.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

PER_IMAGE_CSV = "metrics_per_image.csv"
COLUMNS = ("method", "protocol", "record_id", "dssim", "mse", "lpips", "seconds")
METRICS = ("dssim", "mse", "lpips")
METRIC_LABELS = {"dssim": "DSSIM", "mse": "MSE", "lpips": "LPIPS"}
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


def _num(s: str) -> float:
    return math.nan if s.strip() == "" else float(s)


def write_records(path: str | Path, records: Iterable[Record]) -> Path:
    """Write per-image records to a CSV with :data:`COLUMNS` (full float precision)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for r in records:
            w.writerow([r.method, r.protocol, r.record_id]
                       + ["" if math.isnan(x) else repr(float(x)) for x in (r.dssim, r.mse, r.lpips, r.seconds)])
    return path


def read_records(path: str | Path) -> list[Record]:
    """Read a per-image CSV; the header must contain all of :data:`COLUMNS`."""
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = set(COLUMNS) - set(reader.fieldnames or ())
        if missing:
            raise ValueError(f"{path}: missing columns {sorted(missing)}")
        return [Record(row["method"], row["protocol"], row["record_id"],
                       *(_num(row[k]) for k in ("dssim", "mse", "lpips", "seconds"))) for row in reader]


# ------------------------------------------------------------------------------------- the table


def _protocol_key(p: str) -> tuple[int, str]:
    order = list(PROTOCOL_LABELS)
    return (order.index(p), "") if p in order else (len(order), p)


@dataclass
class Table:
    """Summary statistics: ``cells[(method, protocol)][metric] -> Stat``; ``seconds[method] -> Stat``."""

    methods: list[str]
    protocols: list[str]
    cells: dict[tuple[str, str], dict[str, Stat]]
    seconds: dict[str, Stat]

    # -- formatting helpers
    def _best(self) -> dict[tuple[str, str], float]:
        """Lowest mean per (protocol, metric): every metric here is lower-is-better."""
        best: dict[tuple[str, str], float] = {}
        for (_, p), stats in self.cells.items():
            for k, s in stats.items():
                if math.isfinite(s.mean):
                    best[(p, k)] = min(best.get((p, k), math.inf), s.mean)
        return best

    def _cell(self, method: str, protocol: str, metric: str, digits: int, latex: bool, bold: bool) -> str:
        s = self.cells.get((method, protocol), {}).get(metric)
        if s is None or s.n == 0:
            return "--" if latex else "–"
        pm = r" \pm " if latex else " ± "
        se = f"{s.se:.{digits}f}" if math.isfinite(s.se) else "n/a"
        body = f"{s.mean:.{digits}f}{pm}{se}"
        if latex:
            return f"$\\mathbf{{{s.mean:.{digits}f}}}{pm}{se}$" if bold else f"${body}$"
        return f"**{body}**" if bold else body

    def _time(self, method: str) -> str:
        # 3 significant digits: spans 0.07 s (DiFaReli++) to minutes (DiFaReli) without zeros.
        s = self.seconds.get(method)
        return f"{s.mean:.3g}" if s is not None and s.n else "–"

    def _is_best(self, best, method, protocol, metric, digits) -> bool:
        s = self.cells.get((method, protocol), {}).get(metric)
        b = best.get((protocol, metric))
        # Compare at the printed precision so ties print bold together.
        return s is not None and b is not None and s.n > 0 and round(s.mean, digits) == round(b, digits)

    # -- renderers
    def to_markdown(self, digits: int = 4, bold_best: bool = True) -> str:
        """GitHub Markdown: one row per method, columns ``<protocol> <metric>`` then ``s/img``."""
        best = self._best()
        head = ["Method"] + [f"{PROTOCOL_LABELS.get(p, p)} {METRIC_LABELS[k]}"
                             for p in self.protocols for k in METRICS] + ["s/img"]
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" + "---:|" * (len(head) - 1)]
        for m in self.methods:
            row = [m] + [self._cell(m, p, k, digits, False, bold_best and self._is_best(best, m, p, k, digits))
                         for p in self.protocols for k in METRICS] + [self._time(m)]
            lines.append("| " + " | ".join(row) + " |")
        return "\n".join(lines) + "\n"

    def to_latex(self, digits: int = 4, bold_best: bool = True, caption: str | None = None) -> str:
        """Booktabs table: a column group per protocol (DSSIM, MSE, LPIPS), then seconds/image."""
        best = self._best()
        out = [r"\begin{table}[t]", r"\centering"]
        if caption:
            out.append(f"\\caption{{{_tex_escape(caption)}}}")
        out += [r"\begin{tabular}{l" + "ccc" * len(self.protocols) + "c}", r"\toprule"]
        groups = " & ".join(f"\\multicolumn{{3}}{{c}}{{{_tex_escape(PROTOCOL_LABELS.get(p, p))}}}"
                            for p in self.protocols)
        out.append(f" & {groups} & \\\\")
        out.append("".join(f"\\cmidrule(lr){{{2 + 3 * i}-{4 + 3 * i}}}" for i in range(len(self.protocols))))
        out.append("Method & " + " & ".join(METRIC_LABELS[k] for _ in self.protocols for k in METRICS)
                   + r" & s/img \\")
        out.append(r"\midrule")
        for m in self.methods:
            cells = [self._cell(m, p, k, digits, True, bold_best and self._is_best(best, m, p, k, digits))
                     for p in self.protocols for k in METRICS]
            out.append(" & ".join([_tex_escape(m)] + cells + [self._time(m)]) + r" \\")
        out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
        return "\n".join(out) + "\n"

    def to_csv(self, path: str | Path | None = None) -> str:
        """Wide CSV, full precision: ``method, <protocol>_<metric>_{mean,se}, <protocol>_n, seconds_per_image``."""
        header = ["method"]
        for p in self.protocols:
            header += [f"{p}_{k}_{s}" for k in METRICS for s in ("mean", "se")] + [f"{p}_n"]
        header.append("seconds_per_image")
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(header)
        for m in self.methods:
            row: list[str] = [m]
            for p in self.protocols:
                stats = self.cells.get((m, p), {})
                for k in METRICS:
                    s = stats.get(k, Stat(math.nan, math.nan, 0))
                    row += [_fmt(s.mean), _fmt(s.se)]
                row.append(str(max((s.n for s in stats.values()), default=0)))
            row.append(_fmt(self.seconds[m].mean) if m in self.seconds else "")
            w.writerow(row)
        text = buf.getvalue()
        if path is not None:
            Path(path).write_text(text)
        return text


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
    for r in records:
        keys.setdefault((r.method, r.protocol), []).append(r)
    seen = list(dict.fromkeys(r.method for r in records))
    order = list(methods) + [m for m in seen if m not in methods] if methods else seen
    protocols = sorted({p for _, p in keys}, key=_protocol_key)
    cells = {k: {m: mean_se(getattr(r, m) for r in rs) for m in METRICS} for k, rs in keys.items()}
    seconds = {m: mean_se(r.seconds for r in records if r.method == m) for m in order}
    return Table(order, protocols, cells, seconds)


def merge_runs(run_dirs: Iterable[str | Path], filename: str = PER_IMAGE_CSV,
               methods: Sequence[str] | None = None) -> Table:
    """Read each run's per-image CSV and summarise them as one table.

    The same (method, protocol, record_id) appearing twice (e.g. a run listed twice) is an error:
    it would silently double-count an image.
    """
    records: list[Record] = []
    where: dict[tuple[str, str, str], Path] = {}
    for d in run_dirs:
        path = Path(d) / filename
        if not path.is_file():
            raise FileNotFoundError(f"no {filename} in run dir {d}")
        for r in read_records(path):
            key = (r.method, r.protocol, r.record_id)
            if key in where:
                raise ValueError(f"duplicate record {key} in {where[key]} and {path}")
            where[key] = path
            records.append(r)
    return summarize(records, methods)

