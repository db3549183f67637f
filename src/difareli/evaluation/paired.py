"""Paired comparisons of methods scored on the same pairs, and breakdowns of any table by stratum.

Two methods are compared per (protocol, metric) on the pairs both scored: their per-image rows are joined on
(protocol, record id) (the pair id the benchmark writes), and the table gives the mean paired difference
``B - A`` with a seeded percentile bootstrap 95% CI (``n_boot`` resamples of the pairs) and the two-sided Wilcoxon
signed-rank p-value (``scipy.stats.wilcoxon``; NaN when every difference is 0). A pair where either score is
undefined (a failed relight, a shadow metric with no target shadow) is left out of that metric's n.

Refused, naming the rows: a (method, protocol, record id) that appears twice, and two methods whose pair sets of a
protocol differ or whose runs record stores of different identities (the same record ids in another store are other
images; ``strict``; otherwise those method pairs are skipped and named in a note).

:func:`stratify` relabels each row's protocol ``"<protocol> | <stratum>"`` (the target light's category, a bin of the
target shadow's share of the face), so every table (summary and paired) breaks down by it.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, replace
from typing import Mapping, Sequence

import numpy as np

from difareli.errors import UserError
from difareli.evaluation.records import BETTER, METRIC_LABELS, Record, _protocol_key, protocol_label

#: The strata ``difareli-table strata=`` takes; ``protocol`` is every table's own grouping.
STRATA = ("protocol", "light_category", "shadow_share")
#: Default bin edges of the target shadow's share of the face (the last bin is closed).
SHADOW_BINS = (0.0, 0.05, 0.15, 0.3, 1.0)
N_BOOT = 10_000


@dataclass(frozen=True)
class Comparison:
    """``b`` minus ``a`` on ``n`` shared pairs of ``protocol``: mean difference, bootstrap CI, Wilcoxon p."""

    protocol: str
    metric: str
    a: str
    b: str
    n: int
    mean: float
    lo: float
    hi: float
    p: float


def bootstrap_ci(d: np.ndarray, n_boot: int = N_BOOT, seed: int = 0, level: float = 0.95) -> tuple[float, float]:
    """Percentile bootstrap CI of the mean of ``d`` (resampling its entries with replacement, seeded)."""
    d = np.asarray(d, np.float64)
    if d.size == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    means = np.empty(n_boot)
    step = max(1, 4_000_000 // d.size)  # bounded memory: resample in chunks of ~4M draws
    for i in range(0, n_boot, step):
        k = min(step, n_boot - i)
        means[i:i + k] = d[rng.integers(0, d.size, (k, d.size))].mean(1)
    q = (1 - level) / 2
    return float(np.quantile(means, q)), float(np.quantile(means, 1 - q))


def wilcoxon_p(d: np.ndarray) -> float:
    """Two-sided Wilcoxon signed-rank p-value of the differences ``d`` (NaN when all are 0 or none are given)."""
    from scipy.stats import wilcoxon

    d = np.asarray(d, np.float64)
    if d.size == 0 or not np.any(d != 0):
        return math.nan
    return float(wilcoxon(d).pvalue)


def _index(records: Sequence[Record]) -> dict[tuple[str, str], dict[str, Record]]:
    """(method, protocol) -> record id -> row; a duplicated row is a UserError naming it."""
    out: dict[tuple[str, str], dict[str, Record]] = {}
    for r in records:
        rows = out.setdefault((r.method, r.protocol), {})
        if r.record_id in rows:
            raise UserError(f"paired comparison: {r.method} has two rows for {r.protocol} pair {r.record_id}; "
                            "remove the duplicate (a run listed twice, or a CSV with a repeated row)")
        rows[r.record_id] = r
    return out


def _mismatch(a: str, b: str, p: str, ia: set[str], ib: set[str]) -> str:
    only_a, only_b = sorted(ia - ib), sorted(ib - ia)
    return (f"{a} and {b} were scored on different {p} pairs ({len(only_a)} only in {a}, e.g. {only_a[:3]}; "
            f"{len(only_b)} only in {b}, e.g. {only_b[:3]})")


@dataclass(frozen=True)
class Origin:
    """Where a method's rows were scored: its run dir(s) and the store's identity as the run records it (None: the
    run records none), with the store as a user knows it (its path)."""

    runs: str
    identity: str | None
    store: str


def _other_store(a: str, b: str, oa: Origin, ob: Origin) -> str:
    return (f"{a} (run dir {oa.runs}) was scored on store {oa.store} and {b} (run dir {ob.runs}) on store "
            f"{ob.store}, so their rows of one record id are not the same pair")


def compare(records: Sequence[Record], metrics: Sequence[str], *, n_boot: int = N_BOOT, seed: int = 0,
            strict: bool = True, methods: Sequence[str] | None = None,
            origins: Mapping[str, Origin] | None = None) -> tuple[list[Comparison], list[str]]:
    """Every method pair x protocol x metric scored on the same pairs -> (comparisons, notes on skipped pairs).

    ``strict``: two methods of one protocol with different pair sets, or (``origins``: method -> where it was
    scored) scored on stores of different identities, are a UserError naming them; otherwise they are skipped and
    named in the notes."""
    origins = origins or {}
    index = _index(records)
    order = list(methods or dict.fromkeys(r.method for r in records))
    protocols = sorted({p for _, p in index}, key=_protocol_key)
    out, notes = [], []
    for p in protocols:
        here = [m for m in order if (m, p) in index]
        for i, a in enumerate(here):
            for b in here[i + 1:]:
                ra, rb = index[(a, p)], index[(b, p)]
                oa, ob = origins.get(a), origins.get(b)
                if oa and ob and oa.identity and ob.identity and oa.identity != ob.identity:
                    why = _other_store(a, b, oa, ob)
                    if strict:
                        raise UserError(f"paired comparison: {why}; compare runs benchmarked on one store, or pass "
                                        "paired=auto to skip such pairs of methods")
                    notes.append(f"not compared: {why}")
                    continue
                if set(ra) != set(rb):
                    why = _mismatch(a, b, p, set(ra), set(rb))
                    if strict:
                        raise UserError(f"paired comparison: {why}; benchmark both on the same pairs (same store, "
                                        "protocols and limit), or pass paired=auto to skip such pairs of methods")
                    notes.append(f"not compared: {why}")
                    continue
                for k in metrics:
                    x = np.array([[ra[i].value(k), rb[i].value(k)] for i in sorted(ra)], np.float64).reshape(-1, 2)
                    d = np.diff(x[np.isfinite(x).all(1)], axis=1)[:, 0]
                    if d.size == 0:
                        continue
                    lo, hi = bootstrap_ci(d, n_boot, seed)
                    out.append(Comparison(p, k, a, b, int(d.size), float(d.mean()), lo, hi, wilcoxon_p(d)))
    return out, list(dict.fromkeys(notes))  # a store mismatch is noted once, not once per protocol


def to_markdown(rows: Sequence[Comparison], notes: Sequence[str] = (), n_boot: int = N_BOOT, seed: int = 0) -> str:
    """The comparisons as one Markdown table, with how the CI and p were computed under it and which orderings are
    significant (:func:`significance`)."""
    lines = ["| protocol | metric | A | B | n | mean(B - A) | 95% CI | Wilcoxon p |",
             "|---|---|---|---|---:|---:|---|---:|"]
    for c in rows:
        lines.append(f"| {protocol_label(c.protocol)} | {METRIC_LABELS.get(c.metric, c.metric)} | {c.a} | {c.b} | "
                     f"{c.n} | {c.mean:+.4g} | [{c.lo:+.4g}, {c.hi:+.4g}] | {_p(c.p)} |")
    lines += ["", f"Per-image differences B - A on the pairs both methods scored (joined on protocol and pair id); "
              f"95% CI: percentile bootstrap of the mean, {n_boot} resamples, seed {seed}; p: two-sided Wilcoxon "
              "signed-rank test (n/a when every difference is 0)."]
    lines += ["", significance(rows)] if rows else []
    return "\n".join(lines + list(notes)) + "\n"


def significance(rows: Sequence[Comparison], alpha: float = 0.05) -> str:
    """One sentence, from the numbers: per protocol and metric, which orderings are significant at ``alpha`` (the
    Wilcoxon p below ``alpha`` and the bootstrap CI excluding 0: both tests agree) and which are not."""
    yes, no = {}, {}
    for c in rows:
        where = f"{protocol_label(c.protocol)} {METRIC_LABELS.get(c.metric, c.metric)}"
        ci_clear = c.lo > 0 or c.hi < 0
        if math.isfinite(c.p) and c.p < alpha and ci_clear:
            lo, hi = (c.b, c.a) if c.mean < 0 else (c.a, c.b)  # lo has the lower mean
            way = BETTER.get(c.metric)
            text = (f"{lo} better than {hi}" if way == "low" else f"{hi} better than {lo}" if way == "high"
                    else f"{lo} lower than {hi}")
            yes.setdefault(where, []).append(f"{text} (p={_p(c.p)})")
        else:
            split = " (the CI and p disagree)" if ci_clear or (math.isfinite(c.p) and c.p < alpha) else ""
            no.setdefault(where, []).append(f"{c.a} vs {c.b} (p={_p(c.p)}){split}")

    def listing(groups: dict[str, list[str]]) -> str:
        return "; ".join(f"{k}: {', '.join(v)}" for k, v in groups.items()) or "none"

    # Each test stands alone: with many comparisons some "significant" ones are expected by chance, and says so.
    return (f"At the {alpha:.0%} level (Wilcoxon p < {alpha:g} and the bootstrap 95% CI excluding 0; each of the "
            f"{len(rows)} comparisons on its own, no multiple-comparison correction), significant: {listing(yes)}; "
            f"not significant: {listing(no)}.")


def _p(p: float) -> str:
    return "n/a" if not math.isfinite(p) else f"{p:.3g}"


def to_csv(rows: Sequence[Comparison]) -> str:
    """The comparisons as CSV at full precision."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["protocol", "metric", "a", "b", "n", "mean_b_minus_a", "ci_lo", "ci_hi", "wilcoxon_p"])
    for c in rows:
        w.writerow([c.protocol, c.metric, c.a, c.b, c.n, *(repr(float(x)) for x in (c.mean, c.lo, c.hi, c.p))])
    return buf.getvalue()


def shadow_bin(share: float, bins: Sequence[float] = SHADOW_BINS) -> str:
    """The label ``shadow [lo, hi)`` of the bin holding ``share`` (the last bin is closed)."""
    edges = [float(b) for b in bins]
    for lo, hi in zip(edges[:-1], edges[1:]):
        if lo <= share < hi or (hi == edges[-1] and share == hi):
            return f"shadow [{lo:g}, {hi:g}{']' if hi == edges[-1] else ')'}"
    raise UserError(f"shadow share {share} is outside the bins {edges}; give strata_bins covering [0, 1]")


def stratify(records: Sequence[Record], by: str | None, bins: Sequence[float] = SHADOW_BINS) -> list[Record]:
    """``records`` with each protocol relabelled ``"<protocol> | <stratum>"`` by ``by`` (:data:`STRATA`; None or
    ``protocol``: unchanged). A row without the stratum's column is a UserError naming the run's CSV column."""
    if by in (None, "protocol"):
        return list(records)
    if by not in STRATA:
        raise UserError(f"strata={by}: not one of {', '.join(STRATA)} (null: by protocol only)")
    if list(bins) != sorted(float(b) for b in bins) or len(bins) < 2:
        raise UserError(f"strata_bins={list(bins)}: give increasing bin edges, e.g. {list(SHADOW_BINS)}")
    out = []
    for r in records:
        v = r.info.get(by, "")
        if r.status == "ok" and str(v).strip() == "":
            raise UserError(f"strata={by}: {r.method}'s row {r.protocol} {r.record_id} has no {by} column value; "
                            "rescore or rerun its benchmark with this difareli version (it writes the strata columns)")
        label = shadow_bin(float(v), bins) if by == "shadow_share" and str(v).strip() else f"{by}={v or '?'}"
        out.append(replace(r, protocol=f"{r.protocol} | {label}"))
    return out
