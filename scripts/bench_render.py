"""Benchmark the ray-cast renderer: ms per G-buffer, shadow pass and shading at a given resolution.

The mesh is a bumpy sphere (~10k triangles, non-convex so shadow rays do real work) plus a floating box
occluder and a backdrop plane, in camera space. Prints the median wall and CPU time of ``--repeats`` runs of each
stage after one warm-up (:func:`difareli.perf.measure.time_calls`; CPU time is the steadier figure on a shared machine)
and the ray backend (embree or pure Python), then a per-record estimate for SynthFaces-sized renders
(``--record-res``, one scene build, one G-buffer, ``--shadows`` shadow passes, one shading reference).

    python scripts/bench_render.py --res 256 --repeats 10
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import trimesh

from difareli.perf.measure import time_calls
from difareli.render import OrthoCamera, Scene, cast_shadow, cast_shadows, render_gbuffer, shading_reference


def bench_mesh(rings: int = 50) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Bumpy unit sphere (~2 * rings * (rings + 1) triangles) + a box in front + a backdrop, with labels."""
    head = trimesh.creation.uv_sphere(radius=1.0, count=[rings, rings + 1])
    v = head.vertices
    theta = np.arccos(np.clip(v[:, 2] / np.linalg.norm(v, axis=1), -1, 1))
    phi = np.arctan2(v[:, 1], v[:, 0])
    head.vertices = v * (1.0 + 0.06 * np.sin(5 * theta) * np.sin(4 * phi))[:, None]
    box = trimesh.creation.box(bounds=[[-0.3, 0.5, 1.2], [0.4, 0.8, 1.4]])
    back = trimesh.Trimesh(
        [[-3.0, -3.1, -1.5], [3.1, -3.0, -1.5], [3.0, 3.1, -1.5], [-3.1, 3.0, -1.5]], [[0, 1, 2], [0, 2, 3]]
    )
    mesh = trimesh.util.concatenate([head, box, back])
    labels = np.r_[np.full(len(head.faces), 1), np.full(len(box.faces), 13), np.zeros(2, int)]
    return mesh, labels


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--res", type=int, default=256, help="image size (square)")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--record-res", type=int, default=64, help="resolution of the per-record estimate")
    parser.add_argument("--shadows", type=int, default=4, help="shadow passes per record")
    parser.add_argument("--backend", default="auto", choices=["auto", "embree", "python"])
    args = parser.parse_args()

    mesh, labels = bench_mesh()

    def ms(fn) -> str:
        return time_calls(fn, args.repeats).median_ms()

    build = ms(lambda: Scene(mesh.copy(), labels, backend=args.backend))
    scene = Scene(mesh, labels, backend=args.backend)
    cam = OrthoCamera(0.7, 0.0, 0.0)
    light = np.zeros((9, 3), np.float32)
    light[0], light[1], light[3] = 2.0, 0.6, 0.8
    dirs = np.array([[0.6, 0.3, 0.74], [-0.5, 0.5, 0.7], [0.0, 0.9, 0.44], [0.8, -0.2, 0.57]])
    dirs = np.resize(dirs, (max(args.shadows, 1), 3))
    n = args.res
    g = render_gbuffer(scene, cam, n, n)

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"backend: {scene.backend}; mesh: {len(mesh.faces)} triangles; {n}x{n}, median of {args.repeats}; "
          f"{os.cpu_count()} cores, load {load:.1f}")
    print(f"  scene build (BVH)        {build}")
    print(f"  primary G-buffer         {ms(lambda: render_gbuffer(scene, cam, n, n))}"
          f"  ({g.hit.mean():.0%} pixels hit)")
    frac = cast_shadow(scene, g, dirs[0]).sum() / max(g.hit.sum(), 1)
    print(f"  shadow pass (1 light)    {ms(lambda: cast_shadow(scene, g, dirs[0]))}"
          f"  ({frac:.1%} of hit pixels in cast shadow)")
    print(f"  shadow passes batched x{len(dirs)} {ms(lambda: cast_shadows(scene, g, dirs))}")
    print(f"  shading reference        {ms(lambda: shading_reference(g, light))}")

    r = args.record_res

    def record():
        sc = Scene(mesh.copy(), labels, backend=args.backend)
        gb = render_gbuffer(sc, cam, r, r)
        cast_shadows(sc, gb, dirs[: args.shadows])
        shading_reference(gb, light)

    print(f"per record at {r}x{r} (build + G-buffer + {args.shadows} shadows + shading): "
          f"{ms(record)}  (x1000 records: ms -> s)")


if __name__ == "__main__":
    main()
