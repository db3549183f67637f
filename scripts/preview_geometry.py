"""Preview SynthFaces geometry: normal and part-label images of random heads, ray-cast orthographically.

Usage: python scripts/preview_geometry.py [--n 4] [--res 128] [--seed 0] [--out /tmp/geometry_preview.png]
Also prints the time of ``build_head`` for new random subjects.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from PIL import Image

from difareli.data.encodings import NUM_MASK_PARTS
from difareli.synth.accessories import build_head, default_camera


def raycast(head, cam, res: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-space normal (res, res, 3) and label (res, res) maps of ``head`` seen through DECA camera ``cam``."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    mesh = head.mesh
    s, tx, ty = cam
    v, u = np.mgrid[0:res, 0:res] + 0.5
    x, y = (u / res * 2 - 1) / s - tx, (1 - v / res * 2) / s - ty
    o = np.stack([x.ravel(), y.ravel(), np.full(res * res, 10.0)], 1)
    tri, ray = RayMeshIntersector(mesh).intersects_id(o, np.tile([0.0, 0.0, -1.0], (res * res, 1)), multiple_hits=False)
    normal = np.zeros((res * res, 3))
    label = np.zeros(res * res, np.uint8)
    normal[ray] = mesh.face_normals[tri]
    label[ray] = head.face_labels[tri]
    return normal.reshape(res, res, 3), label.reshape(res, res)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="/tmp/geometry_preview.png")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    build_head(rng=np.random.default_rng(12345))  # loads the model and templates
    t0 = time.perf_counter()
    heads = [build_head(rng=rng) for _ in range(max(args.n, 20))]
    print(f"build_head: {(time.perf_counter() - t0) / len(heads) * 1e3:.1f} ms per new random subject "
          f"({len(heads[0].vertices)} vertices, {len(heads[0].faces)} triangles)")
    import matplotlib

    palette = (np.asarray(matplotlib.colormaps["tab20"](np.arange(NUM_MASK_PARTS)))[:, :3] * 255).astype(np.uint8)
    palette[0] = 0
    rows = []
    for head in heads[: args.n]:
        normal, label = raycast(head, default_camera(head), args.res)
        shade = ((normal * 0.5 + 0.5) * 255 * (label > 0)[..., None]).astype(np.uint8)
        rows.append(np.concatenate([shade, palette[label]], 1))
        print("pose (yaw, pitch, roll) =", np.round(head.params.pose, 1), "hat" if head.accessories.hat else "")
    Image.fromarray(np.concatenate(rows, 0) if args.n <= 2 else np.concatenate(
        [np.concatenate(rows[i : i + 2], 1) for i in range(0, len(rows) - 1, 2)], 0)).save(args.out)
    print("saved", args.out)


if __name__ == "__main__":
    main()
