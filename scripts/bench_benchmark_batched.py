"""difareli-benchmark's seconds per pair, batched relights against pair by pair, interleaved in one process (issue 63).

One model method at the benchmark's defaults (the default sampler, runtime and batch size, torch's threads as
``num_threads`` gives, or ``--threads``), run through :func:`difareli.evaluation.benchmark.run_benchmark` in turns:
``batched`` (the method as shipped: ``relight_many``, :mod:`difareli.evaluation.batched`) and ``one_by_one`` (the
same method behind a wrapper without ``relight_many``: each pair through ``Relighter.relight``, a source's inversion
cached for its other pairs, as before). The relighter's caches are emptied before every run. Prints per run the wall
seconds per pair (relight, scoring and writing) and the rows' relight seconds per pair, then the medians and their
ratio.

    nice -n 19 env OMP_NUM_THREADS=1 .venv/bin/python scripts/bench_benchmark_batched.py --limit 12 --rounds 2
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from difareli.data.store import EncodingStore
from difareli.diffusion.spec import DEFAULT_SAMPLER, PRESETS
from difareli.evaluation.baselines import DiffusionMethod
from difareli.evaluation.benchmark import run_benchmark
from difareli.utils.processes import openmp_wait_policy

BOTH = ["same_subject", "different_subject"]


class OneByOne:
    """The method without ``relight_many``: the benchmark relights it pair by pair."""

    needs_light, needs_light_fit = True, False

    def __init__(self, method: DiffusionMethod):
        self.method, self.name, self.relighter = method, method.name, method.relighter

    def check_store(self, store) -> None:
        self.method.check_store(store)

    def relight(self, *args, **kwargs):
        return self.method.relight(*args, **kwargs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="difareli_pp-synth64")
    ap.add_argument("--store", default="data/test_est_s1011")
    ap.add_argument("--limit", type=int, default=None, help="pairs per protocol (default: all)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=None,
                    help="torch CPU threads (default: torch's, as conf/benchmark.yaml's num_threads)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    method = DiffusionMethod(args.checkpoint, PRESETS[DEFAULT_SAMPLER].to_config())
    store = EncodingStore.open(args.store)
    print(f"{method.name}, {method.relighter.describe()}, batch_size {method.batch_size}, store {args.store}, "
          f"limit {args.limit}, {torch.get_num_threads()} thread(s), OMP_WAIT_POLICY {openmp_wait_policy()}")
    wall: dict[str, list[float]] = {"batched": [], "one_by_one": []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for name, m in (("batched", method), ("one_by_one", OneByOne(method))):
                method.relighter._inversions.clear()
                method.relighter._suns.clear()
                start = time.perf_counter()
                res = run_benchmark(store, m, BOTH, Path(tmp) / f"{name}{r}", limit=args.limit, progress=False,
                                    save_images=False)
                n = len(res.records)
                wall[name].append((time.perf_counter() - start) / n)
                relight = float(np.mean([x.seconds for x in res.records]))
                print(f"round {r} {name:10s}: {n} pairs, {wall[name][-1]:.3f} s/pair wall, {relight:.3f} s/pair "
                      f"relight (rows' seconds)", flush=True)
    med = {k: float(np.median(v)) for k, v in wall.items()}
    print(f"median wall s/pair: batched {med['batched']:.3f}, one by one {med['one_by_one']:.3f}, "
          f"speed-up {med['one_by_one'] / med['batched']:.2f}x")


if __name__ == "__main__":
    main()
