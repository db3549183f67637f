"""The photo path against ground truth at full resolution (difareli.evaluation.photo_path): SynthFaces heads
rendered at --resolution px on a seed no model trained on, each source put through the photo path (detect, align,
preprocess, relight, composite) and scored on the whole head against the render under the target light, beside the
unrelit photo and the Lambertian ratio composite; seams, blotches and luminance beside the ground truth's own.

    python scripts/photo_path_bench.py --pairs 20 --seed 5150 --out logs/photo_path \
        --sheet docs/images/photo_path_sheet.png

Writes under --out: photo_path.md (the table, the paired tests, how it ran), photo_path.csv (the summary),
photo_path_pairs.csv (every pair, protocol and method) and photo_path_sheet.png (photo | relit composite |
Lambertian composite | ground truth); --sheet: a copy of the sheet there.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from difareli import errors
from difareli.evaluation import photo_path as pp
from difareli.utils.fileio import write_text_atomic

#: The seeds of this project's SynthFaces stores (trained or benchmarked on): a fresh seed keeps the faces unseen.
USED_SEEDS = (0, 777, 4242, 9001, 1011, 2022, 3033)


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default=pp.DEFAULT_CHECKPOINT, help="a shipped name or a checkpoint path")
    ap.add_argument("--pairs", type=int, default=20, help="pairs per protocol (even: whole light groups)")
    ap.add_argument("--seed", type=int, default=5150)
    ap.add_argument("--resolution", type=int, default=256, help="the photos' size in px")
    ap.add_argument("--sheet-rows", type=int, default=4)
    ap.add_argument("--out", default="logs/photo_path")
    ap.add_argument("--sheet", default=None, help="also copy the contact sheet to this path")
    return ap.parse_args()


@errors.cli_entry("photo-path-bench")
def main() -> None:
    args = parse()
    if args.seed in USED_SEEDS:
        raise errors.UserError(f"--seed {args.seed} is the seed of one of this project's stores, which models trained "
                               f"or were benchmarked on ({', '.join(map(str, USED_SEEDS))}); give a fresh one, e.g. "
                               "--seed 5150")
    errors.check_int(args.resolution, "--resolution", 128)
    errors.check_int(args.sheet_rows, "--sheet-rows", 1)
    pairs = pp.plan_pairs(args.pairs)
    out = errors.check_out_dir(args.out, "--out")
    if args.sheet:
        errors.check_out_dir(Path(args.sheet).parent, "--sheet's folder")
    from difareli.relight.relighter import Relighter

    start = time.perf_counter()
    relighter = Relighter(args.checkpoint)
    records, sheet, failed = pp.run_pairs(relighter, pairs, args.seed, args.resolution)
    if not records:
        raise errors.UserError(f"none of the {len(pairs)} pairs could be relit: {failed[0]}")
    rows = pp.summary(records)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "photo_path.csv", pp.to_csv(rows))
    write_text_atomic(out / "photo_path_pairs.csv", pp.pairs_csv(records))
    text = "\n".join([
        f"Photo path at full resolution: {len(sheet)} SynthFaces pairs per protocol, seed {args.seed}, "
        f"{args.resolution} px, realism=full.", "", pp.provenance(relighter, time.perf_counter() - start), "",
        pp.to_markdown(rows), *(f"Not relit: {line}" for line in failed), "", pp.paired_tests(records)])
    pp.publish(out, "photo_path", text, pp.contact_sheet(sheet, args.sheet_rows), args.sheet,
               ("photo_path.csv", "photo_path_pairs.csv"))


if __name__ == "__main__":
    main()
