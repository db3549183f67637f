"""difareli-demo: the README's main job: a shipped checkpoint relights unseen faces (see ``difareli.jobs.demo``)."""

from __future__ import annotations

import math
import re
import time
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from difareli import errors
from difareli.checkpoints import loading, zoo
from difareli.checkpoints.format import load_torch_file
from difareli.cli import common
from difareli.jobs.demo import DemoResult, run_demo


def run(cfg: DictConfig) -> DemoResult:
    """Run the demo as configured; prints the answer first (:func:`answer`), then the detail: the live table, the
    notes and the seconds."""
    validate(cfg)
    if cfg.num_threads is not None:
        torch.set_num_threads(int(cfg.num_threads))
    start = time.perf_counter()
    res = run_demo(str(loading.resolve(cfg.checkpoint)), cfg.out_dir, sampler=OmegaConf.to_container(cfg.sampler),
                   runtime=OmegaConf.to_container(cfg.runtime), subjects=int(cfg.subjects),
                   resolution=int(cfg.resolution), seed=int(cfg.seed), frames=int(cfg.frames), pairs=int(cfg.pairs),
                   rows=int(cfg.rows), photo=errors.check_bool(cfg.photo, "photo"),
                   progress=errors.check_bool(cfg.progress, "progress"))
    print(answer(cfg, res))
    print("\n== the detail ==")
    if res.table is not None:
        print(f"Live check on {cfg.pairs} pairs per protocol of unseen subjects ({res.how}): "
              "too few pairs to rank the methods; read the ± standard errors")
        print(res.table.to_markdown())
    if zoo.suite():
        print(f"The shipped models' suite (the figures the README quotes): {zoo.SHIPPED_DIR / 'suite.md'}")
    elif card := card_benchmark(cfg.checkpoint):
        print(f"The model card's table for {cfg.checkpoint} (the figures the README quotes):\n{card}")
    for note in res.notes:
        print(note)
    print("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in res.seconds.items())
          + f"; total {time.perf_counter() - start:.1f}")
    return res


#: What each of the demo's pictures shows.
LOOK = {"comparison": "input | relit | ground truth", "video": "the light turning 360 degrees",
        "sheet": "the rotation's frames", "photo": "the astronaut under 4 turned lights",
        "benchmark": "the live check's table"}


def answer(cfg: DictConfig, res: DemoResult) -> str:
    """The answer, short: what was relit, by which model, where the files are, and the shipped suite's verdict
    on this model in one line (:func:`suite_verdict`; the live check's few pairs only show that the model runs)."""
    what = [f"{cfg.rows} unseen SynthFaces subjects under another light (with ground truth)",
            "one's light turned 360 degrees"] + (["scikit-image's astronaut photo"] if "photo" in res.paths else [])
    files = ", ".join(f"{Path(path).name} ({LOOK[k]})" for k, path in res.paths.items() if k in LOOK)
    lines = ["== difareli-demo: the answer ==", f"relit: {', '.join(what)} (seed {cfg.seed})",
             f"model: {cfg.checkpoint} ({res.how})", f"files in {Path(cfg.out_dir).resolve()}: {files}"]
    verdict = suite_verdict(zoo.suite(), Path(str(cfg.checkpoint)).stem)
    if verdict:
        lines.append(verdict)
    return "\n".join(lines)


def suite_verdict(suite: str | None, checkpoint: str) -> str | None:
    """The DSSIM of ``checkpoint`` in the shipped suite's first table (its headline: the pooled fresh seeds),
    beside the Lambertian ratio image and the unrelit input, per protocol, in one line (lower is better); None where
    that table does not list it."""
    first = first_section(suite or "")
    label = next((m.group(1) for m in re.finditer(r"`([^`]+)` = `([^`]+)`", first) if m.group(2) == checkpoint), None)
    table = [line for line in first.splitlines() if line.startswith("| ")]
    if label is None or not table:
        return None
    head = [c.strip() for c in table[0].strip("|").split("|")]
    rows = {r[0]: r for r in ([c.strip() for c in line.strip("|").split("|")] for line in table[1:])}
    if label not in rows or "lambertian" not in rows or "identity" not in rows:
        return None
    dssim = lambda row, proto: float(row[head.index(f"{proto} DSSIM")].strip("*").split()[0])  # noqa: E731
    parts = []
    for proto in ("(i) same subject", "(ii) different subject"):
        got, lam, idn = (dssim(rows[k], proto) for k in (label, "lambertian", "identity"))
        # The paired Wilcoxon test of the same table's pairs says whether the gap to the ratio image is real.
        paired = [c.strip() for line in table if line.startswith(f"| {proto} | DSSIM | lambertian | {label} |")
                  for c in line.strip("|").split("|")]
        p = float(paired[-1]) if paired else math.nan
        than = "level with" if not p < 0.05 else ("better than" if got < lam else "worse than")
        parts.append(f"{proto.split(' ', 1)[1]} {got:.3f}, {than} the Lambertian ratio image's {lam:.3f}"
                     f"{f' (p = {p:.2g})' if math.isfinite(p) else ''}, the unrelit input {idn:.3f}")
    n = re.search(r"(\d+) pairs per protocol|(\d+) different", first)
    pairs = next((g for g in (n.groups() if n else ()) if g), "?")
    return f"the shipped suite ({pairs} pairs per protocol of unseen seeds, DSSIM, lower is better): {'; '.join(parts)}"


def first_section(suite: str) -> str:
    """The suite's first section: from its first bold heading line (``**<store>**: ...``) up to the next one."""
    lines = suite.splitlines()
    starts = [k for k, line in enumerate(lines) if line.startswith("**")]
    if not starts:
        return ""
    end = starts[1] if len(starts) > 1 else len(lines)
    return "\n".join(lines[starts[0]:end])


def card_benchmark(checkpoint: str) -> str | None:
    """The benchmark paragraph of a checkpoint's model card (shipped checkpoints have one), else None."""
    ckpt = load_torch_file(loading.resolve(checkpoint), "checkpoint")
    text = (ckpt.get("model_card") or {}).get("benchmark") if isinstance(ckpt, dict) else None
    return str(text) if text else None


def validate(cfg: DictConfig) -> None:
    """Config values, checked before any work."""
    common.check_relighting(cfg)  # before the store is made and the checkpoint read
    loading.resolve(cfg.checkpoint)
    for key, low in (("subjects", 10), ("resolution", 16), ("frames", 1), ("pairs", 1), ("rows", 1)):
        errors.check_int(cfg[key], key, low)
    errors.check_int(cfg.num_threads, "num_threads", 1, allow_none=True)
    errors.check_out_dir(cfg.out_dir)


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="demo")
@errors.cli_entry("demo")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
