"""Where the bright patch on the nose bridge and forehead under a named light comes from (issue 61): one photo's
relight taken apart stage by stage, beside the Lambertian ratio relight of the same crop under the same light.

    nice -n 19 env OMP_NUM_THREADS=1 .venv/bin/python scripts/photo_patch_trace.py --photos astronaut_112 astronaut \
        --sheet docs/images/photo_patch_trace.png

Per photo and light, on the face's pixels with an estimated normal, the patch is the tenth of them that the target
light lights most (its irradiance E_t on the estimated normals over the face's mean). Printed: how much brighter (log,
patch mean less face mean) each stage makes the patch: the target light's own change log(E_t / E_s), the Lambertian
relight over the aligned crop, the model's relight over the aligned crop (what the ratio composite multiplies the
photo by) and over the model's own reconstruction (a composite that cancels the model's bias); and the target
light's face contrast (max / min of E_t). The sheet: per photo, the crops (aligned, relit, Lambertian) and the maps.
"""

from __future__ import annotations

import argparse

import numpy as np

from difareli.evaluation import photo_path as pp
from difareli.evaluation import photo_presets as pr
from difareli.lighting import sh
from difareli.lighting.light_fit import face_normals
from difareli.relight.relighter import Relighter
from difareli.utils import viz

Y = np.array([0.2126, 0.7152, 0.0722])


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default=pp.DEFAULT_CHECKPOINT)
    ap.add_argument("--photos", nargs="*", default=["astronaut_112", "astronaut"])
    ap.add_argument("--targets", nargs="*", default=["top", "rim", "sunset", "front"])
    ap.add_argument("--sheet", default=None, help="write the stages sheet of the first photo here")
    return ap.parse_args()


def grey(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return (np.repeat(np.clip((x - lo) / (hi - lo), 0, 1)[..., None], 3, -1) * 255).astype(np.uint8)


def stages(source, relit, names):
    """The stages as luminance logs on the crop: (log E_t/E_s, log lam/aligned, log relit/aligned, log relit/own),
    E_t / its face mean, the face's known-normal mask and the crops."""
    a = source.arrays
    lights = np.asarray(relit.targets.lights, np.float64)
    crops = np.stack([np.asarray(x) for x in relit]).astype(np.float64)
    lam = pp.lambertian_crops(source, lights).astype(np.float64)
    normals, known = face_normals({"normal": a["normal"]})
    e = np.stack([sh.irradiance(x, normals) @ Y for x in lights])
    aligned = np.asarray(a["image"], np.float64)
    lum = lambda im: im @ Y + 4.0  # noqa: E731  (4/255 of the composite's eps, in 0-255 units)
    logs = np.stack([np.log(np.maximum(e, 1e-3) / np.maximum(e[:1], 1e-3)), np.log(lum(lam) / lum(aligned)),
                     np.log(lum(crops) / lum(aligned)), np.log(lum(crops) / lum(crops[:1]))])
    rel = e / np.stack([x[known].mean() for x in e])[:, None, None]
    return logs, rel, known, crops.astype(np.uint8), lam.astype(np.uint8), aligned.astype(np.uint8)


def main() -> None:
    args = parse()
    relighter = Relighter(args.checkpoint, progress=False)
    print("photo target contrast(E_t max/min) | patch - face, log: E_t/E_s lambert/aligned relit/aligned relit/own")
    for i, name in enumerate(args.photos):
        photo = next(p for p in pr.PHOTOS if p.name == name)
        source, relit = pr.relight_photo(relighter, photo, args.targets)
        logs, rel, known, crops, lam, aligned = stages(source, relit, args.targets)
        for k, target in enumerate(args.targets, start=1):
            face = rel[k][known]
            patch = known & (rel[k] >= np.quantile(face, 0.9))
            d = [float(x[k][patch].mean() - x[k][known].mean()) for x in logs]
            print(f"{name} {target} {face.max() / face.min():.2f} | " + " ".join(f"{v:+.3f}" for v in d))
        if i == 0 and args.sheet:
            blank = np.zeros_like(aligned)
            log_rows = [[blank, *(grey(x * known, -1, 1) if j == 0 else grey(x, -1, 1) for x in s)]
                        for j, s in enumerate(logs)]
            rows = [[aligned, *crops], [aligned, *lam], *log_rows, [blank, *(grey(r * known, 0, 2) for r in rel)]]
            sheet = viz.grid([[viz.enlarge(x, 160) for x in r] for r in rows], col_labels=["aligned", "own",
                             *args.targets], row_labels=["relit", "Lambertian", "log E_t/E_s", "log lam/aligned",
                                                         "log relit/aligned", "log relit/own", "E_t/face mean"])
            print(viz.save_png(sheet, args.sheet))


if __name__ == "__main__":
    main()
