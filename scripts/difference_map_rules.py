"""Which rule turns a DiFaReli's raw differences into the best shadow maps: centring (none | mean | median) x cut
(the authors' fixed 0.05 | relative to the response), scored by IoU against ``shadow_visible_gt`` on the records
that hold a raw-difference version (``difareli-shadow-maps maker=difference ... records_split=<split>`` writes
``shadow_map@diffraw-<hash>``); no relighting.

    python scripts/difference_map_rules.py --store data/unseen_v3_s4242 --split val [--version difference]
"""

from __future__ import annotations

import argparse

import numpy as np

from difareli.data.store import EncodingStore
from difareli.evaluation.map_response import shadowed_records
from difareli.jobs import shadow_maps as sm
from difareli.jobs import shadow_response as sr

CUTS = ("fixed 0.05", "relative 0.05", "relative 0.1", "relative 0.15", "relative 0.25", "relative 0.35",
        "relative 0.5")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--shadowed", type=float, default=0.04, help="only records whose visible shadow covers this share")
    ap.add_argument("--version", default=None, help="the maps whose raw differences to read (e.g. difference; "
                    "default: the first raw-difference version holding the split's records)")
    a = ap.parse_args()
    store = EncodingStore.open(a.store)
    raws = [k for k in store.derived if k.startswith("shadow_map@diffraw-")]
    if a.version is not None:
        name = f"shadow_map@{a.version}"
        if name not in store.derived or "raw" not in store.derived[name]:
            raise SystemExit(f"--version {a.version}: {a.store} has no difference maps of that name "
                             f"({', '.join(k for k in store.derived if k.startswith('shadow_map@'))})")
        raws = [store.derived[name]["raw"]]
    ids = [r for r in store.ids(split=a.split) if any((store.records_dir / r / f"{k}.npy").is_file() for k in raws)]
    ids = shadowed_records(store, ids, a.shadowed)
    if not ids:
        raise SystemExit(f"no shadowed {a.split} record of {a.store} has a raw difference: "
                         "run the difference job first")
    raw = next(k for k in raws if (store.records_dir / ids[0] / f"{k}.npy").is_file())
    print(f"{len(ids)} shadowed {a.split} records of {a.store} ({raw}); IoU against shadow_visible_gt, both on the "
          "face less the eyes, brows and mouth\n")
    print("| centre | " + " | ".join(CUTS) + " |\n|---|" + "---:|" * len(CUTS))
    for centre in sr.CENTRES:
        diffs, _, _, faces = sm._face_values(store, raw, ids, sm.ZERO_PARTS, centre)
        row = []
        for cut in CUTS:
            kind, value = cut.split()
            resp = sr.measure(list(diffs.values()), list(faces.values()),
                              float(value) if kind == "fixed" else "relative", float(value))
            ious = []
            for r in ids:
                m = (diffs[r] > resp.threshold) & faces[r]  # the map's support (median 1 at 64 px)
                gt = np.asarray(store.read(r, ["shadow_visible_gt"])["shadow_visible_gt"], bool) & faces[r]
                union = (m | gt).sum()
                ious.append((m & gt).sum() / union if union else np.nan)
            row.append(f"{np.nanmean(ious):.3f}")
        print(f"| {centre} | " + " | ".join(row) + " |")
    # The whole judged face marked as shadow: what a map must beat to say anything about where the shadow is.
    whole = []
    for r in ids:
        gt = np.asarray(store.read(r, ["shadow_visible_gt"])["shadow_visible_gt"], bool) & faces[r]
        whole.append(gt.sum() / faces[r].sum() if faces[r].any() else np.nan)
    print(f"\nwhole face (baseline): IoU {np.nanmean(whole):.3f} on the same records and region")


if __name__ == "__main__":
    main()
