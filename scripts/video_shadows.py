"""Cast shadows in light-rotation videos, several models x records x target maps in one table: each cell is one
``difareli-video`` run (a 60-frame yaw rotation of an unseen record beside its SynthFaces ground truth) at the
model's defaults, with the ground truth's exact target maps (``oracle_maps=true``) and with the model's own (the
relight's march toward each frame's light, or toward the input's found key sun turned with it: ``target.sun``);
the table gives each model's mean over the records of the relit-shadow IoU against the ground truth (the shadow
detected in the relit frame against the ground truth's exact visible shadows), how well the detection rule finds
those shadows in the ground-truth frames (a relit frame that draws them darker can score above it), what the
ground-truth frames rendered without cast shadows score (what a relight that draws none scores), how far the
frames follow their maps, and DSSIM / LPIPS.

    python scripts/video_shadows.py --store data/unseen_v3_s4242 --records s00000_l1 s00001_l1 \
        --checkpoints difareli_pp-synth64 difareli_pp_shadows-synth64 --out logs/video_shadows

A finished cell (its ``summary.json``) is read back, not run again: a killed run resumes. Extra ``difareli-video``
overrides after ``--``, e.g. ``-- sampler=ddim sampler.steps=50`` or ``-- rotation.axis=roll`` (use another
``--out`` for each: a cell is known by model, record and maps).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

MAPS = {"exact": "oracle_maps=true", "own": "oracle_maps=false"}
COLUMNS = ("shadow_iou_mean", "rule_iou_mean", "floor_iou_mean", "map_iou_mean", "map_adherence_mean", "dssim_mean",
           "lpips_mean")


def cell(checkpoint: str, store: str, record: str, maps: str, out: Path, extra: list[str]) -> dict:
    """One video's summary (run unless its summary.json is there)."""
    where = out / Path(checkpoint).stem / f"{record}_{maps}"
    summary = where / "summary.json"
    if not summary.is_file():
        exe = shutil.which("difareli-video") or str(Path(sys.executable).with_name("difareli-video"))
        cmd = [exe, f"checkpoint={checkpoint}", f"store={store}", f"record={record}", MAPS[maps],
               "progress=false", "format=gif", f"out_dir={where}", *extra]
        print(" ".join(cmd[1:]), flush=True)
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"difareli-video failed for {checkpoint} {record} {maps}:\n{proc.stderr[-2000:]}")
    return json.loads(summary.read_text())


def mean(values: list[float]) -> float:
    ok = [v for v in values if v == v]
    return sum(ok) / len(ok) if ok else math.nan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--store", required=True)
    ap.add_argument("--records", nargs="+", required=True)
    ap.add_argument("--checkpoints", nargs="+", required=True)
    ap.add_argument("--out", default="logs/video_shadows")
    ap.add_argument("--maps", nargs="+", choices=list(MAPS), default=list(MAPS),
                    help="which target maps (default: both)")
    ap.add_argument("extra", nargs="*", help="difareli-video overrides (after --)")
    a = ap.parse_args()
    out = Path(a.out)
    rows = []
    for ck in a.checkpoints:
        for maps in a.maps:
            got = [cell(ck, a.store, r, maps, out, a.extra) for r in a.records]
            per = " ".join(f"{g['shadow_iou_mean']:.3f}" for g in got)
            cols = [mean([g.get(c, math.nan) for g in got]) for c in COLUMNS]
            rows.append(f"| {ck} | {maps} | " + " | ".join(f"{v:.3f}" for v in cols)
                        + f" | {per} |")
    sampler = got[0]["sampler"]
    rotation = got[0]["rotation"].split(", ")[0].replace("the input's light ", "")  # e.g. "rotated about yaw"
    head = (f"{len(a.records)} records of {a.store} ({', '.join(a.records)}), {got[0]['frames']} frames, the "
            f"input's light {rotation}, "
            f"sampler {sampler['name']}-{sampler['steps']}; means over the records\n\n"
            "| model | target maps | shadow IoU vs GT | the rule on the GT | GT without cast shadows | map IoU "
            "| map adherence | DSSIM | LPIPS | shadow IoU per record |\n"
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---|\n")
    text = head + "\n".join(rows) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
