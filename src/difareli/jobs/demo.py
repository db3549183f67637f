"""The README's main job (``difareli-demo``): a shipped checkpoint relights faces it has never seen.

On the embedded default (SynthFaces test subjects generated on the fly with a seed the reference models never
trained on, and scikit-image's astronaut photo when the photo estimators are installed) it writes:

- ``comparison.png``: rows of input | relit | ground truth (the same subject rendered under the target light),
  the columns and rows labelled;
- ``rotation_yaw.mp4`` (where imageio-ffmpeg is installed, else an optimised ``rotation_yaw.gif``) and
  ``rotation_yaw.png``, its contact sheet with each frame's light angle: a 360-degree yaw rotation of the input's
  light, cast shadows included, each frame's light made plausible for the face (:func:`plausible`);
- ``benchmark.md`` / ``benchmark.csv``: the checkpoint against identity and the Lambertian ratio image on a few
  pairs of both protocols (fitted target lights, as a user has them).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from difareli.data.store import EncodingStore
from difareli.evaluation import tables
from difareli.jobs.compare import compare_to_baselines
from difareli.relight.relighter import Relighter
from difareli.relight.request import Rotation, Target, plausible, rotation_video
from difareli.relight.targets import Targets
from difareli.utils import viz
from difareli.utils.fileio import write_text_atomic


@dataclass
class DemoResult:
    paths: dict[str, Path] = field(default_factory=dict)
    table: tables.Table | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    #: how the model relit: its sampler and steps, or one pass (a student)
    how: str = ""


def make_store(root: Path, *, subjects: int, resolution: int, seed: int, progress: bool) -> EncodingStore:
    """A small SynthFaces v2 store (every effect, estimated inputs) at ``root``; reused when it exists."""
    from difareli.synth.generator import generate

    generate(out_dir=str(root), subjects=subjects, lights=4, resolution=resolution, seed=seed, workers=1,
             realism="full", inputs="estimated_light",
             progress=_bar("SynthFaces", progress) if progress else None)
    return EncodingStore.open(root)


def _bar(desc: str, enabled: bool) -> Callable[[int, int], None]:
    from tqdm.auto import tqdm

    state: dict[str, Any] = {}

    def update(done: int, total: int) -> None:
        if "bar" not in state:
            state["bar"] = tqdm(total=total, desc=desc, disable=not enabled)
        state["bar"].n = done
        state["bar"].refresh()
        if done >= total:
            state["bar"].close()

    return update


def run_demo(checkpoint: Any, out_dir: str | Path, *, sampler: Mapping[str, Any], runtime: Mapping[str, Any] | None,
             subjects: int = 30, resolution: int = 64, seed: int = 2026, frames: int = 60, pairs: int = 8,
             rows: int = 3, photo: bool = True, progress: bool = True) -> DemoResult:
    """Run the demo into ``out_dir``; see the module docstring."""
    from difareli.lit import load_checkpoint

    out, res = Path(out_dir), DemoResult()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    store = make_store(out / "synthfaces", subjects=subjects, resolution=resolution, seed=seed, progress=progress)
    res.seconds["data"] = time.perf_counter() - t0
    loaded = load_checkpoint(checkpoint)
    relighter = Relighter(loaded, sampler, runtime=runtime, batch_size=frames, progress=progress)
    res.how = relighter.describe()
    test = store.ids(split="test")
    subjects_ids = sorted({store.meta(r)["subject"] for r in test})

    # 1. A new light with ground truth: each test subject's most directionally lit record relit under the light of
    #    its record whose light differs most (the same subject rendered under that light is the ground truth).
    t0 = time.perf_counter()
    by_subject = {s: sorted(r for r in test if store.meta(r)["subject"] == s) for s in subjects_ids}
    lights = {r: np.asarray(store.read(r, ["light"])["light"], dtype=np.float64) for r in test}
    grid, names = [], []
    for subject in subjects_ids[:rows]:
        recs = by_subject[subject]
        src = max(recs, key=lambda r: directionality(lights[r]))
        tgt = max((r for r in recs if r != src), key=lambda r: np.abs(lights[r] - lights[src]).sum())
        source, target = relighter.source(store, src), Target(record=tgt)
        other = relighter.source(store, tgt)  # its light, c' and key sun: the light of its image
        relit = relighter.relight(source, target.for_source(relighter, source, other)[0])[0]
        grid.append([source.arrays["image"], relit, np.asarray(other.arrays["image"])])
        names.append(f"{src} -> {tgt}")  # the source record, the record whose light it takes
    res.paths["comparison"] = viz.save_png(
        viz.grid(_zoom(grid, 3), col_labels=["input", "relit", "ground truth"],
                 cell_labels=[[n, "", ""] for n in names]), out / "comparison.png")
    res.seconds["relight"] = time.perf_counter() - t0

    # 2. A 360-degree yaw rotation of the most directionally lit test input's light; the cast-shadow map is
    #    re-rendered toward every frame's light (its key sun found from the input's cast shadows, turned with it).
    t0 = time.perf_counter()
    first = max(test, key=lambda r: directionality(lights[r]))
    source = relighter.source(store, first)
    # The demo chose these lights itself (the input's turned), so they are made plausible for the face: it had
    # warned about itself (26 of 60 frames negative on most of the face).
    video, notes = rotation_video(relighter, source, Rotation("yaw", frames, plausible=True), store)
    res.notes.append(f"rotation video of {first}, shadow strength: {notes['shadow']}")
    res.paths.update(viz.write_rotation(np.asarray(video), out, "rotation_yaw", axis="yaw", fps=20, zoom=2,
                                        fmt="auto"))
    res.seconds["video"] = time.perf_counter() - t0

    # 3. A small benchmark: the checkpoint against identity and the Lambertian ratio image, fitted target lights.
    comparison = compare_to_baselines(store, loaded, sampler, out / "benchmark", pairs=pairs, runtime=runtime,
                                      progress=progress)
    res.table = comparison.table
    write_text_atomic(out / "benchmark.md", res.table.to_markdown() + "\n")
    res.table.to_csv(out / "benchmark.csv")
    res.paths["benchmark"] = out / "benchmark.md"
    res.seconds["benchmark"] = comparison.seconds["total"]

    # 4. A photo, when the estimators of difareli-preprocess are installed.
    if photo:
        t0 = time.perf_counter()
        try:
            res.paths["photo"] = relight_photo(relighter, out / "astronaut.png", resolution)
        except ImportError as e:
            res.notes.append(f"astronaut photo skipped: {e}")
        res.seconds["photo"] = time.perf_counter() - t0
    return res


def relight_photo(relighter: Relighter, path: Path, resolution: int) -> Path:
    """scikit-image's astronaut, preprocessed in memory and relit under yaw -60, -30, +30, +60 degrees."""
    from skimage import data

    source = relighter.photo_source(data.astronaut(), size=resolution, what="the astronaut photo",
                                    key=("photo", "astronaut"))
    made = [Target(yaw=a).for_source(relighter, source)[0] for a in (-60, -30, 30, 60)]
    relit = relighter.relight(source, plausible(Targets.of([m.lights[0] for m in made], [m.shadows[0] for m in made],
                                                           suns=[m.suns[0] if m.suns else None for m in made]),
                                                source, "the demo's lights"))
    strip = viz.grid(_zoom([[source.arrays["image"], *relit]], 2),
                     col_labels=["input", "yaw -60°", "yaw -30°", "yaw +30°", "yaw +60°"])
    return viz.save_png(strip, path)


def directionality(light: np.ndarray) -> float:
    """How directional an SH light is: the first-order (band 1) energy over the ambient (band 0) term."""
    light = np.asarray(light, dtype=np.float64)
    return float(np.linalg.norm(light[1:4]) / max(np.linalg.norm(light[0]), 1e-8))


def _zoom(rows: list[list[np.ndarray]], k: int) -> list[list[np.ndarray]]:
    """Nearest-neighbour upscaling by ``k`` (64 px faces are too small to judge)."""
    return [[np.repeat(np.repeat(np.asarray(im), k, axis=0), k, axis=1) for im in row] for row in rows]
