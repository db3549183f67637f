"""The photo path measured against ground truth at full resolution (``scripts/photo_path_bench.py``).

SynthFaces heads (hair or hat, ears, neck, clothes, a background) are rendered at ``resolution`` px on a seed no model
trained on, each subject under two lights of its light group. Every source image goes through exactly what
``difareli-relight image=...`` does with a photo, through its public doors: :meth:`Relighter.photo_source` (detect,
align, preprocess), :class:`~difareli.relight.request.Target` (a target light taken from another photo: its light,
shadow strength and key sun as the photo path fits them) and :meth:`Relighter.relight` + :meth:`Relit.composite`
(the request's default compositing, at the photo's resolution). Three targets per source, decoded in one batch:

- ``same`` (protocol i): the light fitted on the ground truth itself (the same subject under the target light);
- ``different`` (protocol ii): the light fitted on the other subject of the light group under the target light;
- ``exact``: the renderer's exact SH light of the target (an oracle light; shadow strength and key sun as ``same``).

Each composite is scored against the ground truth on the whole head (the renderer's face, hair, hat and neck
labels): DSSIM, MSE, LPIPS (:mod:`difareli.evaluation.metrics`, paper rule), beside the unrelit photo and the
Lambertian ratio relight (:func:`difareli.evaluation.baselines.ratio_relight` on the photo path's own aligned crop,
normals and fitted source light, composited the same way); paired tests as :mod:`difareli.evaluation.paired`
computes them. Artefacts (:mod:`difareli.evaluation.artefacts`) are scored for the composite, the Lambertian
composite and the ground truth itself: the seam along the paste boundary, the blotches inside the renderer's face
(away from the source's and the target's visible cast-shadow edges) and the face's luminance change, whose
difference from the Lambertian prediction's is ``lum_dev``. The real-photo bench without ground truth is
:mod:`difareli.evaluation.photo_presets`.
"""

from __future__ import annotations

import datetime
import math
import os
import sys
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from scipy import ndimage

from difareli.checkpoints import zoo
from difareli.data.encodings import FACE_PARTS
from difareli.errors import UserError
from difareli.evaluation import artefacts as art
from difareli.evaluation import metrics, paired
from difareli.evaluation.baselines import ratio_relight
from difareli.evaluation.records import Record, mean_se, protocol_label
from difareli.estimators.align import crop_to_photo
from difareli.relight.composite import part_mask
from difareli.relight.relighter import Relighter
from difareli.relight.request import Request, Target
from difareli.relight.sources import Source
from difareli.relight.targets import Targets
from difareli.utils import viz
from difareli.utils.fileio import write_text_atomic

#: The model the photo path relights with when none is named: the app's default.
DEFAULT_CHECKPOINT = zoo.RECOMMENDED
#: The renderer's labels that make the head a photo relight should change.
HEAD_PARTS = (*FACE_PARTS, "neck", "hair", "hat")
PROTOCOLS = ("same", "different", "exact")
METHODS = ("relit", "lambertian", "photo")  # scored against the ground truth; "truth" scores its own artefacts
LIGHTS = 4


def composite_settings() -> dict:
    """How a photo's relights go back into it: the request's defaults (``conf/relight.yaml``'s composite block)."""
    return dict(Request().composite)


# --------------------------------------------------------------------------- geometry of a relit photo
def to_photo(crop_map: np.ndarray, quad: np.ndarray, hw: tuple[int, int], order: int = 0) -> np.ndarray:
    """A crop-space map (S, S) warped into photo pixels (H, W) through the alignment ``quad`` (the composite's
    transform, :func:`~difareli.estimators.align.crop_to_photo`); 0 outside the crop. ``order`` 0: nearest."""
    crop_map = np.asarray(crop_map, np.float64)
    m = crop_to_photo(quad, crop_map.shape[0])
    inv = np.linalg.inv(m[:, :2])
    matrix = inv[::-1, ::-1]  # (row, col) = (y, x) order on both sides
    offset = -matrix @ m[::-1, 2]
    return ndimage.affine_transform(crop_map, matrix, offset, output_shape=hw, order=order, cval=0.0)


@dataclass
class Regions:
    """Where a photo's relight lands, in photo pixels: the paste region (where the blend mask is above one half),
    the face (the photo path's face parts), and the size of one crop pixel (photo px) that sets the scores'
    scales."""

    paste: np.ndarray
    face: np.ndarray
    crop_px: float

    @property
    def width(self) -> int:
        """The seam's band: one crop pixel, at least 2 px."""
        return max(2, round(self.crop_px))

    @property
    def sigma(self) -> float:
        """The blotch score's blur: two crop pixels."""
        return 2.0 * self.crop_px


def regions(source: Source) -> Regions:
    """The :class:`Regions` of a photo source (its compositor's mask and its masks encoding)."""
    prep = source.photo
    hw = prep.rgb.shape[:2]
    paste = prep.compositor(**composite_settings()).mask() > 0.5
    face = to_photo(part_mask(prep.arrays["masks"], FACE_PARTS), prep.quad, hw) > 0.5
    side = float(np.linalg.norm(prep.quad[3] - prep.quad[0]))
    return Regions(paste, face, side / prep.arrays["masks"].shape[0])


def lambertian_crops(source: Source, lights: np.ndarray) -> np.ndarray:
    """The Lambertian ratio relight of the source's aligned crop under each light (N, S, S, 3): the baseline on
    the photo path's own estimates (normals, fitted source light)."""
    a = source.arrays
    return np.stack([ratio_relight(a["image"], a["normal"], a["light"], light) for light in lights])


# --------------------------------------------------------------------------- the synthetic pairs
@dataclass(frozen=True)
class Pair:
    """Subject ``subject`` under light ``source`` relit toward light ``target``; ``partner``: the other subject of
    its light group (protocol ii's light source)."""

    subject: int
    partner: int
    source: int
    target: int

    @property
    def id(self) -> str:
        return f"s{self.subject:03d}_l{self.source}-l{self.target}"


def plan_pairs(n: int, lights: int = LIGHTS) -> list[Pair]:
    """``n`` pairs (n even: whole light groups of 2), one per subject; group ``g`` goes from light ``g mod lights``
    to another light, the step cycling with ``g`` so that every ordered pair of lights comes up."""
    if n < 2 or n % 2:
        raise UserError(f"{n} pairs: give an even number of pairs >= 2 (whole light groups of two subjects)")
    out = []
    for k in range(n):
        g = k // 2
        i = g % lights
        out.append(Pair(k, k ^ 1, i, (i + 1 + (g // lights) % (lights - 1)) % lights))
    return out


def render(pairs: list[Pair], seed: int, resolution: int) -> dict[tuple[int, int], dict[str, np.ndarray]]:
    """(subject, light) -> the record's arrays (image, masks, face mask, visible shadows, exact light), rendered
    as ``difareli-synth realism=full`` renders them."""
    from difareli.synth.config import SynthConfig
    from difareli.synth.generator import render_records

    cfg = SynthConfig(subjects=len(pairs), lights=LIGHTS, resolution=resolution, seed=seed, realism="full")
    need: dict[int, set[int]] = {}
    for p in pairs:
        need.setdefault(p.subject, set()).update((p.source, p.target))
        need.setdefault(p.partner, set()).add(p.target)
    out = {}
    for k, js in sorted(need.items()):
        for _, arrays, meta in render_records(k, sorted(js), cfg, "test"):
            out[(k, int(meta["light_index"]))] = arrays
    return out


def pair_targets(relighter: Relighter, source: Source, same: Source, other: Source, exact: np.ndarray) -> Targets:
    """The three targets of a pair (module doc), each as the photo path makes a target from another photo."""
    made = [Target(record=s.what).for_source(relighter, source, s)[0] for s in (same, other)]
    lights = [made[0].lights[0], made[1].lights[0], exact]
    shadows = [made[0].shadows[0], made[1].shadows[0], made[0].shadows[0]]
    suns = [(m.suns or (None,))[0] for m in made]
    return Targets.of(lights, shadows, source.what, suns=[*suns, suns[0]])


def _image_scores(pred: np.ndarray, gt: np.ndarray, head: np.ndarray) -> dict[str, float]:
    p, g = metrics.unit_tensor(pred), metrics.unit_tensor(gt)
    m = torch.from_numpy(np.asarray(head, bool))[None]
    return {"dssim": float(metrics.dssim(p, g, m)[0]), "mse": float(metrics.masked_mse(p, g, m)[0]),
            "lpips": float(metrics.lpips(p.float(), g.float(), m)[0])}


def _artefacts(image, photo, truth, reg: Regions, face, exclude, lam) -> dict[str, float]:
    """The artefact columns of one image: its seam and blotch against the photo (the truth's own are the bound),
    against the truth (what it has that the truth lacks), and its face luminance against the Lambertian's."""
    return {"seam": art.seam_score(image, photo, reg.paste, reg.width),
            "seam_vs_gt": art.seam_score(image, truth, reg.paste, reg.width),
            "blotch": art.blotch_score(image, photo, face, reg.sigma, exclude),
            "blotch_vs_gt": art.blotch_score(image, truth, face, reg.sigma, exclude),
            "lum_dev": art.luminance_change(image, photo, face) - art.luminance_change(lam, photo, face)}


def score_pair(relighter: Relighter, pair: Pair, renders: dict) -> tuple[list[Record], dict[str, np.ndarray]]:
    """Every protocol of one pair relit through the photo path and scored: the records (methods relit,
    lambertian, photo and truth) and the images of protocol ``same`` for the contact sheet."""
    src, gt = renders[(pair.subject, pair.source)], renders[(pair.subject, pair.target)]
    photo = src["image"]
    source = relighter.photo_source(photo, what=f"render {pair.id}", key=("photo_path", pair.id),
                                    also=("normal", "face_mask"))
    same = relighter.photo_source(gt["image"], what=f"render s{pair.subject:03d}_l{pair.target}")
    other = relighter.photo_source(renders[(pair.partner, pair.target)]["image"],
                                   what=f"render s{pair.partner:03d}_l{pair.target}")
    targets = pair_targets(relighter, source, same, other, gt["light"])
    relit = relighter.relight(source, targets)
    seconds = sum(relit.seconds.values()) / len(targets)
    comps = relit.composite(**composite_settings())
    lams = relit.composite(**composite_settings(), images=lambertian_crops(source, targets.lights))
    reg = regions(source)
    head = part_mask(gt["masks"], HEAD_PARTS)
    face = np.asarray(gt["face_mask"], bool)
    width = int(math.ceil(reg.sigma))
    exclude = art.shadow_edges([src["shadow_visible_gt"], gt["shadow_visible_gt"]], width)
    rows = []
    for k, proto in enumerate(PROTOCOLS):
        images = {"relit": comps[k], "lambertian": lams[k], "photo": photo}
        for name, image in images.items():
            extra = _artefacts(image, photo, gt["image"], reg, face, exclude, lams[k])
            rows.append(Record(name, proto, pair.id, **_image_scores(image, gt["image"], head),
                               seconds=seconds if name == "relit" else math.nan, extra=extra))
        rows.append(Record("truth", proto, pair.id, 0.0, 0.0, 0.0,
                           extra=_artefacts(gt["image"], photo, gt["image"], reg, face, exclude, lams[k])))
    return rows, {"photo": photo, "relit": comps[0], "lambertian": lams[0], "truth": gt["image"]}


def run_pairs(relighter: Relighter, pairs: list[Pair], seed: int, resolution: int,
              tell: Callable[[str], None] = print) -> tuple[list[Record], list[dict], list[str]]:
    """Every pair scored (:func:`score_pair`): the records, the contact-sheet images and the pairs that could
    not be relit (the photo path's one line each)."""
    renders = render(pairs, seed, resolution)
    records, sheet, failed = [], [], []
    for n, pair in enumerate(pairs, 1):
        try:
            rows, images = score_pair(relighter, pair, renders)
        except UserError as e:
            failed.append(f"{pair.id}: {e}")
            tell(f"[{n}/{len(pairs)}] {pair.id}: not relit ({e})")
            continue
        records += rows
        sheet.append({"id": pair.id, **images})
        r = {x.protocol: x for x in rows if x.method == "relit"}
        tell(f"[{n}/{len(pairs)}] {pair.id}: relit DSSIM " + ", ".join(f"{p} {r[p].dssim:.4f}" for p in PROTOCOLS))
    return records, sheet, failed


# --------------------------------------------------------------------------- the table
def provenance(relighter: Relighter, seconds: float) -> str:
    """One line saying how a bench ran: the command, the model and how it relit, the CPU, the date, the wall time."""
    cpu = "unknown CPU"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    cores = len(os.sched_getaffinity(0))
    return (f"`python {' '.join(sys.argv)}`: checkpoint={relighter.checkpoint} ({relighter.describe()}), "
            f"{cpu} ({cores} cores), {datetime.date.today().isoformat()}, {seconds / 60:.1f} min wall")


COLUMNS = ("dssim", "lpips", "mse", "seam", "seam_vs_gt", "blotch", "blotch_vs_gt", "lum_dev")


def summary(records: list[Record]) -> list[dict]:
    """Mean, SE and n of every column per protocol and method (the truth row: its artefacts only)."""
    out = []
    for proto in PROTOCOLS:
        for method in (*METHODS, "truth"):
            rs = [r for r in records if r.protocol == proto and r.method == method]
            if rs:
                stats = {k: mean_se(r.value(k) for r in rs) for k in COLUMNS}
                out.append({"protocol": proto, "method": method, **stats})
    return out


def to_markdown(rows: list[dict]) -> str:
    """The summary as one Markdown table: mean ± SE (n where a score is undefined for some pairs)."""
    head = "| protocol | method | DSSIM | LPIPS | MSE | " + " | ".join(COLUMNS[3:]) + " | n |"
    lines = [head, "|---|---|" + "---:|" * (len(COLUMNS) + 1)]
    for row in rows:
        n = max(s.n for k, s in row.items() if k in COLUMNS)
        cells = []
        for k in COLUMNS:
            s = row[k]
            truth_metric = row["method"] == "truth" and k in ("dssim", "lpips", "mse")
            cells.append("–" if truth_metric or not s.n else f"{s.mean:.4f} ± {s.se:.4f}"
                         + (f" (n={s.n})" if s.n != n else ""))
        lines.append(f"| {protocol_label(row['protocol'])} | {row['method']} | " + " | ".join(cells) + f" | {n} |")
    return "\n".join(lines) + "\n"


def to_csv(rows: list[dict]) -> str:
    """The summary as CSV at full precision (``<column>_mean``, ``_se``, ``_n``)."""
    head = ["protocol", "method"] + [f"{k}_{s}" for k in COLUMNS for s in ("mean", "se", "n")]
    lines = [",".join(head)]
    for row in rows:
        lines.append(",".join([row["protocol"], row["method"]] + [repr(float(v)) if s != "n" else str(v) for k in
                               COLUMNS for s, v in (("mean", row[k].mean), ("se", row[k].se), ("n", row[k].n))]))
    return "\n".join(lines) + "\n"


def pairs_csv(records: list[Record]) -> str:
    """Every scored image (method, protocol, pair) at full precision: the per-pair table behind the summary."""
    lines = [",".join(["method", "protocol", "pair", *COLUMNS, "seconds"])]
    for r in records:
        values = [r.value(k) for k in COLUMNS] + [r.seconds]
        lines.append(",".join([r.method, r.protocol, r.record_id, *("" if not math.isfinite(v) else repr(float(v))
                                                                    for v in values)]))
    return "\n".join(lines) + "\n"


def paired_tests(records: list[Record]) -> str:
    """The paired tests (:func:`difareli.evaluation.paired.compare`): the composite against the unrelit photo and
    the Lambertian composite on DSSIM and LPIPS, and its seam, blotch and luminance against the ground truth's."""
    scores, _ = paired.compare([r for r in records if r.method in METHODS], ["dssim", "lpips"],
                               methods=["relit", "lambertian", "photo"])
    own, _ = paired.compare([r for r in records if r.method in ("relit", "truth")], ["seam", "blotch", "lum_dev"],
                            methods=["relit", "truth"])
    return paired.to_markdown(scores) + "\n" + paired.to_markdown(own)


def contact_sheet(sheet: list[dict], rows: int = 4) -> np.ndarray:
    """photo | relit composite | Lambertian composite | ground truth for the first ``rows`` pairs (protocol i)."""
    picked = sheet[:rows]
    return viz.grid([[s[k] for k in ("photo", "relit", "lambertian", "truth")] for s in picked],
                    col_labels=["photo", "relit composite", "Lambertian composite", "ground truth"],
                    row_labels=[s["id"] for s in picked])


def publish(out, stem: str, text: str, image: np.ndarray, sheet=None, written: tuple[str, ...] = ()) -> None:
    """A photo bench's report: ``<out>/<stem>.md`` and ``<stem>_sheet.png`` (and the sheet at ``sheet`` too),
    the text printed, then every file written (``written``: the bench's CSVs, already in ``out``)."""
    write_text_atomic(out / f"{stem}.md", text)
    viz.save_png(image, out / f"{stem}_sheet.png")
    if sheet:
        viz.save_png(image, sheet)
    print(text)
    print(f"written: {out}/{stem}.md, {', '.join([*written, f'{stem}_sheet.png'])}" + (f"; {sheet}" if sheet else ""))
