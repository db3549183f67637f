"""Send images, tables and the run's identity to whatever loggers a run has (wandb, TensorBoard, CSV...).

Lightning loggers only share ``log_metrics``/``log_hyperparams``. Everything richer is dispatched here by
*capability*, not by logger name: a logger with ``log_image``/``log_table`` methods (wandb) gets them; a
logger whose ``experiment`` has ``add_image``/``add_text`` (TensorBoard's SummaryWriter) gets those; others
(CSV) are skipped, the files being on disk already. Every function takes a Trainer (its loggers, global
step, rank 0 only) or a plain list of loggers (e.g. ``difareli-benchmark``, which has no Trainer).
"""

from __future__ import annotations

import csv
import functools
import io
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
from difareli.configs import instantiate_group

Target = Any  # a lightning Trainer, or an iterable of Lightning loggers


def _loggers_and_step(target: Target, step: int | None) -> tuple[list[Any], int | None]:
    if hasattr(target, "loggers"):  # a Trainer: rank 0 writes, at the current global step
        if not target.is_global_zero:
            return [], step
        return list(target.loggers), target.global_step if step is None else step
    return list(target or []), step


def _as_image(image: str | Path | np.ndarray) -> np.ndarray:
    """uint8 HxWx3 from an array or an image file."""
    if isinstance(image, (str, Path)):
        import imageio.v3 as iio

        image = iio.imread(image)
    a = np.asarray(image)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    return a[..., :3].astype(np.uint8)


def _experiment_with(logger, method: str):
    """``logger.experiment`` if it offers ``method`` (TensorBoard's SummaryWriter), else None."""
    if not hasattr(type(logger), "experiment"):
        return None
    exp = logger.experiment
    return exp if callable(getattr(type(exp), method, None)) else None


def log_image(target: Target, key: str, image: str | Path | np.ndarray, step: int | None = None) -> None:
    """Log one image (an array or a PNG written by a callback) under ``key`` to every image-capable logger."""
    loggers, step = _loggers_and_step(target, step)
    if not loggers:
        return
    img = _as_image(image)
    for lg in loggers:
        if callable(getattr(lg, "log_image", None)):  # wandb
            lg.log_image(key=key, images=[img], step=step)
        elif (exp := _experiment_with(lg, "add_image")) is not None:  # TensorBoard
            exp.add_image(key, img, global_step=step, dataformats="HWC")
            exp.flush()  # also after fit, when Lightning has already closed the writer once


def log_text(target: Target, key: str, text: str, step: int | None = None) -> None:
    """Log Markdown/plain text (a config, a table) to every text-capable logger."""
    loggers, step = _loggers_and_step(target, step)
    for lg in loggers:
        if callable(getattr(lg, "log_text", None)):  # wandb: a one-cell table
            lg.log_text(key=key, columns=["text"], data=[[text]], step=step)
        elif (exp := _experiment_with(lg, "add_text")) is not None:
            # TensorBoard renders Markdown; indenting by 4 spaces keeps YAML/CSV as a code block.
            exp.add_text(key, text, global_step=step or 0)
            exp.flush()


def log_table(target: Target, key: str, table, step: int | None = None, digits: int = 4) -> None:
    """Log a :class:`difareli.evaluation.tables.Table` (benchmark summary): a real table where the logger has one
    (wandb), its Markdown rendering elsewhere (TensorBoard)."""
    loggers, step = _loggers_and_step(target, step)
    if not loggers:
        return
    rows = list(csv.reader(io.StringIO(table.to_csv())))
    for lg in loggers:
        if callable(getattr(lg, "log_table", None)):
            lg.log_table(key=key, columns=rows[0], data=rows[1:], step=step)
        elif (exp := _experiment_with(lg, "add_text")) is not None:
            exp.add_text(key, table.to_markdown(digits=digits), global_step=step or 0)
            exp.flush()


@functools.lru_cache(maxsize=None)
def git_commit(path: str | None = None) -> dict[str, Any]:
    """``{"git_commit": sha, "git_dirty": bool}`` of the repository holding ``path`` (default: this package's
    source tree); ``"unknown"`` when it is not a git checkout (e.g. an installed wheel)."""
    cwd = path or str(Path(__file__).resolve().parent)
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=cwd,
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip() != ""
    except (OSError, subprocess.SubprocessError):
        return {"git_commit": "unknown", "git_dirty": None}
    return {"git_commit": sha, "git_dirty": dirty}


def log_run_info(target: Target, cfg) -> dict[str, Any]:
    """Log the resolved config (as hyperparameters and as YAML text) and the git commit; returns the commit
    info. Hydra also keeps the config in ``<run>/.hydra/``; this puts it next to the curves."""
    from omegaconf import OmegaConf

    loggers, _ = _loggers_and_step(target, 0)
    if not loggers:
        return {}
    info = git_commit()
    for lg in loggers:
        lg.log_hyperparams(info)
    yaml = OmegaConf.to_yaml(cfg, resolve=True)
    log_text(target, "config", f"git commit {info['git_commit']}" + (" (dirty)" if info["git_dirty"] else "")
             + "\n\n" + "\n".join("    " + line for line in yaml.splitlines()), step=0)
    return info


def log_benchmark(cfg, result) -> list[Any]:
    """``difareli-benchmark`` with a ``logger`` group: its resolved config, git commit, summary table and
    comparison grids go to those loggers (no Trainer there); returns the loggers, finalised."""
    loggers = instantiate_group(cfg.logger)
    log_run_info(loggers, cfg)
    log_table(loggers, "benchmark/summary", result.table, step=0)
    for name, path in result.paths.items():
        if name.startswith("comparison_"):
            log_image(loggers, f"benchmark/{name}", path, step=0)
    for lg in loggers:
        lg.finalize("success")
    return loggers
