"""difareli-ablate: train every row of a paper ablation table, benchmark each checkpoint, write the merged table.

``difareli-ablate table=4`` (or ``table=2``) reads the rows from ``conf/experiment/table<N>.yaml`` (its
``hydra.sweeper.params.model`` list, the same list ``difareli-train -m experiment=table<N>`` sweeps) and, per row:

1. trains it with ``difareli-train experiment=table<N> model=<row>`` (preset and steps from the experiment unless
   ``preset`` / ``steps`` are set), into ``<out_dir>/<row>/train``;
2. benchmarks its ``last.ckpt`` with ``difareli-benchmark method=diffusion`` on both protocols with one sampler
   for every row, into ``<out_dir>/<row>/bench``;

then merges the per-image CSVs into ``table.{md,csv,tex}`` (rows labelled as in the paper, mean ± SE, seconds per
image, which include a ControlNet's per-step cost) and ``figure.png`` (one relit example per row). Both steps run
the real CLIs as child processes (no duplicated training or benchmark code). Resumable: a row whose training
finished (``train/done.json``) is not retrained (an interrupted one resumes from its ``last.ckpt``), a row whose
benchmark finished (``bench/metrics_per_image.csv``) is not re-benchmarked (an interrupted one continues where
it stopped).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import yaml
from omegaconf import DictConfig

from difareli import errors
from difareli.data import provenance
from difareli.evaluation import tables
from difareli.utils import viz
from difareli.cli import common
from difareli.configs import CONFIG_DIR
from difareli.utils.fileio import folder_lock, write_json_atomic, write_text_atomic
from difareli.data.store import EncodingStore
from difareli.evaluation.pairs import load_pairs

EXPERIMENTS = CONFIG_DIR / "experiment"
#: Each row's train/ and bench/ folder records the settings that made it (difareli.data.provenance).
ROW_PROVENANCE = "ablate_row.json"


def table_rows(table: int | str) -> tuple[list[str], dict[str, str], str]:
    """``(model configs, labels, caption)`` of ``conf/experiment/table<N>.yaml``: the rows are its sweep list."""
    path = EXPERIMENTS / f"table{table}.yaml"
    if not path.is_file():
        known = sorted(p.stem.removeprefix("table") for p in EXPERIMENTS.glob("table*.yaml"))
        raise errors.UserError(f"table={table!r}: no {path}; known tables: {known}")
    cfg = yaml.safe_load(path.read_text())
    models = [m.strip() for m in str(cfg["hydra"]["sweeper"]["params"]["model"]).split(",") if m.strip()]
    ablation = cfg.get("ablation") or {}
    return models, dict(ablation.get("labels") or {}), str(ablation.get("caption") or f"Table {table}")


def row_dir(out_dir: Path, model: str) -> Path:
    return Path(out_dir) / model.replace("/", "__")


def _run(cmd: list[str], what: str) -> None:
    print("+ " + " ".join(cmd), flush=True)
    proc = subprocess.run(cmd)
    if proc.returncode != 0:
        raise errors.UserError(f"{what} failed (exit {proc.returncode}); its output is above. Fix it and re-run "
                               "difareli-ablate: finished rows are kept")


def train_row(cfg: DictConfig, model: str, resolution: int | None) -> Path:
    """Train one row unless done; returns its ``last.ckpt``."""
    out = row_dir(cfg.out_dir, model) / "train"
    last = out / "checkpoints" / "last.ckpt"
    # A row trained with other settings (steps, preset, store, overrides) is not this row: refuse, naming them.
    provenance.ensure(out, {"table": str(cfg.table), "model": model, "store": _store_id(cfg.store),
                            "preset": cfg.preset, "steps": cfg.steps,
                            "train_overrides": list(cfg.train_overrides or [])},
                      f"the training of row {model}", name=ROW_PROVENANCE)
    if (out / "done.json").is_file() and last.is_file():
        print(f"[{model}] trained: {last}")
        return last
    cmd = [sys.executable, "-m", "difareli.cli.train", f"experiment=table{cfg.table}", f"model={model}",
           f"hydra.run.dir={out}", "sample_grid=false"]
    cmd.append(f"data.root={Path(cfg.store).resolve()}")
    if resolution is not None:  # an existing store: its size; otherwise the experiment's SynthFaces is generated
        cmd += [f"data.resolution={resolution}", "data.synth=null"]
    if cfg.preset is not None:
        cmd.append(f"model.preset={cfg.preset}")
    if cfg.steps is not None:
        cmd.append(f"trainer.max_steps={int(cfg.steps)}")
    if last.is_file():  # an interrupted training continues from its last step
        cmd.append(f"ckpt_path={last}")
    cmd += list(cfg.train_overrides or [])
    _run(cmd, f"training row {model}")
    if not last.is_file():
        raise errors.UserError(f"training row {model} left no {last}; a debug run (fast_dev_run) saves no "
                               "checkpoint: drop debug=... from train_overrides")
    write_json_atomic(out / "done.json", {"model": model, "checkpoint": str(last)}, indent=None)
    return last


def sampler_choice(cfg: DictConfig) -> str:
    """The ``sampler`` group choice (conf/sampler/<choice>.yaml) this run composed, for the benchmark child."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return str(HydraConfig.get().runtime.choices["sampler"])
    except (ValueError, KeyError):  # composed without a Hydra run (tests): the preset named by the config
        return str(cfg.sampler.name)


def benchmark_row(cfg: DictConfig, model: str, checkpoint: Path, store: str) -> Path:
    """Benchmark one row's checkpoint unless done; returns its run dir."""
    out = row_dir(cfg.out_dir, model) / "bench"
    provenance.ensure(out, {"checkpoint": provenance.checkpoint_identity(checkpoint), "store": _store_id(store),
                            "sampler": sampler_choice(cfg), "sampler_steps": cfg.sampler_steps or cfg.sampler.steps,
                            "protocols": list(cfg.protocols), "limit": cfg.limit,
                            "benchmark_overrides": list(cfg.benchmark_overrides or [])},
                      f"the benchmark of row {model}", name=ROW_PROVENANCE)
    if (out / tables.PER_IMAGE_CSV).is_file():
        print(f"[{model}] benchmarked: {out / tables.PER_IMAGE_CSV}")
        return out
    protocols = "[" + ",".join(cfg.protocols) + "]"
    cmd = [sys.executable, "-m", "difareli.cli.benchmark", f"store={store}", "method=diffusion",
           f"method.checkpoint={checkpoint}", f"method.name={model}", f"sampler={sampler_choice(cfg)}",
           f"sampler.steps={int(cfg.sampler_steps if cfg.sampler_steps is not None else cfg.sampler.steps)}",
           f"protocols={protocols}", f"hydra.run.dir={out}", f"out_dir={out}"]
    if cfg.limit is not None:
        cmd.append(f"limit={int(cfg.limit)}")
    cmd += list(cfg.benchmark_overrides or [])
    _run(cmd, f"benchmarking row {model}")
    return out


def merged_table(run_dirs: dict[str, Path], labels: dict[str, str]) -> tables.Table:
    """One table over the rows' per-image CSVs, rows in the given order, named by their paper labels."""
    records = []
    for model, d in run_dirs.items():
        label = labels.get(model, model)
        records += [dataclasses.replace(r, method=label) for r in tables.read_records(d / tables.PER_IMAGE_CSV)]
    return tables.summarize(records, [labels.get(m, m) for m in run_dirs])


def write_table(table: tables.Table, out: Path, caption: str, digits: int = 4) -> dict[str, Path]:
    out.mkdir(parents=True, exist_ok=True)
    paths = {"md": out / "table.md", "csv": out / "table.csv", "tex": out / "table.tex"}
    write_text_atomic(paths["md"], f"{caption}\n\n" + table.to_markdown(digits=digits))
    table.to_csv(paths["csv"])
    write_text_atomic(paths["tex"], table.to_latex(digits=digits, caption=caption))
    return paths


def figure(run_dirs: dict[str, Path], store_root: str, protocols: list[str], limit: int | None,
           path: Path, per_protocol: int = 1) -> Path | None:
    """``per_protocol`` lines per protocol: the input, each row's relit image of one of the protocol's first
    benchmarked pairs (the benchmark's selection for ``limit``), the ground truth."""
    import imageio.v3 as iio

    store = EncodingStore.open(store_root)
    lines = []
    for proto, pairs in load_pairs(store, protocols, limit=limit).items():
        if not pairs:
            continue
        for pair in pairs[:per_protocol]:
            relit = [d / "relit" / proto / f"{pair.id}.png" for d in run_dirs.values()]
            if not all(p.is_file() for p in relit):
                continue
            src, gt = (np.asarray(store.read(r, ["image"])["image"]) for r in (pair.source, pair.target))
            lines.append([src, *(np.asarray(iio.imread(p))[..., :3] for p in relit), gt])
    return viz.save_png(viz.grid(lines), path) if lines else None


def run(cfg: DictConfig) -> tables.Table:
    """Train + benchmark every (selected) row, then write the merged table and figure into ``out_dir``."""
    models, labels, caption = table_rows(cfg.table)
    if cfg.rows:
        unknown = [m for m in cfg.rows if m not in models]
        if unknown:
            raise errors.UserError(f"rows={list(cfg.rows)}: {unknown} not in table {cfg.table}'s rows {models}")
        models = [m for m in models if m in cfg.rows]
    errors.check_int(cfg.limit, "limit", 1, allow_none=True)
    errors.check_int(cfg.steps, "steps", 1, allow_none=True)
    errors.check_out_dir(cfg.out_dir)
    store = str(Path(cfg.store).resolve())
    resolution = _store_resolution(store)
    with folder_lock(cfg.out_dir, "ablate"):
        return _run_rows(cfg, models, labels, caption, store, resolution)


def _run_rows(cfg: DictConfig, models: list[str], labels: dict[str, str], caption: str, store: str,
              resolution: int | None) -> tables.Table:
    run_dirs = {}
    for i, model in enumerate(models):
        print(f"=== row {i + 1}/{len(models)}: {model} ({labels.get(model, model)})", flush=True)
        ckpt = train_row(cfg, model, resolution)
        run_dirs[model] = benchmark_row(cfg, model, ckpt, store)
    out = Path(cfg.out_dir)
    table = merged_table(run_dirs, labels)
    paths = write_table(table, out, caption)
    fig = figure(run_dirs, store, list(cfg.protocols), cfg.limit, out / "figure.png")
    legend = "figure.png, per line (one per protocol): input | " + " | ".join(labels.get(m, m) for m in models)
    write_text_atomic(out / "figure.txt", legend + " | ground truth\n")
    print(paths["md"].read_text())
    print(f"written: {paths['md']}, table.csv, table.tex" + (f", {fig}" if fig else ""))
    return table


def _store_id(store: str) -> str | None:
    """The store's identity, or None while it is still to be generated (by the first row's training)."""
    return provenance.store_identity(EncodingStore.open(store)) if (Path(store) / "store.json").is_file() else None


def _store_resolution(store: str) -> int | None:
    """The store's image size, or None when the store is still to be generated (by the first training)."""
    header = Path(store) / "store.json"
    if not header.is_file():
        return None
    return int(json.loads(header.read_text())["dims"]["H"])


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="ablate")
@errors.cli_entry("ablate")
def main(cfg: DictConfig) -> Any:
    run(cfg)


if __name__ == "__main__":
    main()
