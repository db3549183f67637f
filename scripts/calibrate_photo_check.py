"""Calibrate the photo check's limits (``relight/photo_check.LIMITS``) against the DSSIM of relit SynthFaces photos.

SynthFaces heads of a seed no shipped model trained on are rendered at 256 px (``synth/subject.py``: the
generator's own ``build_subject`` / ``shade``, realism ``full``) and made into photos, one factor at a time away
from a clean photo (face 64 px, facing the camera, a soft light, nothing cut):

- ``size``: the render shrunk so the face (half the aligned square) spans ~128 .. 10 px, centred on a canvas of
  the render's border colour at least 192 px wide (a small face sits in a larger photo, the detector's regime);
- ``yaw`` / ``pitch``: the head turned 10 .. 60 / tilted 10 .. 50 degrees (the sign alternates between subjects);
- ``light``: the soft light replaced by a hard, coloured, over-exposed (bright), dim, grazing or rim one
  (``synth/lights.py``'s categories);
- ``crop``: the photo's top cut through the head's square (the share past the photo's edge).

Each photo goes through the product's door (``Relighter.photo_source``: preprocessing and the check), is relit by
``difareli_pp_ss-synth64`` to a directional target light, and the relit aligned crop is scored (DSSIM, paper rule)
against the ground truth: the same head and pose rendered under that light, warped by the same quad from the
full-resolution render (so a small photo is scored against the sharp face it should give), on the exact face mask
inside the photo. The target light and c are those a SynthFaces v2 store would hold (estimated on the exact
geometry). Each limit comes from :func:`difareli.relight.photo_check.choose_limit`, with its spread over the
subjects resampled; which measured limits ``LIMITS`` takes, and why the others stay provisional: docs/photos.md.

    python scripts/calibrate_photo_check.py --out runs/photo_check --subjects 48   # 1,632 photos, ~10-15 min
    python scripts/calibrate_photo_check.py --out runs/photo_check --analyse   # the rule again on photos.csv

Writes ``photos.csv`` (factors, measures, DSSIM per photo), ``limits.md`` and ``calibration.png``.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import time
import warnings
from pathlib import Path

import numpy as np

from difareli.relight.photo_check import LIMITS, choose_limit
from difareli.utils import fileio

SEED = 9100            # SynthFaces seed of the subjects: no shipped model trained on it
RENDER = 256           # render size; the aligned square spans about the whole render
NOMINAL = 128          # face_px of the 256 px render (default_camera frames the FFHQ square: half of it)
MIN_SIDE = 192         # smallest photo side: a small face sits in a larger photo, as real ones do
BASE = {"size": 64, "yaw": 0.0, "pitch": 0.0, "light": "soft", "crop": 0.0}
LEVELS = {"size": (128, 48, 40, 32, 28, 24, 20, 16, 14, 12, 10), "yaw": (10, 20, 30, 40, 50, 60),
          "pitch": (10, 20, 30, 40, 50), "light": ("hard", "coloured", "bright", "dim", "grazing", "rim"),
          "crop": (0.1, 0.2, 0.3, 0.4, 0.5)}
#: Which factor moves which measure: a limit is chosen on the clean photos and those of its factor (None: all).
MOVED_BY = {"face_px": "size", "yaw_deg": "yaw", "pitch_deg": "pitch", "light_rel_rmse": "light",
            "past_edge": "crop", "landmark_px": None}
MEASURES = ("face_px", "yaw_deg", "pitch_deg", "landmark_px", "light_rel_rmse", "past_edge")
FIELDS = ("subject", "factor", "level", "size", "yaw", "pitch", "light", "crop", "status", *MEASURES,
          "dssim", "mse", "verdict")


def plan(k: int) -> list[dict]:
    """The photos of subject ``k``: the clean one, then each factor's levels with the others clean."""
    sign = 1.0 if k % 2 == 0 else -1.0
    rows = [{"subject": k, "factor": "clean", "level": "", **BASE}]
    for factor, levels in LEVELS.items():
        for level in levels:
            value = sign * level if factor in ("yaw", "pitch") else level
            rows.append({"subject": k, "factor": factor, "level": level, **{**BASE, factor: value}})
    return rows


def _target_light(k: int):
    # A directional light from the side (cast shadows, a real relight), the same for every photo of a subject.
    from difareli.synth.lights import Light, ambient_sh, direction

    rng = np.random.default_rng([SEED, k, 8])
    az = (1 if k % 2 == 0 else -1) * rng.uniform(35, 60)  # from the side the head does not turn to
    return Light("target", ambient_sh(rng, rng.uniform(0.4, 0.6), gradient=0.3, band2=0.1),
                 direction(az, rng.uniform(10, 35)), np.full(3, rng.uniform(0.6, 0.9)))


def render_pose(k: int, pose: tuple[float, float], categories: list[str]) -> dict:
    """Subject ``k`` at (yaw, pitch): its image under each light category, and under the target light its image,
    the exact face mask and the target light and c a SynthFaces v2 store would hold."""
    from difareli.render import cast_shadows
    from difareli.synth.config import SynthConfig
    from difareli.synth.lights import sample_light
    from difareli.synth.subject import build_subject, shade

    cfg = SynthConfig(subjects=k + 1, lights=1, resolution=RENDER, seed=SEED, realism="full", inputs="exact")
    subject = build_subject(k, cfg, pose=(pose[0], pose[1], 0.0))
    lights = [sample_light(np.random.default_rng([SEED, k, 7, i]), c) for i, c in enumerate(categories)]
    lights.append(_target_light(k))
    dirs = [d for light in lights for d, _ in light.suns()]
    maps = list(cast_shadows(subject.scene, subject.gbuffer, np.array(dirs))) if dirs else []
    out = {}
    for name, light in zip([*categories, "target"], lights):
        n = len(light.suns())
        casts, maps = maps[:n], maps[n:]
        mode = dataclasses.replace(cfg, inputs="estimated_light") if name == "target" else cfg
        arrays, _ = shade(subject, light, casts, mode)
        out[name] = arrays["image"]
        if name == "target":
            out["face_mask"] = np.asarray(arrays["face_mask"], np.uint8) * 255
            out["light"], out["c"] = np.asarray(arrays["light"]), float(arrays["shadow"][0])
    return out


def photo_geometry(size: float, crop: float) -> tuple[int, int, float]:
    """(pad, cut, scale): the 256 px render padded by ``pad`` px each side, its top ``cut`` rows dropped, then
    scaled by ``scale`` so the face spans ``size`` px and the photo at least :data:`MIN_SIDE`."""
    scale = float(size) / NOMINAL
    pad = max(RENDER // 2, math.ceil((MIN_SIDE / scale - RENDER) / 2))
    return pad, (pad + round(crop * RENDER)) if crop > 0 else 0, scale


def padded(image: np.ndarray, pad: int) -> np.ndarray:
    """``image`` on a canvas ``pad`` px wider each side, of the median colour of its border (a plain backdrop:
    replicated or mirrored edges draw poles and second faces)."""
    import cv2

    edge = np.concatenate([image[0], image[-1], image[:, 0], image[:, -1]])
    fill = [int(v) for v in np.median(edge.reshape(-1, image.shape[-1]), axis=0)] if image.ndim == 3 else 0
    return cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=fill)


def make_photo(image: np.ndarray, pad: int, cut: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The photo (uint8) and the (sx, sy) that map its continuous coordinates back to the padded render's."""
    import cv2

    full = padded(image, pad)[cut:]
    h, w = full.shape[:2]
    nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
    photo = cv2.resize(full, (nw, nh), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    return photo, np.array([nw / w, nh / h])


def score_photo(relighter, photo: np.ndarray, back: np.ndarray, cut: int, pad: int, truth: dict, what: str) -> dict:
    """The check's measures of one photo and the DSSIM / MSE of its relight against the ground truth."""
    import torch

    from difareli.estimators.align import warp_quad
    from difareli.evaluation import metrics
    from difareli.relight.targets import Targets

    src = relighter.photo_source(photo, what=what)
    relit = relighter.relight(src, Targets.of([truth["light"]], [truth["c"]], what=what))[0]
    size = relit.shape[0]
    quad = src.photo.quad / back + [0.0, cut]  # photo -> padded full-resolution render coordinates
    gt = warp_quad(padded(truth["target"], pad), quad, size)
    mask = (warp_quad(padded(truth["face_mask"], pad), quad, size, border="zeros") > 127) & src.photo.inside
    pred, target = metrics.unit_tensor(relit), metrics.unit_tensor(gt)
    m = torch.from_numpy(mask)[None]
    return {**src.check.measures, "dssim": float(metrics.dssim(pred, target, m)[0]),
            "mse": float(metrics.masked_mse(pred, target, m)[0]), "verdict": "ok" if src.check.ok else "poor"}


def run(out: Path, subjects: int) -> None:
    """Render, relight and score every photo of ``subjects`` subjects, appended to photos.csv as they come (a
    rerun skips the photos already there)."""
    from difareli.errors import UserError
    from difareli.relight.relighter import Relighter

    relighter = Relighter("difareli_pp_ss-synth64")
    path = out / "photos.csv"
    done = {(r["subject"], r["factor"], r["level"]) for r in read_rows(path)} if path.exists() else set()
    for k in range(subjects):
        todo = [p for p in plan(k) if (str(k), p["factor"], str(p["level"])) not in done]
        poses: dict[tuple[float, float], list[dict]] = {}
        for p in todo:
            poses.setdefault((p["yaw"], p["pitch"]), []).append(p)
        for pose, photos in poses.items():
            start = time.perf_counter()
            truth = render_pose(k, pose, sorted({p["light"] for p in photos}))
            for p in photos:
                pad, cut, scale = photo_geometry(p["size"], p["crop"])
                photo, back = make_photo(truth[p["light"]], pad, cut, scale)
                what = f"s{k} {p['factor']} {p['level']}"
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        row = {**p, "status": "ok", **score_photo(relighter, photo, back, cut, pad, truth, what)}
                except UserError as e:  # no face found: counted, not scored
                    row = {**p, "status": f"refused: {str(e)[:80]}"}
                append_row(path, row)
            print(f"subject {k} pose {pose}: {len(photos)} photo(s) in {time.perf_counter() - start:.1f} s",
                  flush=True)


def read_rows(path: Path) -> list[dict]:
    """The rows of a photos.csv (strings)."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def append_row(path: Path, row: dict) -> None:
    """One photo's row appended to photos.csv (the header first), whole or not at all: a killed run keeps what it
    measured."""
    fileio.append_csv_row(path, FIELDS, {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})


def _limit(rows: list[dict], name: str, margin: float, bin_size: int) -> float | None:
    worse = "lower" if name == "face_px" else "higher"
    return choose_limit([float(r[name]) for r in rows], [r["excess"] for r in rows], 0.0, margin=margin,
                        worse=worse, bin_size=bin_size)


def analyse(rows: list[dict], margin: float, bin_size: int, resamples: int = 200) -> dict[str, dict]:
    """Per measure: the photos the rule reads, the chosen limit, its spread over subjects resampled with
    replacement (10th-90th percentile, and the share of resamples without a limit) and the DSSIM excess either
    side. The excess is a photo's DSSIM less its subject's clean photo's: the clean photos alone span 0.05-0.16
    over subjects, more than most factors move it."""
    clean = {r["subject"]: float(r["dssim"]) for r in rows if r["status"] == "ok" and r["factor"] == "clean"}
    scored = [{**r, "excess": float(r["dssim"]) - clean[r["subject"]]} for r in rows
              if r["status"] == "ok" and r["subject"] in clean]
    subjects = sorted(clean)
    rng = np.random.default_rng(0)
    draws = [rng.choice(len(subjects), len(subjects)) for _ in range(resamples)]
    out = {}
    for name, factor in MOVED_BY.items():
        used = [r for r in scored if r.get(name) not in (None, "") and (factor is None or r["factor"] in
                                                                          ("clean", factor))]
        by_subject = {s: [r for r in used if r["subject"] == s] for s in subjects}
        limit = _limit(used, name, margin, bin_size)
        boot = [_limit([r for i in d for r in by_subject[subjects[i]]], name, margin, bin_size) for d in draws]
        found = np.array([b for b in boot if b is not None])
        v = np.array([float(r[name]) for r in used])
        e = np.array([r["excess"] for r in used])
        past = (v < limit if name == "face_px" else v > limit) if limit is not None else np.zeros(len(v), bool)
        out[name] = {"factor": factor or "all", "n": len(v), "limit": limit, "values": v, "excess": e,
                     "spread": tuple(np.percentile(found, [10, 90])) if len(found) else None,
                     "none": 1.0 - len(found) / resamples, "factors": [r["factor"] for r in used],
                     "within": float(np.median(e[~past])) if (~past).any() else float("nan"),
                     "past": float(np.median(e[past])) if past.any() else float("nan"), "n_past": int(past.sum()),
                     "clean": float(np.median(list(clean.values())))}
    return out


def write_report(out: Path, rows: list[dict], result: dict, margin: float, bin_size: int) -> None:
    """limits.md (the rule, per-measure limits, per-factor medians) and calibration.png."""
    scored = [r for r in rows if r["status"] == "ok"]
    clean = next(iter(result.values()))["clean"]
    lines = [f"{len(rows)} photos of {len({r['subject'] for r in rows})} subjects (SynthFaces seed {SEED}), "
             f"{len(scored)} relit and scored, {len(rows) - len(scored)} refused (no face found); clean photos' "
             f"median DSSIM {clean:.4f}.",
             f"Rule: a photo's excess = its DSSIM less its subject's clean photo's; the photos sorted by the measure "
             f"from good to bad in bins of {bin_size}; the limit is where the final run of bins whose median excess "
             f"exceeds {margin} begins (midway between that bin's first photo and the one before). Spread: the "
             "limit over subjects resampled with replacement (10th-90th percentile; share with no limit).", "",
             "| measure | photos read | in LIMITS | limit measured | spread (no limit) | median excess within "
             "| past (n) |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, r in result.items():
        lim = "none in the data" if r["limit"] is None else f"{r['limit']:.3g}"
        spread = "-" if r["spread"] is None else f"{r['spread'][0]:.3g}-{r['spread'][1]:.3g}"
        lines.append(f"| {name} | {r['n']} (clean + {r['factor']}) | {LIMITS[name][0]:g} | {lim} | {spread} "
                     f"({r['none']:.0%}) | {r['within']:+.4f} | {r['past']:+.4f} ({r['n_past']}) |")
    lines += ["", "| factor | level | photos | median DSSIM | " + " | ".join(MEASURES) + " |",
              "|---|---|---:|---:|" + "---:|" * len(MEASURES)]
    for factor in ["clean", *LEVELS]:
        for level in sorted({r["level"] for r in scored if r["factor"] == factor}, key=_level_key):
            sel = [r for r in scored if r["factor"] == factor and r["level"] == level]
            n_all = sum(r["factor"] == factor and r["level"] == level for r in rows)
            med = [np.median([float(r[m]) for r in sel if r.get(m) not in (None, "")] or [np.nan]) for m in MEASURES]
            lines.append(f"| {factor} | {level} | {len(sel)} of {n_all} | "
                         f"{np.median([float(r['dssim']) for r in sel]):.4f} | " + " | ".join(f"{v:.3g}" for v in med)
                         + " |")
    (out / "limits.md").write_text("\n".join(lines) + "\n")
    plot(out / "calibration.png", result, margin, bin_size)


def _level_key(level: str):
    try:
        return (0, float(level))
    except ValueError:
        return (1, level)


def plot(path: Path, result: dict, margin: float, bin_size: int) -> None:
    """DSSIM excess against each measure, coloured by factor, the bins' medians, the margin and the limits."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"clean": "k", "size": "tab:blue", "yaw": "tab:orange", "pitch": "tab:green", "light": "tab:red",
               "crop": "tab:purple"}
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5))
    for ax, (name, r) in zip(axes.ravel(), result.items()):
        for f in dict.fromkeys(r["factors"]):
            sel = np.array([x == f for x in r["factors"]])
            ax.scatter(r["values"][sel], r["excess"][sel], s=6, alpha=0.5, c=colours.get(f, "grey"), label=f)
        order = np.argsort(-r["values"] if name == "face_px" else r["values"], kind="stable")
        v, e = r["values"][order], r["excess"][order]
        edges = [i * bin_size for i in range(max(1, len(v) // bin_size))] + [len(v)]
        ax.plot([np.median(v[a:b]) for a, b in zip(edges[:-1], edges[1:])],
                [np.median(e[a:b]) for a, b in zip(edges[:-1], edges[1:])], "k-", lw=1.2, label="bin median")
        ax.axhline(margin, color="grey", lw=0.8, ls=":")
        ax.axvline(LIMITS[name][0], color="grey", lw=1, ls="--", label="in LIMITS")
        if r["limit"] is not None:
            ax.axvline(r["limit"], color="crimson", lw=1.5, label="measured")
        ax.set_xscale("log" if name == "face_px" else "linear")
        ax.set_xlabel(name)
        ax.set_ylabel("DSSIM - subject's clean photo's")
        ax.set_ylim(-0.1, 0.25)
        ax.legend(fontsize=6, ncol=2)
    fig.suptitle("Photo check calibration: relight DSSIM excess against each measure (dotted: the margin)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=60)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--subjects", type=int, default=48)
    ap.add_argument("--margin", type=float, default=0.02, help="DSSIM above the subject's clean photo's")
    ap.add_argument("--bin-size", type=int, default=16)
    ap.add_argument("--analyse", action="store_true", help="only the rule and report, on an existing photos.csv")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.analyse:
        run(args.out, args.subjects)
    rows = read_rows(args.out / "photos.csv")  # one form (strings) for a fresh run and a re-analysis
    result = analyse(rows, args.margin, args.bin_size)
    write_report(args.out, rows, result, args.margin, args.bin_size)
    print((args.out / "limits.md").read_text())


if __name__ == "__main__":
    main()
