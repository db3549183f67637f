"""The docs' pictures of the app, a photo's rotation and the demo, regenerated with today's code in one command
(issue 61: they must not show the masks of an older code).

    nice -n 19 env OMP_NUM_THREADS=1 .venv/bin/python scripts/regenerate_images.py            # every picture
    .venv/bin/python scripts/regenerate_images.py --only rotation --checkpoint difareli_pp_ss-synth64

Writes into --out (docs/images):

- app_gallery.png, app_before_after.png: difareli-app in headless Chromium (tests/app/test_browser.py with
  DIFARELI_SCREENSHOTS; needs `apt-get install -y chromium chromium-driver`, selenium and the photo estimators);
- photo_rotation_yaw.png: scikit-image's astronaut relit by --checkpoint under a 360-degree yaw rotation of its
  own light (the path of `difareli-relight image=... video.axis=yaw`: rotation_video, then the composite into the
  whole photo), every frame's face window of the composited 512 px photo, captioned with its angle;
- demo_comparison.png, demo_rotation_yaw.png, demo_astronaut.png: `difareli-demo`'s pictures (its default model).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
PARTS = ("app", "rotation", "demo")
DEMO_FILES = {"comparison.png": "demo_comparison.png", "rotation_yaw.png": "demo_rotation_yaw.png",
              "astronaut.png": "demo_astronaut.png"}


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "docs" / "images"))
    ap.add_argument("--only", nargs="*", choices=PARTS, default=list(PARTS))
    ap.add_argument("--checkpoint", default="difareli_pp-synth64", help="the photo rotation's model (difareli-"
                    "relight's default: the diffusion model)")
    ap.add_argument("--frames", type=int, default=12, help="the photo rotation's frames over 360 degrees")
    return ap.parse_args()


def run(cmd: list[str], env: dict[str, str] | None = None) -> None:
    """``cmd`` run from the repository's root; its failure stops the script with the command named."""
    print("$", " ".join(cmd), flush=True)
    done = subprocess.run(cmd, cwd=ROOT, env={**os.environ, **(env or {})})
    if done.returncode:
        sys.exit(f"regenerate_images: `{' '.join(cmd)}` failed (exit {done.returncode}); see its output above")


def app(out: Path) -> None:
    """The browser test saves the app's two screenshots into ``out``; a skip (no Chromium ...) is a failure here."""
    run([str(BIN / "pytest"), "-q", "-m", "slow", "-rs", "-p", "no:cacheprovider",
         "tests/app/test_browser.py"], env={"DIFARELI_SCREENSHOTS": str(out)})
    for name in ("app_gallery.png", "app_before_after.png"):
        if not (out / name).is_file():
            sys.exit(f"regenerate_images: the browser test wrote no {out / name} (skipped? see its reason above)")


def request_config(overrides: list[str], out_dir: Path):
    """``conf/relight.yaml`` composed with ``overrides`` as ``difareli-relight`` composes it (Hydra's live config
    for its ``${hydra:...}`` values), writing into ``out_dir``."""
    from hydra import compose, initialize_config_dir
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict

    from difareli.configs import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("relight", overrides=[*overrides, f"out_dir={out_dir}"], return_hydra_config=True)
        with open_dict(cfg):
            cfg.hydra.runtime.output_dir = cfg.hydra.runtime.cwd = str(out_dir)
        HydraConfig().set_config(cfg)
        with open_dict(cfg):
            del cfg.hydra
    return cfg


def rotation(out: Path, checkpoint: str, frames: int) -> Path:
    """The astronaut's composited yaw rotation, answered as ``difareli-relight image=astronaut.png video.axis=yaw``
    answers it (Request, respond), each frame's face window as a captioned contact sheet."""
    import imageio.v3 as iio
    from skimage import data

    from difareli.evaluation.photo_presets import face_window
    from difareli.relight.request import Request, respond
    from difareli.utils import viz

    with tempfile.TemporaryDirectory() as tmp:
        photo = Path(tmp) / "astronaut.png"
        iio.imwrite(photo, data.astronaut())
        request = Request.from_config(request_config(
            [f"checkpoint={checkpoint}", f"image={photo}", "video.axis=yaw", f"video.frames={frames}",
             "progress=false"], Path(tmp)))
        answer = respond(request.how.make_relighter(), request, print)
    cells = [face_window(answer.source, frame, side=192) for frame in answer.whole_video]
    sheet = viz.contact_sheet(cells, viz.rotation_captions("yaw", frames), columns=min(frames, 6))
    return viz.save_png(sheet, out / "photo_rotation_yaw.png")


def demo(out: Path) -> None:
    """``difareli-demo`` into a scratch folder; its three pictures copied into ``out``."""
    with tempfile.TemporaryDirectory() as tmp:
        run([str(BIN / "difareli-demo"), f"out_dir={tmp}", "progress=false"])
        for name, target in DEMO_FILES.items():
            shutil.copyfile(Path(tmp) / name, out / target)
            print(f"{out / target}")


def main() -> None:
    args = parse()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if "demo" in args.only:
        demo(out)
    if "rotation" in args.only:
        print(rotation(out, args.checkpoint, args.frames))
    if "app" in args.only:
        app(out)


if __name__ == "__main__":
    main()
