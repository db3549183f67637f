"""Real photos relit under their own light and every named light, without ground truth
(difareli.evaluation.photo_presets): light error, identity, seam, blotch, face luminance against the Lambertian
prediction, cast-shadow response and reconstruction error, per photo and target.

    python scripts/photo_presets_bench.py --out logs/photo_presets --sheet docs/images/photo_presets_sheet.png
    python scripts/photo_presets_bench.py --checkpoint difareli_pp_ss-synth64 --photos astronaut camera

Writes under --out: photo_presets.md (the summary per target, the face luminance change and the cast-shadow
response per photo, how it ran), photo_presets.csv (every photo and target) and photo_presets_sheet.png (the face
window of a photo of each kind, evaluation.photo_presets.SHEET, or of every photo when few are asked for, then its
composite under each target); --sheet: a copy of the sheet there.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from difareli import errors
from difareli.data.encodings import denormalise_c
from difareli.evaluation import photo_path as pp
from difareli.evaluation import photo_presets as pr
from difareli.utils.fileio import write_text_atomic
from difareli.utils.viz import grid


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default=pp.DEFAULT_CHECKPOINT, help="a shipped name or a checkpoint path")
    ap.add_argument("--photos", nargs="*", default=None, help="names from the fixed list (default: every one)")
    ap.add_argument("--out", default="logs/photo_presets")
    ap.add_argument("--sheet", default=None, help="also copy the contact sheet to this path")
    ap.add_argument("--targets", nargs="*", default=None, help="named lights to relight with (default: every one)")
    ap.add_argument("--shadow", type=float, default=None, help="the named lights' shadow strength in [0, 1] (the "
                    "app's slider, encodings.denormalise_c); default: the relight's own default for a photo")
    ap.add_argument("--bounds", default=None, help="photo_path_pairs.csv of scripts/photo_path_bench.py: count the "
                    "photos beyond the ground truth's own seam, blotch and luminance deviation (90th percentiles)")
    return ap.parse_args()


@errors.cli_entry("photo-presets-bench")
def main() -> None:
    args = parse()
    names = [p.name for p in pr.PHOTOS]
    unknown = [n for n in args.photos or [] if n not in names]
    if unknown:
        raise errors.UserError(f"--photos {' '.join(unknown)}: not in the fixed list; give some of {', '.join(names)}")
    photos = [p for p in pr.PHOTOS if args.photos is None or p.name in args.photos]
    targets = tuple(args.targets or pr.NAMES)
    wrong = [t for t in targets if t not in pr.NAMES]
    if wrong:
        raise errors.UserError(f"--targets {' '.join(wrong)}: not named lights; give some of {', '.join(pr.NAMES)}")
    if args.shadow is not None and not 0.0 <= args.shadow <= 1.0:
        raise errors.UserError(f"--shadow {args.shadow}: give a strength in [0, 1]")
    shadow = None if args.shadow is None else denormalise_c(args.shadow)
    out = errors.check_out_dir(args.out, "--out")
    limits = None if args.bounds is None else pr.bounds(errors.check_file(args.bounds, "--bounds").read_text())
    if args.sheet:
        errors.check_out_dir(Path(args.sheet).parent, "--sheet's folder")
    from difareli.relight.relighter import Relighter

    start = time.perf_counter()
    relighter = Relighter(args.checkpoint)
    rows, cells = [], []
    for n, photo in enumerate(photos, 1):
        source, relit = pr.relight_photo(relighter, photo, targets, shadow)
        rows += pr.score_photo(source, relit, targets)
        if photo.name in pr.SHEET or len(photos) <= len(pr.SHEET):
            comps = relit.composite(**pp.composite_settings())
            cells.append((photo.name, [pr.face_window(source, source.photo.rgb),
                                       *(pr.face_window(source, c) for c in comps)]))
        print(f"[{n}/{len(photos)}] {photo.name}: relit under {len(relit)} targets ({relit.describe_seconds()})")
    image = grid([c for _, c in cells], col_labels=["photo", "own", *targets], row_labels=[n for n, _ in cells])
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "photo_presets.csv", pr.to_csv(rows))
    listing = "\n".join(f"- {p.name}: {p.about}" for p in photos)
    strength = "the relight's default" if args.shadow is None else f"{args.shadow:g} (c' = {shadow:.3f})"
    text = "\n".join([f"Named lights on {len(photos)} photos, shadow strength {strength}:", "", listing, "",
                      pp.provenance(relighter, time.perf_counter() - start), "", pr.summary(rows),
                      *([] if limits is None else [f"Beyond the ground truth's own (90th percentiles over the pairs "
                                                   f"of {args.bounds}, protocol (i)):", "", pr.beyond(rows, limits)]),
                      pr.matrix(rows, "lum_change"), pr.matrix(rows, "lum_dev"), pr.matrix(rows, "shadow_response")])
    pp.publish(out, "photo_presets", text, image, args.sheet, ("photo_presets.csv",))


if __name__ == "__main__":
    main()
