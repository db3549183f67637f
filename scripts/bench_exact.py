"""Print every sampler's exact error and empirical order, in both directions, on the Gaussian ODE (SPEC 10).

The data are per-dimension Gaussians, whose probability-flow ODE has a closed-form solution
(``difareli.diffusion.exact``): feeding the optimal eps to a sampler measures its discretisation error alone.
Rows: relative L2 error per step count for generation (x_{T-1} -> x_0), inversion (x_0 -> x_{T-1}) and the
invert-then-generate round trip; the last column is the order fitted on ``--fit`` step counts.

    python scripts/bench_exact.py                       # uniform grid, clean ends, float64
    python scripts/bench_exact.py --grid logsnr --end t0 --samplers ddim unipc paper
"""

from __future__ import annotations

import argparse
import time

import torch

from difareli.diffusion.exact import DEFAULT_NS, SAMPLER_CONFIGS, format_table, gaussian_ode_errors
from difareli.diffusion.schedule import GRID_KINDS
from difareli.diffusion.spec import PRESETS


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samplers", nargs="+", default=list(SAMPLER_CONFIGS), choices=list(PRESETS),
                   help="presets (difareli.diffusion.spec.PRESETS); steps, grid and clipping are this table's")
    p.add_argument("--ns", nargs="+", type=int, default=list(DEFAULT_NS), help="step counts")
    p.add_argument("--fit", nargs="+", type=int, default=[50, 100, 200],
                   help="step counts the order is fitted on (asymptotic range, before float64 round-off)")
    p.add_argument("--grid", default="uniform", choices=GRID_KINDS)
    p.add_argument("--end", default="clean", choices=("clean", "t0"), help="grid end: clean data (t=-1) or t=0")
    p.add_argument("--dtype", default="float64", choices=("float64", "float32"))
    p.add_argument("--dim", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    start = time.perf_counter()
    result = gaussian_ode_errors(args.samplers, args.ns, grid=args.grid, end=args.end, dim=args.dim,
                                 seed=args.seed, dtype=getattr(torch, args.dtype))
    print(f"Gaussian ODE, relative L2 error vs the exact flow ({args.grid} grid, {args.end} end, {args.dtype}, "
          f"dim {args.dim}); order fitted on n = {args.fit}")
    print(format_table(result, fit_ns=args.fit))
    print(f"({time.perf_counter() - start:.1f} s)")


if __name__ == "__main__":
    main()
