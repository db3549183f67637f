"""The reference suite: every shipped model beside identity and the Lambertian ratio image (estimated inputs) on
one SynthFaces store generated with a seed none of them trained on, both protocols, the paper's metric rule, each
model at the defaults a user gets (the default sampler; one pass for a student). Mean ± standard error and s/img.

Writes ``<out>/suite.md`` and ``suite.csv`` and, with ``--ship``, ``src/difareli/checkpoints/suite.md`` (package
data: ``difareli-demo`` prints it). Runs resume: a model's rows already in ``<out>`` with the same settings are
reused (``scripts/release_reference.py --out <out>`` writes the same run folders).

    difareli-synth out_dir=data/unseen_v2_s777 subjects=100 lights=4 resolution=64 seed=777 realism=full \\
        inputs=estimated_light workers=2
    python scripts/reference_suite.py --store data/unseen_v2_s777 --pairs 100 --out runs/suite --ship
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from difareli import tables, zoo
from difareli.diffusion import DEFAULT_SAMPLER, PRESETS
from difareli.fileio import write_text_atomic
from difareli.jobs.compare import compare_to_baselines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", required=True, help="a SynthFaces store of a seed no shipped model trained on")
    ap.add_argument("--store-cmd", default=None, help="the difareli-synth command that made --store (stated)")
    ap.add_argument("--pairs", type=int, default=100, help="pairs per protocol")
    ap.add_argument("--out", required=True, help="folder of the benchmark runs (resumed)")
    ap.add_argument("--models", nargs="*", default=None, help="shipped names (default: all of them)")
    ap.add_argument("--ship", action="store_true", help="also write src/difareli/checkpoints/suite.md")
    a = ap.parse_args()

    start = time.perf_counter()
    sampler = PRESETS[DEFAULT_SAMPLER].to_config()
    runs, names = {}, {}
    for name in a.models or zoo.available():
        comparison = compare_to_baselines(a.store, name, sampler, a.out, pairs=a.pairs, progress=True)
        runs.update(comparison.runs)  # identity and Lambertian are the same runs for every model (resumed)
        names[comparison.facts["model"]] = f"`{name}` ({comparison.facts['sampler']})"
    table = tables.summarize([r for run in runs.values() for r in run.records])
    out = Path(a.out)
    table.to_csv(out / "suite.csv")
    counts = sorted({n for run in runs.values() for n in _pairs(run).values()})
    text = "\n".join([
        f"Reference suite: {' and '.join(map(str, counts))} pairs per protocol of `{a.store}` (a seed no shipped model "
        "trained on), target lights fitted to the target images and c estimated (no oracle inputs), every model at "
        "its defaults. Rows: " + "; ".join(f"`{row}` = {shipped}" for row, shipped in names.items()) + ".", "",
        table.to_markdown(), "",
        "Reproduce:", "", "```bash", *([a.store_cmd] if a.store_cmd else []),
        f"python scripts/reference_suite.py --store {a.store} --pairs {a.pairs} --out <folder>",
        "```", ""])
    write_text_atomic(out / "suite.md", text)
    if a.ship:
        write_text_atomic(zoo.SHIPPED_DIR / "suite.md", text)
    print(text)
    print(f"{time.perf_counter() - start:.0f} s; {out / 'suite.md'}")


def _pairs(run) -> dict[str, int]:
    counts: dict[str, int] = {}
    for r in run.records:
        counts[r.protocol] = counts.get(r.protocol, 0) + 1
    return counts


if __name__ == "__main__":
    main()
