"""Training recipes side by side at equal wall time: score against seconds, from the runs' own metrics.

Each run dir is a `difareli-train` run (a multirun job dir): its `csv/metrics.csv` holds the relight metrics of
every validation (`val/{dssim,mse,lpips}/{same,different}`, `callbacks.relight_metrics`) and `perf/wall_s`, the
wall-clock seconds the run had cost by then (validation, checkpoints and resumed runs included). The label of a
run is its `.hydra/overrides.yaml` minus the overrides all runs share. Prints, per run, the score at the last
validation at or before a common wall time (default: the shortest run's last validation) and writes the curves.

    difareli-train -m experiment=reference_cpu trainer.max_time=00:00:30:00 model.loss.weighting=simple,min_snr
    python scripts/recipe_curves.py 'logs/reference_cpu/multiruns/<time>/*' --out docs/perf/recipes
"""

from __future__ import annotations

import argparse
import csv
import glob
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import yaml  # noqa: E402

METRICS = ("val/dssim/same", "val/dssim/different", "val/mse/same", "val/lpips/same", "val/loss")


def read_run(run: Path) -> list[dict[str, float]]:
    """One row per validation: step, perf/wall_s and the metrics present (validation rows share their step)."""
    rows: dict[int, dict[str, float]] = {}
    with open(run / "csv" / "metrics.csv", newline="") as f:
        for r in csv.DictReader(f):
            for k, v in r.items():
                if v not in ("", None) and (k in METRICS or k == "perf/wall_s"):
                    rows.setdefault(int(r["step"]), {"step": int(r["step"])})[k] = float(v)
    return [r for _, r in sorted(rows.items()) if "perf/wall_s" in r]


def labels(runs: list[Path]) -> list[str]:
    """Each run's overrides that not every run shares (the recipe choices the sweep varied)."""
    over = []
    for run in runs:
        path = run / ".hydra" / "overrides.yaml"
        over.append(yaml.safe_load(path.read_text()) or [] if path.is_file() else [run.name])
    common = set(over[0]).intersection(*map(set, over[1:])) if over else set()
    return [" ".join(o for o in ov if o not in common) or run.name for ov, run in zip(over, runs)]


def at_time(rows: list[dict[str, float]], seconds: float, metric: str) -> tuple[float, float, int] | None:
    """(value, wall seconds, step) of the last validation at or before ``seconds`` that logged ``metric``."""
    best = None
    for r in rows:
        if r["perf/wall_s"] <= seconds + 1e-6 and metric in r:
            best = (r[metric], r["perf/wall_s"], int(r["step"]))
    return best


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="run dirs or glob patterns")
    ap.add_argument("--seconds", type=float, default=None, help="the common wall time (default: shortest run's)")
    ap.add_argument("--out", default="recipe_curves", help="folder for recipe_curves.png and recipe_table.md")
    args = ap.parse_args(argv)
    runs = sorted({Path(p) for pat in args.runs for p in (glob.glob(pat) or [pat])
                   if (Path(p) / "csv" / "metrics.csv").is_file()})
    if not runs:
        raise SystemExit(f"recipe_curves: no run dir with csv/metrics.csv in {args.runs}; give difareli-train run "
                         "dirs (a multirun's job dirs)")
    data = [read_run(r) for r in runs]
    empty = [str(r) for r, d in zip(runs, data) if not d]
    if empty:
        raise SystemExit(f"recipe_curves: {empty[0]} has no validation with perf/wall_s (it ran before the "
                         "Throughput callback logged it, or never validated); rerun it or leave it out")
    names = labels(runs)
    seconds = args.seconds if args.seconds is not None else min(d[-1]["perf/wall_s"] for d in data)
    shown = [m for m in METRICS if any(m in r for d in data for r in d)]
    lines = [f"Score at the last validation within {seconds:.0f} s of wall time (lower is better):", "",
             "| recipe | " + " | ".join(shown) + " | step | wall s |", "|---|" + "---:|" * (len(shown) + 2)]
    for name, d in zip(names, data):
        cells = [at_time(d, seconds, m) for m in shown]
        first = next((c for c in cells if c is not None), None)
        lines.append(f"| {name} | " + " | ".join("-" if c is None else f"{c[0]:.4f}" for c in cells)
                     + (f" | {first[2]} | {first[1]:.0f} |" if first else " | - | - |"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "recipe_table.md").write_text("\n".join(lines) + "\n")
    cols = min(3, len(shown))
    fig, axes = plt.subplots(math.ceil(len(shown) / cols), cols,
                             figsize=(4.5 * cols, 3.4 * math.ceil(len(shown) / cols)), squeeze=False)
    for ax, m in zip(axes.ravel(), shown):
        for name, d in zip(names, data):
            pts = [(r["perf/wall_s"] / 60, r[m]) for r in d if m in r]
            if pts:
                ax.plot(*zip(*pts), marker="o", ms=3, label=name)
        ax.axvline(seconds / 60, color="grey", lw=0.8, ls="--")
        ax.set_xlabel("wall time (min)")
        ax.set_ylabel(m)
    for ax in axes.ravel()[len(shown):]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "recipe_curves.png", dpi=110)
    print("\n".join(lines))
    print(f"\ncurves: {out / 'recipe_curves.png'}")


if __name__ == "__main__":
    main()
