#!/usr/bin/env python
"""Train the cast-shadow classifier of difareli-preprocess on a SynthFaces store and save its weights.

    python scripts/train_shadow_classifier.py --store data/synthfaces_128 [--out PATH] [--max-records N]

Features are computed exactly as on real photos (FaceMesh geometry, FaceMesh/selfie skin mask, SH fit,
ray-traced cast map: estimators/shadow.py) on each SynthFaces image; records where FaceMesh finds no face
are skipped and counted. Label: SynthFaces ``c > shadow.LABEL_C`` (cast shadows remove > 2% of the face's
light). Train on the store's ``train`` split, report accuracy on the other splits (held out by subject).
The affine calibration ``c ~ a * logit + b`` (least squares on the training set) is saved with the weights.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from difareli.estimators.geometry import FaceMeshGeometry
from difareli.estimators.light import SkinSHLight
from difareli.estimators.masks import FaceMeshSelfieMasks
from difareli.estimators.shadow import (DEFAULT_WEIGHTS, FEATURES, LABEL_C, LABEL_S, LogisticShadowClassifier,
                                        ShadowEstimator, features)
from difareli.data.store import EncodingStore


def record_features(image: np.ndarray, geometry, masks, light, shadow) -> np.ndarray | None:
    """Features of one image through the preprocessing estimators, or None if any of them fails."""
    ctx = {"image": np.ascontiguousarray(image)}
    needed = {"landmarks", "scene", "gbuffer", "skin", "light"}
    try:
        for est in (geometry, masks, light):
            ctx.update(est(ctx, needed))
        cast = shadow.cast(ctx)
    except Exception:  # noqa: BLE001 - FaceMesh misses some synthetic faces; they are counted, not fatal
        return None
    return features(ctx["image"], ctx["gbuffer"], ctx["skin"], ctx["light"], ctx["albedo_prior"], cast)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--store", required=True, help="SynthFaces encodings store (needs image and shadow)")
    ap.add_argument("--out", default=str(DEFAULT_WEIGHTS), help="weights JSON (default: the shipped path)")
    ap.add_argument("--max-records", type=int, default=0, help="use at most this many records (0: all)")
    ap.add_argument("--l2", type=float, default=1e-2)
    args = ap.parse_args(argv)

    store = EncodingStore.open(args.store)
    ids = store.ids()
    if args.max_records:
        ids = ids[:: max(1, len(ids) // args.max_records)][: args.max_records]
    geometry, masks, light, shadow = FaceMeshGeometry(), FaceMeshSelfieMasks(), SkinSHLight(), ShadowEstimator()
    xs, cs, splits, skipped = [], [], [], 0
    t0 = time.perf_counter()
    for i, rid in enumerate(ids):
        rec = store.read(rid, ["image", "shadow"])
        x = record_features(np.asarray(rec["image"]), geometry, masks, light, shadow)
        if x is None:
            skipped += 1
            continue
        xs.append(x)
        cs.append(float(rec["shadow"][0]))
        splits.append(store.meta(rid).get("split", "train"))
        if (i + 1) % 100 == 0:
            print(f"  {i + 1}/{len(ids)} records, {skipped} skipped", flush=True)
    x, c, split = np.array(xs), np.array(cs), np.array(splits)
    y = (c > LABEL_C).astype(np.float64)
    train = split == "train"
    if train.all() or not train.any():  # no subject split recorded: hold out every fifth record
        train = np.arange(len(x)) % 5 != 0
    print(f"{len(x)} records with features ({skipped} skipped: no FaceMesh face) in {time.perf_counter() - t0:.0f} s; "
          f"positives {y.mean():.1%}; train {train.sum()}, held out {(~train).sum()}")
    if len(np.unique(y[train])) < 2:
        print("training labels are all one class: generate a store with more lights / sun lights", file=sys.stderr)
        return 1
    params = LogisticShadowClassifier.train(x[train], y[train], l2=args.l2)
    clf = LogisticShadowClassifier(params)
    logit = clf.logit(x)
    pred = logit > 0
    acc_tr = float((pred[train] == y[train]).mean())
    acc_te = float((pred[~train] == y[~train]).mean()) if (~train).any() else float("nan")
    base = float(max(y[~train].mean(), 1 - y[~train].mean())) if (~train).any() else float("nan")
    a, b = np.polyfit(logit[train], c[train], 1)
    params.update(calibration=[float(a), float(b)], label={"s": LABEL_S, "c": LABEL_C},
                  train_accuracy=acc_tr, heldout_accuracy=acc_te, heldout_majority_baseline=base,
                  n_train=int(train.sum()), n_heldout=int((~train).sum()), store=str(args.store))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(params, indent=1) + "\n")
    print("weights:", ", ".join(f"{n}={w:+.2f}" for n, w in zip(FEATURES, params["w"])), f"b={params['b']:+.2f}")
    print(f"train accuracy {acc_tr:.3f}; held-out accuracy {acc_te:.3f} (majority baseline {base:.3f}); "
          f"calibration c = {a:.3f} * logit + {b:.3f}; saved {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
