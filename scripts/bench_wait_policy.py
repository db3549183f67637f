"""One-pass relights under each OpenMP wait policy, alone and two jobs side by side (docs/scaling_out.md).

Each job is a fresh process (the policy is read when torch loads) that times ``--relights`` relights of the student
on the first test record of ``--store`` (all torch threads, the runtime's defaults) and prints its median. Per
policy: one job alone, then two at once (what a second command beside a first one meets).

    python scripts/bench_wait_policy.py --store data/test_est_s1011 --relights 150
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

POLICIES = {"passive": {"OMP_WAIT_POLICY": "PASSIVE"}, "libgomp's own": {}}


def job(checkpoint: str, store: str, relights: int) -> None:
    """The timed relights of one process; prints the median milliseconds."""
    from difareli.data.store import EncodingStore
    from difareli.perf import samplers as speed
    from difareli.perf.measure import time_calls
    from difareli.relight.relighter import Relighter
    from difareli.runtime.core import Runtime

    runtime = Runtime()
    relighter = Relighter(checkpoint, runtime=runtime)
    case = speed.store_cases(EncodingStore.open(store), relighter, limit=1)[0]
    timings = time_calls(lambda: speed.timed_relight(relighter.model, case, None, runtime), relights, warmup=5,
                         runtime=runtime)
    print(f"{1e3 * timings.median:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="difareli_pp_ss-synth64", help="a one-pass student")
    ap.add_argument("--store", default="data/test_est_s1011")
    ap.add_argument("--relights", type=int, default=150)
    ap.add_argument("--job", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.job:
        return job(a.checkpoint, a.store, a.relights)
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    cmd = [sys.executable, __file__, "--job", "--checkpoint", a.checkpoint, "--store", a.store,
           "--relights", str(a.relights)]
    print("| policy | jobs at once | median ms per relight (each job) |\n|---|---:|---|")
    for name, env in POLICIES.items():
        for n in (1, 2):
            procs = [subprocess.Popen(cmd, env={**base, **env}, stdout=subprocess.PIPE, text=True) for _ in range(n)]
            outs = [p.communicate()[0].strip().splitlines()[-1] for p in procs]
            print(f"| {name} | {n} | {', '.join(outs)} |", flush=True)


if __name__ == "__main__":
    main()
