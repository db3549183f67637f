"""Choose ``render.sun_fit``'s search on held-out records: for each cone (degrees around the fitted light's radiance
peak) and cost per 90 degrees moved, the median angle between the found sun and the record's key sun (its
header's ``sun_dir``) and the IoU of the march toward it against the visibly shadowed pixels, over a SynthFaces
split's records with a lit key sun. The first row is the radiance peak itself (no search).

    python scripts/sun_fit_sweep.py --store data/unseen_v3_s4242 --split val
"""

from __future__ import annotations

import argparse

import numpy as np
from tqdm import tqdm

from difareli.data.store import EncodingStore
from difareli.evaluation.metrics import binary_scores
from difareli.lighting.suns import Suns
from difareli.render.retarget import target_shadow_map
from difareli.render import sun_fit


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--light", default="light", help="the SH light searched around (default: the fitted one)")
    ap.add_argument("--cones", type=float, nargs="+", default=[30.0, 40.0, 50.0])
    ap.add_argument("--costs", type=float, nargs="+", default=[0.0, 0.1, 0.3, 0.6])
    args = ap.parse_args()
    store = EncodingStore.open(args.store)
    names = [k for k in sun_fit.ENCODINGS if store.available(k)] + [args.light, "shadow_visible_gt"]
    records = []
    for rid in store.ids(args.split):
        meta = store.meta(rid)
        if np.any(np.asarray(meta.get("sun_rgb", 0)) > 0):
            records.append((store.read(rid, names), np.asarray(meta["sun_dir"], np.float64)))
    rows = [("peak", None, None)] + [(f"cone {c:g}, cost {k:g}", c, k) for c in args.cones for k in args.costs]
    print(f"{len(records)} records of {args.split} with a key sun; light: {args.light}\n")
    print("| search | median degrees from the key sun | map IoU vs visible shadows |\n|---|---:|---:|")
    for label, cone, cost in tqdm(rows, desc="searches", leave=False):
        degrees, ious = [], []
        for a, key in records:
            light = np.asarray(a[args.light], np.float64)
            found = sun_fit.fit_sun(a, light, cone_deg=cone if cone is not None else 0.0,
                                    angle_cost=cost if cost is not None else 0.0)
            d = found.peak if cone is None else found.direction
            degrees.append(np.degrees(np.arccos(np.clip(d @ key / np.linalg.norm(key), -1.0, 1.0))))
            cast = target_shadow_map(a, Suns.of_sh(light, d), 0.0, (-10.0, 10.0)) > 0
            ious.append(binary_scores(cast[None], np.asarray(a["shadow_visible_gt"])[None] > 0)["iou"][0])
        print(f"| {label} | {np.median(degrees):.1f} | {np.nanmean(ious):.3f} |", flush=True)


if __name__ == "__main__":
    main()
