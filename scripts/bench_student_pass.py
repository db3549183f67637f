"""One student pass against one teacher pass, interleaved in one process (issue 63).

Loads a teacher and its one-pass student, prepares one store case for each (the same record and target, as
``difareli-bench-samplers`` does), then times, round after round in turn:

- ``teacher``: one network pass of the teacher at batch 1 through ``Runtime.denoiser`` (what each of a sampler's
  steps costs, without the sampler's arithmetic);
- ``student``: the student's whole relight through ``relight.core.relight`` (its Modulator and UNet, as shipped);
- ``student_autocast_mod``: the same relight with the Modulator run as it was before issue 63 (plain autocast on
  the original network, contiguous inputs; the UNet still on the inference copy);
- ``modulator``: the student's Modulator alone, on the inference copy;
- ``teacher_gn_mixed``, ``student_gn_mixed``: the teacher's pass and the student's relight with GroupNorm32 as it
  was before issue 63 (PyTorch's mixed bf16 kernel on channels-last input too);
- ``teacher_k_each_step``: the teacher's pass with AdaGN's ``k = MLP3(nonspatial)`` run again at every pass, as
  before a prepared condition kept them (``nn.reuse.ReusedVector``; the timed ``teacher`` reuses them).

Only ratios of one run compare on a loaded machine; the medians and minima of every entry are printed, then the
per-op self CPU time of the teacher's and the student's pass (``--profile``, torch.profiler, interleaved).

    nice -n 19 env OMP_NUM_THREADS=1 .venv/bin/python scripts/bench_student_pass.py --rounds 60 --profile 20
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import time
from unittest import mock

import numpy as np
import torch
import torch.nn.functional as F

from difareli.data.store import EncodingStore
from difareli.nn import reuse
from difareli.nn.unet import GroupNorm32
from difareli.perf import samplers as speed
from difareli.relight.core import _condition, relight
from difareli.relight.relighter import Relighter
from difareli.runtime.core import Runtime


def _passes(teacher: Relighter, student: Relighter, store: EncodingStore, runtime: Runtime) -> dict:
    """The timed callables, each one pass at batch 1 on the first test record of ``store``."""
    tc = speed.store_cases(store, teacher, limit=1)[0]
    sc = speed.store_cases(store, student, records=[tc.record], limit=None)[0]
    tm, sm = teacher.model, student.model
    den = runtime.denoiser(tm.net, _condition(tm, tc.source, runtime))
    t = torch.full((1,), tm.schedule.T // 2, dtype=torch.long)
    (s_sp, s_ns), (t_sp, t_ns) = sm.condition(*sc.source), sm.condition(*sc.target_cond)
    sp, ns = torch.cat([s_sp, t_sp[:, sm._sp_dep]], 1), torch.cat([s_ns, t_ns[:, sm._ns_dep]], 1)
    ts = torch.full((1,), sm.hparams.timestep, dtype=torch.long)

    def old_student():  # before issue 63: the Modulator under plain autocast on the original network
        with runtime.autocast():
            cond = sm.net.condition(sp, ns)
        return sc.x0 + runtime.denoiser(sm.net, cond)(sc.x0, ts)

    fns = {"teacher": lambda: den(tc.x0, t),
           "student": lambda: relight(sm, sc.x0, sc.source, sc.target_cond, runtime=runtime),
           "student_autocast_mod": old_student,
           "modulator": lambda: runtime.condition(sm.net, sp, ns)}
    return {**fns, "teacher_gn_mixed": _with_gn_mixed(fns["teacher"]),
            "student_gn_mixed": _with_gn_mixed(fns["student"]), "teacher_k_each_step": _k_each_step(fns["teacher"])}


def _k_each_step(fn):
    def run():
        with mock.patch.object(reuse, "allowed", lambda: False):
            return fn()
    return run


@contextlib.contextmanager
def _gn_mixed():
    """GroupNorm32 as before issue 63: the mixed bf16 kernel for every bf16 CPU input, channels-last too."""
    new = GroupNorm32.forward

    def old(self, x):
        if x.dtype == torch.bfloat16 and x.device.type == "cpu" and self.weight.dtype == torch.float32:
            return F.group_norm(x, self.num_groups, self.weight, self.bias, self.eps)
        return new(self, x)

    GroupNorm32.forward = old
    try:
        yield
    finally:
        GroupNorm32.forward = new


def _with_gn_mixed(fn):
    def run():
        with _gn_mixed():
            return fn()
    return run


def _timed(fns: dict, rounds: int) -> dict[str, list[float]]:
    secs: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(rounds):
        for k, f in fns.items():
            tick = time.perf_counter()
            f()
            secs[k].append(time.perf_counter() - tick)
    return secs


def _profiled(fns: dict, rounds: int, top: int = 12) -> None:
    """Per-op self CPU time (ms per pass) of the teacher's and the student's pass, profiled in turn."""
    from torch.profiler import profile

    acc = {k: collections.Counter() for k in ("teacher", "student")}
    calls = {k: collections.Counter() for k in acc}
    for _ in range(rounds):
        for k in acc:
            with profile() as prof:
                fns[k]()
            for e in prof.key_averages():
                acc[k][e.key] += e.self_cpu_time_total / 1e3 / rounds
                calls[k][e.key] += e.count
    for k, ops in acc.items():
        print(f"{k}: {sum(ops.values()):.2f} ms self CPU per pass under the profiler")
        for name, ms in ops.most_common(top):
            print(f"  {name:32s} {ms:7.3f} ms  {calls[k][name] // rounds:4d} calls")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--teacher", default="difareli_pp-synth64")
    ap.add_argument("--student", default="difareli_pp_ss-synth64")
    ap.add_argument("--store", default="data/test_est_s1011")
    ap.add_argument("--rounds", type=int, default=60)
    ap.add_argument("--profile", type=int, default=0, help="profiled rounds (0: none)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    runtime = Runtime()
    store = EncodingStore.open(args.store)
    fns = _passes(Relighter(args.teacher, runtime=runtime), Relighter(args.student, runtime=runtime), store, runtime)
    with torch.no_grad():
        _timed(fns, 3)  # warm-up: inference copies, oneDNN primitives
        secs = _timed(fns, args.rounds)
        print(f"{runtime.mode()}, {runtime.memory_format}, {args.threads} thread(s), {args.rounds} interleaved rounds")
        med = {k: float(np.median(v)) for k, v in secs.items()}
        for k, v in secs.items():
            print(f"  {k:22s} median {med[k] * 1e3:7.2f} ms  min {min(v) * 1e3:7.2f} ms")
        # Per-round ratios: the passes of one round ran within milliseconds of each other, under the same load.
        for a, b in (("student", "teacher"), ("student_autocast_mod", "teacher"), ("student_autocast_mod", "student"),
                     ("student_gn_mixed", "teacher_gn_mixed"), ("teacher_gn_mixed", "teacher"),
                     ("student_gn_mixed", "student"), ("teacher_k_each_step", "teacher")):
            paired = np.median(np.array(secs[a]) / np.array(secs[b]))
            print(f"  {a} / {b}: medians {med[a] / med[b]:.3f}, minima {min(secs[a]) / min(secs[b]):.3f}, "
                  f"median of per-round ratios {paired:.3f}")
        if args.profile:
            _profiled(fns, args.profile)


if __name__ == "__main__":
    main()
