"""Quality of cast-shadow maps against SynthFaces' exact ones: IoU / precision / recall per record and
on average for

- ``difference``: derived difference-method versions (``--version [LABEL=]VERSION``, repeatable: one row each,
  e.g. the maps of DiFaReli checkpoints at several training steps),
- ``ray-marched``: screen-space ray marching on the stored depth toward the record's fitted light
  (``retarget.target_shadow_map``), and toward the exact light (``light_gt``, where stored: an oracle light),
- ``mesh``: the store's own ``shadow_map`` (SynthFaces ``inputs=estimated``: mesh rays toward the fitted light, on
  the estimated surface in v3; in an ``inputs=exact`` store it is the ground truth itself, flagged),
- ``ray-marched on the exact depth toward the exact key sun`` (SynthFaces v3 stores): the same march
  (``retarget.target_shadow_map``, stored normals applied after it as ``retarget.cast_shadows`` does) on the exact
  depth toward the key sun's direction from the record's header (empty without a sun, as the upper bound): what
  the screen-space march itself loses against mesh ray casting, with no light or geometry estimation error,
- ``ray-marched on the exact depth toward every exact sun, visibly shadowed`` (SynthFaces stores with suns in
  their headers): the relight's maker given the record's exact light as suns (``lighting.suns.Suns.from_header``:
  key, fill, rim, the ambient being ``light_gt`` less theirs), each pixel kept when the suns it cannot see carry
  more than ``render.visible.MARCH_VISIBLE`` of its light or it is in the key sun's cast shadow: what
  ``difareli-shadow-maps maker=march light=exact`` trains on,
- ``key sun, exact mesh (upper bound)`` (SynthFaces v3 stores): the subject re-built and its exact mesh ray cast
  toward the exact key-sun direction; equal to the GT on single-sun records, whose score is printed apart,
- ``whole face (baseline)``: every mesh pixel (the exact mesh where ``depth_gt`` is stored), the score of a map
  that covers the whole face,

each binarised as ``map > 0`` against the visibly-shadowed mask ``shadow_visible_gt`` (SynthFaces v3's ground truth:
the pixels losing more than the store's ``shadow_visible`` share of their light, or in the key sun's cast shadow),
else ``shadow_map_gt > 0`` (v2), else ``shadow_map`` (v1). Records whose GT
and prediction are both empty have no IoU (counted apart); the pooled IoU counts every pixel of every record once.
Only records that hold every given version are scored. Writes ``shadow_map_quality.md`` / ``.csv`` and a figure
(image | GT | each method) for the first records.

    python scripts/shadow_map_quality.py --store data/synthfaces_64 --version diff-1a2b3c4d --out runs/maps
    python scripts/shadow_map_quality.py --store ... --version step1000=diff-aaaa --version step3500=diff-bbbb
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from difareli.data import derived
from difareli.utils import viz
from difareli.evaluation.metrics import binary_scores
from difareli.data.store import EncodingStore
from difareli.lighting import sh
from difareli.lighting.suns import Suns, sun_direction
from difareli.render import sun_fit
from difareli.render.camera import OrthoCamera
from difareli.render.visible import visible_march
from difareli.render.retarget import target_shadow_map

#: The row of a map covering every mesh pixel: scored, not drawn in the figure.
BASELINE = "whole face (baseline)"
UPPER = "key sun, exact mesh (upper bound)"
KEY_MARCH = "ray-marched on the exact depth toward the exact key sun"
SUNS_MARCH = "ray-marched on the exact depth toward every exact sun, visibly shadowed"


class KeySun:
    """The key sun's cast mask on the exact mesh of a SynthFaces record (the subject re-built from the header)."""

    def __init__(self, store: EncodingStore):
        from dataclasses import fields, replace

        from difareli.synth.config import SynthConfig

        meta = store.store_meta
        cfg = SynthConfig(**{f.name: meta[f.name] for f in fields(SynthConfig) if f.name in meta})
        self.cfg = replace(cfg, realism="lambertian", effects={}, inputs="exact")  # geometry only: same draws
        self.store, self.cache = store, {}

    def __call__(self, rid: str) -> tuple[np.ndarray, bool]:
        from difareli.render import cast_shadow
        from difareli.synth.subject import build_subject

        m = self.store.meta(rid)
        k = int(m["subject"].lstrip("s"))
        if k not in self.cache:
            self.cache = {k: build_subject(k, self.cfg)}
        sub = self.cache[k]
        single = not any(np.any(np.asarray(e["rgb"]) > 0) for e in m.get("extra_suns", []))
        if not np.any(np.asarray(m["sun_rgb"]) > 0):
            return np.zeros_like(sub.gbuffer.hit), single
        return cast_shadow(sub.scene, sub.gbuffer, np.asarray(m["sun_dir"])) & sub.gbuffer.hit, single


def key_sun_march(g: dict, meta: dict) -> np.ndarray:
    """The march on the geometry ``g`` (depth, normal, cam) toward a record's key sun (``sun_dir`` in its header),
    as the relighting targets make it (``target_shadow_map`` given that one sun and no ambient: its cast map); an
    empty map without a sun, as :class:`KeySun`."""
    if not np.any(np.asarray(meta["sun_rgb"]) > 0):
        return np.zeros(np.shape(g["depth"]), bool)
    key = Suns(np.asarray(meta["sun_dir"], dtype=np.float64)[None], np.ones((1, 3)), np.zeros((9, 3)))
    return target_shadow_map(g, key, 0.0, (-10.0, 10.0)) > 0  # one sun, no ambient: its cast map


def parse_versions(specs: list[str]) -> dict[str, str]:
    """``["a=diff-1", "diff-2"]`` -> ``{"difference (a)": "diff-1", "difference": "diff-2"}``."""
    out = {}
    for s in specs:
        label, _, version = s.rpartition("=")
        out[f"difference ({label})" if label else "difference"] = version
    return out


def gt_name(store: EncodingStore) -> str:
    for name in ("shadow_visible_gt", "shadow_map_gt", "shadow_map"):
        if store.available(name):
            return name
    raise KeyError(f"store {store.root} has no shadow map")


def maps_of(store: EncodingStore, rid: str, versions: dict[str, str], light_name: str,
            key_sun: KeySun | None = None, cuts: tuple[float, ...] = ()) -> dict[str, np.ndarray]:
    """The binary maps of one record: GT, then each method."""
    gt = gt_name(store)
    lights = [light_name] + (["light_gt"] if light_name != "light_gt" and store.available("light_gt") else [])
    mesh = "depth_gt" if store.available("depth_gt") else "depth"
    exact_geo = [f"{k}_gt" for k in ("depth", "normal", "cam")] if store.available("depth_gt") else []
    found = [k for k in sun_fit.ENCODINGS if store.available(k)]
    a = {k: np.asarray(v) for k, v in store.read(rid, sorted({"depth", "normal", "cam", gt, "shadow_map", mesh,
                                                                *lights, *exact_geo, *found})).items()}
    out = {"gt": a[gt] > 0}
    for label, version in versions.items():
        name = f"shadow_map@{version}"
        out[label] = np.asarray(store.read(rid, [name])[name]) > 0
    for name in lights:  # c = 0 inside the range: only the support matters
        label = "ray-marched" if name == light_name else "ray-marched toward the exact light (oracle)"
        out[label] = target_shadow_map(a, a[name], 0.0, (-10.0, 10.0)) > 0
        # The same light's sun found from this image's cast shadows (what a relight toward a photo's light marches).
        sun = Suns.of_sh(a[name], sun_fit.fit_sun(a, a[name]).direction)
        out[f"{label}, its sun found from the image's cast shadows"] = target_shadow_map(a, sun, 0.0, (-10.0, 10.0)) > 0
    if exact_geo and "light_gt" in a:  # what the estimated geometry costs: the same march on the exact one
        g = {k: a[f"{k}_gt"] for k in ("depth", "normal", "cam")}
        out["ray-marched on the exact depth toward the exact light (oracle)"] = \
            target_shadow_map(g, a["light_gt"], 0.0, (-10.0, 10.0)) > 0
    out["mesh"] = a["shadow_map"] > 0
    if key_sun is not None:
        g = {k: a[f"{k}_gt"] for k in ("depth", "normal", "cam")} if exact_geo else a
        out[KEY_MARCH] = key_sun_march(g, store.meta(rid))
        suns = Suns.from_header(store.meta(rid), a["light_gt"]) if "light_gt" in a else None
        out[SUNS_MARCH] = (target_shadow_map(g, suns, 0.0, (-10.0, 10.0)) > 0 if suns is not None
                           else np.zeros_like(out[KEY_MARCH]))
        cam = OrthoCamera(*np.asarray(g["cam"], np.float64).tolist())
        for cut in cuts:  # the same maker at other cuts on the share of light (choosing MARCH_VISIBLE)
            out[f"{SUNS_MARCH} at {cut:g}"] = (visible_march(g["depth"], np.asarray(g["normal"], np.float64), cam,
                                                             suns, cut) if suns is not None
                                               else np.zeros_like(out[KEY_MARCH]))
        out[UPPER], _ = key_sun(rid)
    out[BASELINE] = a[mesh] != 0  # every mesh pixel: the IoU a map earns by covering all
    return out


def direction_errors(store: EncodingStore, rid: str, light_names: list[str]) -> dict[str, float]:
    """Degrees from a record's key sun (its header) to the direction each SH light is marched toward
    (``sun_direction``: the radiance peak) and to band 1's (``sh.dominant_direction``); {} without a sun."""
    meta = store.meta(rid)
    if not np.any(np.asarray(meta.get("sun_rgb", 0)) > 0):
        return {}
    key = np.asarray(meta["sun_dir"], np.float64)
    key /= np.linalg.norm(key)
    out = {}
    arrays = store.read(rid, [k for k in sun_fit.ENCODINGS if store.available(k)])
    for name in light_names:
        light = np.asarray(store.read(rid, [name])[name], np.float64)
        for how, d in (("radiance peak", sun_direction(light)), ("band 1", sh.dominant_direction(light)),
                       ("found from the cast shadows", sun_fit.fit_sun(arrays, light).direction)):
            out[f"{name}, {how}"] = float(np.degrees(np.arccos(np.clip(d @ key, -1.0, 1.0))))
    return out


def summary_lines(per: dict[str, list[dict]], pooled: dict[str, np.ndarray], exact_store: bool) -> list[str]:
    """Markdown rows: mean IoU / precision / recall over records, pooled IoU, records with an IoU."""
    lines = ["| method | IoU | precision | recall | pooled IoU | records with IoU |", "|---|---:|---:|---:|---:|---:|"]
    for method, rs in per.items():
        col = {k: np.array([r[k] for r in rs]) for k in ("iou", "precision", "recall")}
        mean = {k: np.nanmean(v) if np.isfinite(v).any() else float("nan") for k, v in col.items()}
        inter, union = pooled[method]
        note = " (= the GT: exact-inputs store)" if method == "mesh" and exact_store else ""
        lines.append(f"| {method}{note} | {mean['iou']:.3f} | {mean['precision']:.3f} | {mean['recall']:.3f} | "
                     f"{inter / max(union, 1):.3f} | {int(np.isfinite(col['iou']).sum())} |")
    return lines


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True)
    ap.add_argument("--version", action="append", default=[],
                    help="[LABEL=]VERSION of difference maps (difareli-shadow-maps); repeatable")
    ap.add_argument("--split", default=None, help="only this split's records (default: all)")
    ap.add_argument("--light", default="light", help="light the ray-marched map aims at: light (a user's) | light_gt")
    ap.add_argument("--every", type=int, default=1, help="score every N-th record only (a quick look)")
    ap.add_argument("--region", choices=("all", "face"), default="all",
                    help="face: GT and every map restricted to the exact face parts (face_mask_gt, else face_mask), "
                         "where the difference recipe's maps live")
    ap.add_argument("--visible", type=float, nargs="*", default=[],
                    help="also score the march toward every sun at these cuts on the share of light (e.g. on the "
                         "val split: 0.05 0.1 0.15 0.2 0.25 0.3)")
    ap.add_argument("--figure-rows", type=int, default=8)
    ap.add_argument("--out", default=".")
    args = ap.parse_args(argv)
    store = EncodingStore.open(args.store)
    versions = parse_versions(args.version)
    for version in versions.values():
        if f"shadow_map@{version}" not in store.derived:
            ap.error(f"--version {version}: store {store.root} has no shadow_map@{version}; declared: "
                     f"{sorted(store.derived)}")
    ids = store.ids(split=args.split) if args.split else store.ids()
    ids = [r for r in ids if all(derived.has(store, r, f"shadow_map@{v}") for v in versions.values())][::args.every]
    if not ids:
        ap.error(f"no record of {store.root} holds every given version; run difareli-shadow-maps first")
    exact_store = store.store_meta.get("inputs", "exact") == "exact" or not store.available("shadow_map_gt")
    key_sun = KeySun(store) if store.available("shadow_visible_gt") else None
    fm = "face_mask_gt" if store.available("face_mask_gt") else "face_mask"
    single: list[float] = []
    angles: dict[str, list[float]] = {}
    light_names = [n for n in ("light", "light_gt") if store.available(n)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, fig, per, pooled = [], [], {}, {}
    for rid in ids:
        m = maps_of(store, rid, versions, args.light, key_sun, tuple(args.visible))
        if args.region == "face":
            face = np.asarray(store.read(rid, [fm])[fm], bool)
            m = {k: v & face for k, v in m.items()}
        if key_sun is not None and key_sun(rid)[1]:
            single.append(float(binary_scores(m[UPPER][None], m["gt"][None])["iou"][0]))
        for k, v in direction_errors(store, rid, light_names).items():
            angles.setdefault(k, []).append(v)
        for method in [k for k in m if k != "gt"]:
            s = binary_scores(m[method][None], m["gt"][None])
            rows.append({"record": rid, "method": method, **{k: float(v[0]) for k, v in s.items()}})
            per.setdefault(method, []).append(rows[-1])
            inter, union = pooled.get(method, (0, 0))
            pooled[method] = (inter + int((m[method] & m["gt"]).sum()), union + int((m[method] | m["gt"]).sum()))
        if len(fig) < args.figure_rows:
            image = np.asarray(store.read(rid, ["image"])["image"])
            cells = [image] + [np.repeat((m[k] * 255).astype(np.uint8)[..., None], 3, -1) for k in m
                               if k != BASELINE]
            fig.append(cells)
    with open(out / "shadow_map_quality.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["record", "method", "iou", "precision", "recall"])
        w.writeheader()
        w.writerows(rows)
    where = (f"split {args.split}" if args.split else "all splits") + ("" if args.region == "all" else
                                                                        f", restricted to {fm}")
    lines = [f"Shadow-map quality on {store.root} ({len(ids)} records of {where}; binary maps > 0 vs the "
             f"GT {gt_name(store)})", ""] + summary_lines(per, pooled, exact_store)
    if single:
        lines.append(f"\n{UPPER} on the {len(single)} single-sun records: IoU {np.nanmean(single):.3f} "
                     f"(records with an IoU: {int(np.isfinite(single).sum())})")
    if angles:
        lines.append("\nDegrees from the key sun (median over the records with one): " + "; ".join(
            f"{k} {np.median(v):.1f}" for k, v in angles.items()))
    if "shadow_visible" in store.store_meta:
        lines.append(f"GT: shadow_visible_gt, share of a pixel's light removed > {store.store_meta['shadow_visible']} "
                     "or in the key sun's cast shadow")
    for label, version in versions.items():
        prov = store.derived[f"shadow_map@{version}"]
        keys = ("global_step", "sampler", "threshold", "threshold_rule", "median", "c_min", "c_max")
        show = {k: prov[k] for k in keys if k in prov}
        if isinstance(show.get("sampler"), dict):
            show["sampler"] = f"{show['sampler'].get('name')}-{show['sampler'].get('steps')}"
        lines.append(f"\n{label} = shadow_map@{version}: " + ", ".join(f"{k} {v}" for k, v in show.items()))
    shown = [k for k in per if k != BASELINE]
    text = "\n".join(lines) + "\n\nFigure columns: image | GT | " + " | ".join(shown) + "\n"
    (out / "shadow_map_quality.md").write_text(text)
    if fig:
        viz.save_png(viz.grid(fig), out / "shadow_map_quality.png")
    print(text)


if __name__ == "__main__":
    main()
