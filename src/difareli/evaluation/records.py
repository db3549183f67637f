"""Per-image metric records and their CSV (one per run, ``<run_dir>/metrics_per_image.csv``), columns in this order:

    method, protocol, record_id, dssim, mse, lpips, seconds[, rule][, <extra metrics>][, <strata>][, status]

``protocol`` is ``same`` ((i) target light estimated from the same person) or ``different``
((ii) from a different person); other names are allowed and sort after these. ``seconds`` is the
wall time spent relighting that image (empty if unknown). Metric values are those of
:mod:`difareli.evaluation.metrics` (``[0, 1]`` images) under the metric rule in the ``rule`` column (``paper`` or
``composite``, :data:`difareli.evaluation.metrics.RULES`); a CSV without that column predates the rules and was scored
with ``composite``.

An optional last column ``status`` marks rows whose relight ``failed`` (a non-finite result): they have no scores.
Reading checks every row: a malformed row (wrong field count, a cut last line), a non-finite or empty metric of a
scored row, or a file with no rows is a :class:`TableError` naming the file and line, or with ``drop_bad_rows`` the
row is left out and named.

Optional columns, each present only when the run computed it: the metrics of
:data:`EXTRA_METRICS` (identity cosines, lighting error, shadow adherence; empty where undefined, e.g. a target
shadow too small to score) and the strata of :data:`STRATA` (the target light's category, the target shadow's share
of the face). Mean ± SE tables of these records: :mod:`difareli.evaluation.tables` (which re-exports every name here).
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from difareli.data import shard as sharding
from difareli.errors import UserError, UserFileNotFoundError
from difareli.evaluation.metrics import DEFAULT_RULE, RULES
from difareli.utils.fileio import atomic_path

PER_IMAGE_CSV = "metrics_per_image.csv"
COLUMNS = ("method", "protocol", "record_id", "dssim", "mse", "lpips", "seconds")
#: The rule of a per-image CSV without a ``rule`` column: every score before the paper rule became the default was
#: composited.
LEGACY_RULE = "composite"
METRICS = ("dssim", "mse", "lpips")
METRIC_LABELS = {"dssim": "DSSIM", "mse": "MSE", "lpips": "LPIPS"}
#: Optional per-image metrics, in table order: identity cosine of the relit face vs the input and vs the
#: ground truth, the lighting error of the relit image (degrees, relative SH), shadow adherence (ratio, raw, IoU).
EXTRA_METRICS = ("identity_input", "identity_gt", "light_angle", "light_rel_error", "light_angle_gt",
                 "shadow_adherence", "shadow_darkening", "shadow_iou")
METRIC_LABELS.update({"identity_input": "ID vs input", "identity_gt": "ID vs GT", "light_angle": "light angle (deg)",
                      "light_rel_error": "light SH rel. err", "light_angle_gt": "light angle vs GT (deg)",
                      "shadow_adherence": "shadow darkening ratio",
                      "shadow_darkening": "shadow darkening", "shadow_iou": "shadow IoU"})
#: Which way is better: "low", "high", "one" (closest to 1); metrics absent here are never marked best.
BETTER = {"dssim": "low", "mse": "low", "lpips": "low", "identity_input": "high", "identity_gt": "high",
          "light_angle": "low", "light_rel_error": "low", "light_angle_gt": "low", "shadow_adherence": "one",
          "shadow_iou": "high"}
#: Optional per-image strata columns (text): the target light's category, the target shadow's share of the face.
STRATA = ("light_category", "shadow_share")


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
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header(extra, status))
        for r in records:
            w.writerow(record_row(r, status, extra))
    return path


def read_records(path: str | Path) -> list[Record]:
    """Read a per-image CSV, strictly (see :func:`read_records_checked`)."""
    return read_records_checked(path)[0]


# ------------------------------------------------------------------------------------- run dirs


def _run_of(run_dir: Path) -> str:
    """Which run a run dir belongs to: the sharded job it is a shard of (its shard marker), else the dir itself."""
    marker = run_dir / sharding.MARKER
    if marker.is_file():
        try:
            return "shard job " + json.dumps(json.loads(marker.read_text())["job"], sort_keys=True)
        except (ValueError, KeyError, TypeError):
            pass  # an unreadable marker: the dir is a run of its own (difareli-table's shard check names it)
    return str(run_dir)


def _check_labels(dirs: list[Path], runs: list[str], labels: Sequence[str], by_dir: dict[Path, list[Record]]) -> None:
    """One label per run dir, unique across runs (the shards of one job share one), each run dir of one method."""
    labels = [str(x) for x in labels]
    if len(labels) != len(dirs):
        raise TableError(f"label={labels}: {len(labels)} label(s) for {len(dirs)} run dir(s) ("
                         + ", ".join(map(str, dirs)) + "); give one label per run dir, in the order of runs=")
    if any(not x.strip() for x in labels):
        raise TableError(f"label={labels}: an empty label; give each run dir a name, e.g. label=[pp_604,pp_8212]")
    run_of_label: dict[str, str] = {}
    label_of_run: dict[str, str] = {}
    for d, run, lab in zip(dirs, runs, labels):
        if run_of_label.setdefault(lab, run) != run:
            raise TableError(f"label={labels}: {lab!r} is given to two runs; give each run dir its own label")
        if label_of_run.setdefault(run, lab) != lab:
            raise TableError(f"label={labels}: run dir {d} is a shard of the same job as one labelled "
                             f"{label_of_run[run]!r}; give every shard of one job the same label")
        methods = sorted({r.method for r in by_dir[d]})
        if len(methods) > 1:
            raise TableError(f"label=: run dir {d} holds {len(methods)} methods {methods}, and a label names one; "
                             "leave label= out or split that run's rows into one run dir per method")


def _check_collisions(dirs: list[Path], runs: list[str], by_dir: dict[Path, list[Record]]) -> None:
    """Two runs holding one method in one protocol would merge into one row: refused, pointing to ``label=``."""
    first: dict[tuple[str, str], tuple[str, Path]] = {}
    for d, run in zip(dirs, runs):
        for m, p in dict.fromkeys((r.method, r.protocol) for r in by_dir[d]):
            run0, d0 = first.setdefault((m, p), (run, d))
            if run0 != run:
                example = ",".join(x.name or str(x) for x in dirs)
                raise TableError(f"run dirs {d0} and {d} both hold method {m} ({p}), which would merge into one row; "
                                 f"use label= to name each run dir (one label per run dir, in order, e.g. "
                                 f"label=[{example}])")


def read_runs(run_dirs: Iterable[str | Path], filename: str = PER_IMAGE_CSV, drop_bad_rows: bool = False,
              labels: Sequence[str] | None = None):
    """The rows of several run dirs' per-image CSVs -> ``(records, dropped rows, label notes, where)``
    (``where``: (method, protocol, record_id) -> its CSV).

    ``labels`` (one per run dir, unique; the shards of one sharded job share one) replace the method name of that
    run dir's rows, so two runs of one method (two checkpoints, two step counts) stay two rows. Refused: a run dir
    listed twice, one method in one protocol from two runs without labels (other than the shards of one job: they
    would merge into one row), and the same (method, protocol, record_id) twice (it would double-count an image).
    """
    dirs = [Path(d) for d in run_dirs]
    resolved = [d.resolve() for d in dirs]
    twice = sorted({str(d) for d, r in zip(dirs, resolved) if resolved.count(r) > 1})
    if twice:
        raise TableError(f"duplicate run dir(s) {twice} in runs=: list each run once")
    by_dir: dict[Path, list[Record]] = {}
    dropped: list[str] = []
    for d in dirs:
        path = d / filename
        if not path.is_file():
            raise UserFileNotFoundError(f"no {filename} in run dir {d}")
        by_dir[d], bad = read_records_checked(path, drop_bad_rows, bad_row_fix=TABLE_BAD_ROW_FIX)
        dropped += bad
    runs = [_run_of(d) for d in dirs]
    named: list[str] = []
    if labels is not None:
        _check_labels(dirs, runs, labels, by_dir)
        for d, lab in zip(dirs, map(str, labels)):
            named.append(f"{lab} = {by_dir[d][0].method} ({d})")
            by_dir[d] = [replace(r, method=lab) for r in by_dir[d]]
    _check_collisions(dirs, runs, by_dir)
    records: list[Record] = []
    where: dict[tuple[str, str, str], Path] = {}
    for d in dirs:
        for r in by_dir[d]:
            key = (r.method, r.protocol, r.record_id)
            if key in where:
                raise TableError(f"duplicate record {key} in {where[key]} and {d / filename}; list each run once "
                                 "and remove repeated rows")
            where[key] = d / filename
            records.append(r)
    return records, dropped, named, where


PROTOCOL_LABELS = {"same": "(i) same subject", "different": "(ii) different subject"}


def _protocol_key(p: str) -> tuple[int, str, str]:
    # A stratified protocol is "<protocol> | <stratum>" (difareli.evaluation.paired.stratify): by protocol first.
    base, _, stratum = p.partition(" | ")
    order = list(PROTOCOL_LABELS)
    return (order.index(base), "", stratum) if base in order else (len(order), base, stratum)


def protocol_label(p: str) -> str:
    """A protocol's printed label (a stratified one keeps its stratum, after a comma: a pipe would split a Markdown
    table's cell)."""
    base, sep, stratum = p.partition(" | ")
    return PROTOCOL_LABELS.get(base, base) + (f", {stratum}" if sep else "")
