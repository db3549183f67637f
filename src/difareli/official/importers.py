"""Import the official DiFaReli preprocessing output into an ``EncodingStore``.

The public DiFaReli code (github.com/diffusion-face-relighting/difareli_code, ``create_dataset.py``) writes::

    <src>/params/<set>/ffhq-<set>-{shape,exp,pose,light,cam,detail,tform,albedo}-anno.txt   DECA
    <src>/params/<set>/ffhq-<set>-faceemb-anno.txt                                      ArcFace
    <src>/params/<set>/ffhq-<set>-shadow-anno.txt                                       Diff-AE shadow probe
    <src>/rendered_images/deca_masked_face_images_woclip/<set>/<stem>.npy                DECA shading render
    <src>/face_segment/<set>/anno/anno_<stem>.png                                       BiSeNet face parsing

Confirmed by reading that repository:

- each ``*-anno.txt`` line is ``<image file name> v1 v2 ...`` (single spaces; the name keeps its extension,
  e.g. ``60922.png``); DECA writes ``codedict[k].flatten()``, so ``light`` is DECA's 9x3 (SH coefficient,
  RGB) array flattened row-major, and DiFaReli's loader reads it back with ``reshape(9, 3)``;
- ``shadow-anno.txt`` has one value per image (the shadow-classifier projection c); faceemb is ArcFace r18;
- the ``woclip`` render is ``shape_images`` permuted to HxWx3 float32 at the image's resolution:
  ``(180/255) * SH-irradiance(light, normal)`` times the visible-mesh mask, unclipped, 0 off the mesh.
  Its folder is ``<save_images_folder>_woclip`` with ``deca_masked_face_images`` as that folder, while the
  README's tree shows ``deca_masked_face_woclip``: both are searched (``shading_dir`` overrides);
- ``anno_<stem>.png`` is a single-channel uint8 map of the 19 BiSeNet/CelebAMask-HQ classes at 256x256.

Assumed (not checkable from the code alone): the render uses the estimated light (DiFaReli's modified
``decode``), 3xHxW ``.npy`` renders from other tools are accepted and transposed, and chunked parameter
files (``ffhq-<start>-<end>-<set>-*``) are merged. The shading is stored as rendered: DECA's grey albedo is
180/255 ~ 0.706 rather than SPEC's 0.7 (recorded as ``shading_albedo`` in the store meta).

Mapping: ``shape`` = concat of ``shape_parts`` (default shape, exp, pose; the layout is stored in the store
meta as ``shape_layout``; DiFaReli's own conditioning order is shape, pose, exp), ``identity`` = faceemb,
``shadow`` = shadow value, ``masks`` = BiSeNet labels merged onto ``encodings.MASK_PARTS``, ``face_mask`` =
``FACE_PARTS`` of the masks, ``background`` = image with ``FOREGROUND_PARTS`` zeroed.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from PIL import Image

from difareli.data import encodings as E
from difareli.data.store import EncodingStore
from difareli.errors import UserError, UserFileNotFoundError

log = logging.getLogger(__name__)

#: BiSeNet / CelebAMask-HQ classes in label order (face-parsing.PyTorch).
BISENET_CLASSES = ("background", "skin", "l_brow", "r_brow", "l_eye", "r_eye", "eye_g", "l_ear", "r_ear", "ear_r",
                   "nose", "mouth", "u_lip", "l_lip", "neck", "neck_l", "cloth", "hair", "hat")
#: Where each BiSeNet class goes among MASK_PARTS: glasses, ears and earrings are skin (SPEC 7).
BISENET_TO_PART = {"eye_g": "skin", "l_ear": "skin", "r_ear": "skin", "ear_r": "skin", "neck_l": "neck",
                   "cloth": "clothes"}
#: Lookup table from BiSeNet label to MASK_PARTS index.
BISENET_LUT = np.array([E.PART_INDEX[BISENET_TO_PART.get(c, c)] for c in BISENET_CLASSES], dtype=np.uint8)

_PRODUCERS = {
    "shape": "DECA (DECA/script/estimate_deca_for_dpm.py; create_dataset.py --deca)",
    "faceemb": "ArcFace (Arcface/inference.py; create_dataset.py --arcface)",
    "shadow": "the Diff-AE shadow probe (diffae/gen_shadow.py; create_dataset.py --shadow)",
    "shading": "DECA rendering (estimate_deca_for_dpm.py; create_dataset.py --deca)",
    "masks": "face parsing (face-parsing.PyTorch/inference.py; create_dataset.py --faceseg)",
}
_PARAM_PRODUCER = {k: _PRODUCERS["shape"] for k in ("shape", "exp", "pose", "light", "cam")}
_PARAM_PRODUCER.update(faceemb=_PRODUCERS["faceemb"], shadow=_PRODUCERS["shadow"])
_SHADING_DIRS = ("deca_masked_face_images_woclip", "deca_masked_face_woclip")
_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
_DEFAULT = ("image", "light", "shape", "cam", "identity", "shadow", "shading", "masks", "face_mask", "background")


def bisenet_to_parts(labels: np.ndarray) -> np.ndarray:
    """Map a BiSeNet 19-class label map onto ``MASK_PARTS`` indices (uint8, same shape)."""
    labels = np.asarray(labels)
    if labels.size and int(labels.max()) >= len(BISENET_CLASSES):
        raise UserError(f"face-parsing label {int(labels.max())} outside the 19 BiSeNet classes")
    return BISENET_LUT[labels]


def read_anno(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Parse one DiFaReli ``*-anno.txt``: ``{image name: float64 vector}``, one equal-length vector per line."""
    out: dict[str, np.ndarray] = {}
    length = None
    with open(path) as f:
        for lineno, line in enumerate(f, 1):
            parts = line.split()
            if not parts:
                continue
            try:
                vec = np.array(parts[1:], dtype=np.float64)
            except ValueError as e:
                raise UserError(f"{path}:{lineno}: not '<name> <numbers...>': {e}") from None
            if length is None:
                length = len(vec)
            if len(vec) != length or length == 0:
                raise UserError(f"{path}:{lineno}: {len(vec)} values, expected {length} like the first line")
            out[parts[0]] = vec
    return out


def _param_file(params_dir: Path, set_name: str, key: str, prefix: str) -> dict[str, np.ndarray]:
    exact = params_dir / f"{prefix}-{set_name}-{key}-anno.txt"
    # DECA run with --index writes chunks "<prefix>-<start>-<end>-<set>-<key>-anno.txt"; merge them.
    paths = [exact] if exact.is_file() else sorted(params_dir.glob(f"*-{set_name}-{key}-anno.txt"))
    if not paths:
        raise UserFileNotFoundError(f"missing {exact} (the '{key}' parameters, produced by {_PARAM_PRODUCER[key]})")
    merged: dict[str, np.ndarray] = {}
    for p in paths:
        for name, vec in read_anno(p).items():
            if name in merged and not np.array_equal(merged[name], vec):
                raise UserError(f"image {name!r} has conflicting '{key}' values across {[str(q) for q in paths]}")
            merged[name] = vec
    return merged


def _record_id(stem: str) -> str:
    # FFHQ names are digits; in-the-wild names may hold spaces etc., which record ids forbid.
    rid = re.sub(r"[^A-Za-z0-9_.+=-]", "_", stem).lstrip(".-") or "_"
    return rid[:200]


def _listing(folder: Path) -> dict[str, Path]:
    return {p.name: p for p in folder.iterdir()} if folder.is_dir() else {}


def _resize(arr: np.ndarray, hw: tuple[int, int], kind: str) -> np.ndarray:
    """Resize an HxW[xC] array to ``hw``: nearest for labels, Lanczos for uint8 images, bilinear for floats."""
    if arr.shape[:2] == hw:
        return arr
    size = (hw[1], hw[0])
    if kind == "labels":
        return np.asarray(Image.fromarray(arr).resize(size, Image.NEAREST))
    if kind == "image":
        return np.asarray(Image.fromarray(arr).resize(size, Image.LANCZOS))
    chans = [np.asarray(Image.fromarray(arr[..., c].astype(np.float32), mode="F").resize(size, Image.BILINEAR))
             for c in range(arr.shape[2])]
    return np.stack(chans, axis=-1)


def _load_shading(path: Path) -> np.ndarray:
    arr = np.load(path, allow_pickle=False)
    if arr.ndim == 3 and arr.shape[0] == 3 and arr.shape[-1] != 3:
        arr = arr.transpose(1, 2, 0)  # CHW from a tool other than DiFaReli's DECA script
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise UserError(f"{path}: shading render has shape {arr.shape}, expected HxWx3 (or 3xHxW)")
    return arr.astype(np.float32)


@dataclass
class ImportReport:
    """What ``import_difareli`` did."""

    store: EncodingStore
    written: list[str] = field(default_factory=list)
    skipped_existing: list[str] = field(default_factory=list)
    skipped_incomplete: dict[str, str] = field(default_factory=dict)  # image name -> reason (strict=False)


def _params(params_dir: Path, set_name: str, wanted: Sequence[str], shape_parts: Sequence[str],
            prefix: str) -> dict[str, dict[str, list]]:
    """The parameter files the ``wanted`` encodings read (light, the shape parts, cam, faceemb, shadow), by key."""
    keys = ((["light"] if "light" in wanted else []) + (list(shape_parts) if "shape" in wanted else [])
            + (["cam"] if "cam" in wanted else []) + (["faceemb"] if "identity" in wanted else [])
            + (["shadow"] if "shadow" in wanted else []))
    for k in keys:
        if k not in _PARAM_PRODUCER:
            raise UserError(f"unknown DiFaReli parameter {k!r} in shape_parts; known: {sorted(_PARAM_PRODUCER)}")
    params = {k: _param_file(params_dir, set_name, k, prefix) for k in keys}
    if "light" in params and any(len(v) != 27 for v in params["light"].values()):
        raise UserError(f"{params_dir}: DECA light vectors must have 27 values (9 SH x RGB)")
    return params


def _image_files(name: str, problems: list[str], seg_files: dict | None, seg_dir: Path, shade_files: dict | None,
                 shading_dir, img_files: dict, images_dir) -> dict[str, Path]:
    """One image's spatial source files (its label map, shading render and image, where they are read); what is
    missing is appended to ``problems``."""
    stem = os.path.splitext(name)[0]
    paths: dict[str, Path] = {}
    if seg_files is not None:
        paths["masks"] = seg_files.get(f"anno_{stem}.png")
        if paths["masks"] is None:
            problems.append(f"{seg_dir / f'anno_{stem}.png'} missing")
    if shade_files is not None:
        paths["shading"] = shade_files.get(f"{stem}.npy")
        if paths["shading"] is None:
            problems.append(f"{Path(shading_dir) / f'{stem}.npy'} missing")
    if images_dir is not None:
        paths["image"] = img_files.get(name) or next(
            (img_files[stem + e] for e in _IMAGE_EXTS if stem + e in img_files), None)
        if paths["image"] is None:
            problems.append(f"no image {name!r} (or {stem}.png/.jpg) in {images_dir}")
    return paths


def _shading_dir(src: Path, set_name: str, shading_dir) -> Path:
    """Where the unclipped DECA shading renders are: ``shading_dir``, else the first of the preprocessing's own
    folders that exists."""
    if shading_dir is None:
        cands = [src / "rendered_images" / d / set_name for d in _SHADING_DIRS]
        shading_dir = next((c for c in cands if c.is_dir()), None)
        if shading_dir is None:
            raise UserFileNotFoundError(f"missing {cands[0]} (or {cands[1]}): unclipped DECA shading renders "
                                        f"(.npy), produced by {_PRODUCERS['shading']}")
    return Path(shading_dir)


def _wanted(encodings: Sequence[str] | None, images_dir) -> list[str]:
    """The encodings to import: those asked for (default: everything derivable; ``image`` and ``background``
    only with ``images_dir``), each one the importer makes."""
    if images_dir is None and ("image" in (encodings or ()) or "background" in (encodings or ())):
        raise UserError("encodings 'image'/'background' need images_dir (the aligned images DiFaReli processed)")
    wanted = [n for n in (encodings or _DEFAULT) if images_dir is not None or n not in ("image", "background")]
    for n in wanted:
        E.get(n)
    unknown = [n for n in wanted if n not in _DEFAULT]
    if unknown:
        raise UserError(f"the DiFaReli importer cannot produce {unknown}; it makes {list(_DEFAULT)}")
    return wanted


def _names(params: dict, seg_files: dict, shade_files: dict, img_files: dict) -> list[str]:
    """The image list: names in the first parameter file, else the files of the first spatial source
    (``anno_<stem>.png`` counts as ``<stem>.png``, as DiFaReli's loader does)."""
    if params:
        return sorted(next(iter(params.values())))
    if seg_files:
        return sorted(n[len("anno_"):] for n in seg_files if n.startswith("anno_") and n.endswith(".png"))
    return sorted(n for n in (shade_files or img_files) if not n.startswith("."))


def _dims(sources: dict[str, dict[str, Path]], params: dict, wanted: Sequence[str], shape_parts: Sequence[str],
          size) -> tuple[dict[str, int], dict[str, list[int]]]:
    """The store's dims from the data (S and D from the parameter vectors, H and W from ``size`` or the first
    record) and where each shape part lies in ``shape``."""
    first = next(iter(sources))
    dims: dict[str, int] = {}
    if "shape" in wanted:
        dims["S"] = int(sum(len(params[k][first]) for k in shape_parts))
    if "identity" in wanted:
        dims["D"] = len(params["faceemb"][first])
    if any(E.get(n).spatial for n in wanted):
        if size is not None:
            dims["H"], dims["W"] = (size, size) if isinstance(size, int) else size
        else:
            probe = _load_spatial(sources[first], None)
            dims["H"], dims["W"] = next(iter(probe.values())).shape[:2]
    layout, off = {}, 0
    for k in shape_parts if "shape" in wanted else ():
        n = len(params[k][first])
        layout[k] = [off, off + n]
        off += n
    return dims, layout


def import_difareli(
    src_root: str | os.PathLike,
    set_name: str,
    out_root: str | os.PathLike,
    images_dir: str | os.PathLike | None = None,
    *,
    encodings: Sequence[str] | None = None,
    size: int | tuple[int, int] | None = None,
    shape_parts: Sequence[str] = ("shape", "exp", "pose"),
    split: str | None = None,
    prefix: str = "ffhq",
    shading_dir: str | os.PathLike | None = None,
    overwrite: bool = False,
    strict: bool = True,
    limit: int | None = None,
    durable: bool = True,
) -> ImportReport:
    """Import one set (``train``/``valid``/...) of DiFaReli preprocessing output into the store at ``out_root``.

    ``encodings`` defaults to everything derivable (``image``/``background`` only with ``images_dir``).
    Images come from ``images_dir`` (``<name>`` as in the param files, else ``<stem>`` + .png/.jpg).
    ``size`` (int or (H, W)) resizes every spatial encoding; without it all sources must share one size.
    Records are named by image stem, carry meta ``{split, subject, source, image_name}`` (``split``
    defaults to ``set_name``, ``subject`` is the stem: FFHQ has no identity labels), and existing records are
    skipped (resume) unless ``overwrite``. With ``strict=False`` images lacking an input are skipped and
    listed in the report instead of raising.
    """
    src, wanted = Path(src_root), _wanted(encodings, images_dir)
    params_dir = src / "params" / set_name
    params = _params(params_dir, set_name, wanted, shape_parts, prefix)
    need_masks = any(n in wanted for n in ("masks", "face_mask", "background"))
    seg_dir = src / "face_segment" / set_name / "anno"
    if need_masks and not seg_dir.is_dir():
        raise UserFileNotFoundError(f"missing {seg_dir} (face-parsing label maps, produced by {_PRODUCERS['masks']})")
    shading_dir = _shading_dir(src, set_name, shading_dir) if "shading" in wanted else shading_dir
    seg_files = _listing(seg_dir) if need_masks else {}
    shade_files = _listing(shading_dir) if "shading" in wanted else {}
    img_files = _listing(Path(images_dir)) if images_dir is not None else {}
    if images_dir is not None and not img_files:
        raise UserFileNotFoundError(f"images_dir {images_dir} is missing or empty (the aligned images DiFaReli "
                                    "processed)")

    sources: dict[str, dict[str, Path]] = {}
    report_missing: dict[str, str] = {}
    for name in _names(params, seg_files, shade_files, img_files)[:limit]:
        problems = [f"no '{k}' entry in {params_dir}" for k in params if name not in params[k]]
        paths = _image_files(name, problems, seg_files if need_masks else None, seg_dir,
                             shade_files if "shading" in wanted else None, shading_dir, img_files, images_dir)
        if problems:
            if strict:
                raise UserFileNotFoundError(f"image {name!r} of set {set_name!r}: " + "; ".join(problems))
            report_missing[name] = "; ".join(problems)
        else:
            sources[name] = paths
    if not sources:
        raise UserError(f"no complete images to import from {src} set {set_name!r}")

    rids = {name: _record_id(os.path.splitext(name)[0]) for name in sources}
    if len(set(rids.values())) != len(rids):
        raise UserError("image names collide after turning them into record ids (same stem, different extension?)")

    dims, layout = _dims(sources, params, wanted, shape_parts, size)
    store_meta = {"source": "difareli", "src_root": str(src.resolve()), "shape_layout": layout,
                  "light_layout": "DECA 9x3 (SH coefficient, RGB), row-major from the 27-value anno line",
                  "mask_source": "BiSeNet 19 classes merged by difareli.official.importers.BISENET_TO_PART",
                  "shading_albedo": 180 / 255}
    store = EncodingStore.create(out_root, dims, wanted, store_meta, durable=durable)
    report = ImportReport(store=store, skipped_incomplete=report_missing)
    for name, paths in sources.items():
        if store.has(rids[name]) and not overwrite:
            report.skipped_existing.append(rids[name])
        else:
            arrays = _record_arrays(name, params, paths, wanted, shape_parts, (dims.get("H"), dims.get("W")), size)
            store.write(rids[name], arrays, {"split": split or set_name, "subject": rids[name], "source": "difareli",
                                             "image_name": name}, overwrite=overwrite)
            report.written.append(rids[name])
    log.info("imported %d records into %s (%d existing skipped, %d incomplete skipped)",
             len(report.written), out_root, len(report.skipped_existing), len(report_missing))
    return report


def _load_spatial(paths: dict[str, Path], hw: tuple[int, int] | None) -> dict[str, np.ndarray]:
    """Load this image's spatial sources, resized to ``hw`` if given; otherwise their sizes must agree."""
    out = {}
    if "image" in paths:
        out["image"] = np.asarray(Image.open(paths["image"]).convert("RGB"))
    if "masks" in paths:
        lab = np.asarray(Image.open(paths["masks"]))
        if lab.ndim == 3:  # saved as RGB by some tools; the label is in every channel
            lab = lab[..., 0]
        out["masks"] = lab.astype(np.uint8)
    if "shading" in paths:
        out["shading"] = _load_shading(paths["shading"])
    if hw is not None:
        kinds = {"image": "image", "masks": "labels", "shading": "float"}
        return {k: _resize(v, hw, kinds[k]) for k, v in out.items()}
    sizes = {k: v.shape[:2] for k, v in out.items()}
    if len(set(sizes.values())) > 1:
        raise UserError(f"spatial inputs differ in size {sizes} ({ {k: str(p) for k, p in paths.items()} }); "
                        "pass size= to resize them to one resolution")
    return out


def _record_arrays(name: str, params: dict, paths: dict[str, Path], wanted: Iterable[str],
                   shape_parts: Sequence[str], hw: tuple, size) -> dict[str, np.ndarray]:
    wanted = list(wanted)
    spatial = _load_spatial(paths, hw if size is not None else None) if paths else {}
    if size is None and spatial:
        got = next(iter(spatial.values())).shape[:2]
        if got != hw:
            raise UserError(f"image {name!r}: inputs are {got[0]}x{got[1]} but the store is {hw[0]}x{hw[1]}; "
                            "pass size= to resize")
    arrays: dict[str, np.ndarray] = {}
    if "light" in wanted:
        arrays["light"] = params["light"][name].reshape(9, 3)
    if "shape" in wanted:
        arrays["shape"] = np.concatenate([params[k][name] for k in shape_parts])
    if "cam" in wanted:
        arrays["cam"] = params["cam"][name]
    if "identity" in wanted:
        arrays["identity"] = params["faceemb"][name]
    if "shadow" in wanted:
        arrays["shadow"] = params["shadow"][name]
    if "shading" in wanted:
        arrays["shading"] = spatial["shading"]
    if "masks" in spatial:
        parts = bisenet_to_parts(spatial["masks"])
        if "masks" in wanted:
            arrays["masks"] = parts
        if "face_mask" in wanted:
            arrays["face_mask"] = np.isin(parts, [E.PART_INDEX[p] for p in E.FACE_PARTS])
        if "background" in wanted:
            fg = np.isin(parts, [E.PART_INDEX[p] for p in E.FOREGROUND_PARTS])
            arrays["background"] = np.where(fg[..., None], 0, spatial["image"]).astype(np.uint8)
    if "image" in wanted:
        arrays["image"] = spatial["image"]
    return arrays
