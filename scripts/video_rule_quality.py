"""How well the video shadow rule (``difareli.evaluation.video.detect_cast_shadow``) finds SynthFaces' own visible
cast shadows, over its one setting: each chosen record's subject is rendered under its light rotated through 360
degrees about yaw or roll (``synth.rotation.ground_truth_rotation``, the frames difareli-video compares against),
the rule is applied to those ground-truth frames with the exact suns (as difareli-video applies it), and its IoU
against the frames' exact visible shadows on the judged pixels is averaged per record, then over records. Choose on
a store the models trained on (its train split), never on the records a table reports.

Two controls, frames that draw no cast shadow, show the floor of difareli-video's shadow IoU (against the ground
truth's exact shadows) and of the detection-against-detection IoU it replaced (against the shadow the rule finds in
the ground-truth frame): the subject rendered under each frame's light without cast shadows (a relight perfect but
for the shadow) and the input image itself in every frame (no relight at all); and a detection that marks every
judged pixel (what shadowing the whole face would score).

    python scripts/video_rule_quality.py --store data/sf_v3_64 --split train --records 10
"""

from __future__ import annotations

import argparse

import numpy as np
from tqdm import tqdm

from difareli.data.store import EncodingStore
from difareli.evaluation import video as vid
from difareli.synth import rotation

#: The visible shares tried (the rule's ``visible``: its darkness cut is ``1 - visible``, its key-sun share
#: ``visible``).
SHARES = (0.15, 0.2, 0.25, 0.3, 0.4)


def shadowed(store: EncodingStore, split: str, n: int, light: str, min_share: float) -> list[str]:
    """The first ``n`` records of ``split`` under light ``light`` whose visible shadow covers more than
    ``min_share`` of the face."""
    out = []
    for rid in store.ids(split=split):
        if not rid.endswith(f"_l{light}"):
            continue
        a = store.read(rid, ["face_mask", "shadow_visible_gt"])
        face = np.asarray(a["face_mask"], bool)
        if (np.asarray(a["shadow_visible_gt"], bool) & face).sum() > min_share * face.sum():
            out.append(rid)
        if len(out) == n:
            break
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", required=True)
    ap.add_argument("--split", default="train")
    ap.add_argument("--records", type=int, default=10)
    ap.add_argument("--light", default="1", help="the light index of the records (default 1, as the tables use)")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--axis", default="yaw", choices=("yaw", "roll"), help="the rotation (default yaw)")
    ap.add_argument("--min-share", type=float, default=0.04, help="visible shadow share of the face a record needs")
    ap.add_argument("--ids", nargs="+", help="these records instead of the first shadowed ones of --split (e.g. the "
                    "records a video table reports, for its controls)")
    a = ap.parse_args()
    store = EncodingStore.open(a.store)
    ids = a.ids or shadowed(store, a.split, a.records, a.light, a.min_share)
    if not ids:
        raise SystemExit(f"{a.store}: no {a.split} record with a visible shadow over {a.min_share} of the face")
    scores = {v: [] for v in SHARES}
    controls = {f"{name}, {against}": [] for name in ("no cast shadow", "the input, unrelit")
                for against in ("vs GT's exact shadows", "vs the rule on the GT")}
    controls["every judged pixel shadowed, vs GT's exact shadows"] = []
    for rid in tqdm(ids, desc="records"):
        gt = rotation.ground_truth_rotation(store, rid, a.axis, a.frames)
        arrays = store.read(rid, ["image", "normal", "face_mask", "shadow_map"])
        suns, src = gt.suns(), rotation.source_suns(store, rid)
        for v in SHARES:
            found, judged = vid.detect_cast_shadow(gt.frames, arrays, suns, src, visible=v)
            scores[v].append(float(np.nanmean(vid.iou(found, gt.cast() & judged))))
        detected, judged = vid.detect_cast_shadow(gt.frames, arrays, suns, src)
        exact = gt.cast() & judged
        # per frame, NaN where both are empty, averaged as difareli-video's summary averages
        controls["every judged pixel shadowed, vs GT's exact shadows"].append(float(np.nanmean(vid.iou(judged, exact))))
        for name, frames in (("no cast shadow", gt.without_shadows().frames),
                             ("the input, unrelit", np.repeat(np.asarray(arrays["image"])[None], len(gt), 0))):
            found, _ = vid.detect_cast_shadow(frames, arrays, suns, src)
            for against, truth in (("vs GT's exact shadows", exact), ("vs the rule on the GT", detected)):
                controls[f"{name}, {against}"].append(float(np.nanmean(vid.iou(found, truth))))
    which = "given" if a.ids else f"shadowed {a.split}"
    print(f"{len(ids)} {which} records of {a.store} ({' '.join(ids)}), {a.frames}-frame {a.axis} rotations: "
          "the rule on the ground-truth frames against their exact visible shadows\n")
    print("| visible share | IoU (mean over records) | per record |\n|---:|---:|---|")
    for v, s in scores.items():
        mark = " (the default)" if v == vid.VISIBLE else ""
        print(f"| {v:g}{mark} | {np.mean(s):.3f} | {' '.join(f'{x:.2f}' for x in s)} |")
    print("\nControls at the default: frames that draw no cast shadow, and a detection that marks every pixel\n")
    print("| frames, against | shadow IoU | per record |\n|---|---:|---|")
    for name, s in controls.items():
        print(f"| {name} | {np.mean(s):.3f} | {' '.join(f'{x:.2f}' for x in s)} |")


if __name__ == "__main__":
    main()
