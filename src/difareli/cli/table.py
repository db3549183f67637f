"""difareli-table: merge benchmark run dirs into one table (rows = methods, column groups = protocols); on Multi-PIE
runs, ``published=all|ours|[names]`` adds the paper's Table I rows, labelled as published figures. ``paired`` adds the
paired comparisons of every two methods scored on the same pairs (``difareli.evaluation.paired``: mean difference,
bootstrap CI, Wilcoxon p) and ``strata=`` breaks every table down by light category or target shadow share.
``label=[...]`` names each run dir's rows (two runs of one method, e.g. two checkpoints, are refused without it)."""

from __future__ import annotations

import glob
import json
from pathlib import Path
from typing import Iterable

import hydra
from omegaconf import DictConfig, ListConfig

from difareli import errors
from difareli.evaluation import paired, published, tables
from difareli.evaluation.benchmark import SETTINGS
from difareli.data import shard as sharding
from difareli.cli import common
from difareli.utils.fileio import read_json_mapping, staged_outputs, write_text_atomic


def expand_runs(patterns: Iterable[str]) -> list[Path]:
    """Run dirs from dirs and glob patterns. A glob keeps only dirs holding a per-image CSV (a multirun
    folder also holds multirun.yaml); a plain path must hold one."""
    found: list[Path] = []
    for pat in patterns:
        pat = str(pat)
        if glob.has_magic(pat):
            hits = [Path(p) for p in sorted(glob.glob(pat)) if (Path(p) / tables.PER_IMAGE_CSV).is_file()]
            if not hits:
                raise errors.UserFileNotFoundError(f"no run dir with {tables.PER_IMAGE_CSV} matches {pat!r}")
            found += hits
        else:
            if not (Path(pat) / tables.PER_IMAGE_CSV).is_file():
                raise errors.UserFileNotFoundError(not_a_run_dir(Path(pat)))
            found.append(Path(pat))
    return list(dict.fromkeys(found))


def not_a_run_dir(path: Path) -> str:
    """Why ``path`` (given in ``runs=``) is no benchmark run dir, and what to give: said by what it is."""
    fix = f"give difareli-benchmark run dirs (each holds {tables.PER_IMAGE_CSV}) or a glob of them"
    if not path.exists():
        return f"runs: {path} does not exist; {fix}"
    if not path.is_dir():
        return f"runs: {path} is a file, not a run dir; {fix}"
    if (path / "store.json").is_file():
        return (f"runs: {path} is an encodings store, not a benchmark run dir; benchmark it first "
                f"(difareli-benchmark store={path} method=<method>) and give that run's out_dir")
    inner = sorted(p.parent.name for p in path.glob(f"*/{tables.PER_IMAGE_CSV}"))
    if inner:  # a multirun folder: its jobs are the run dirs
        shown = ", ".join(inner[:3]) + (", ..." if len(inner) > 3 else "")
        return f"runs: {path} holds run dirs ({shown}), not a per-image CSV itself; give '{path}/*'"
    return f"runs: {path} holds no {tables.PER_IMAGE_CSV}, so no benchmark finished there; {fix}"


def published_methods(value) -> list[str] | None | bool:
    """``published``: null/false (no rows), ``all``, ``ours`` (DiFaReli, DiFaReli++, DiFaReli++_ss) or a list of
    names; anything else (``published=0``, a number) is a UserError saying what it accepts."""
    accepts = (f"published= accepts null or false (no published rows), all, ours, or a list of names from "
               f"{list(published.FIGURES)}")
    # `is`, not ==: 0 == False and 1 == True would read published=0 as "none" and published=1 as "all".
    if value is None or value is False or value in ("", "none", "null", "false"):
        return False
    if value is True or value == "all":
        return None
    if value == "ours":
        return list(published.OURS)
    if not isinstance(value, (str, ListConfig, list)):
        raise errors.UserError(f"published={value!r}: {accepts}")
    names = [str(v) for v in value] if isinstance(value, (ListConfig, list)) else [str(value)]
    unknown = sorted(set(names) - set(published.FIGURES))
    if unknown:
        raise errors.UserError(f"published={value}: no published Multi-PIE figures for {unknown}; {accepts}")
    return names


def check_multipie(dirs: list[Path], rule: str) -> None:
    """Published Multi-PIE rows go only beside Multi-PIE runs scored with the paper's rule."""
    if rule != "paper":
        raise errors.UserError(f"published=...: the runs were scored with metrics.rule={rule}, the paper's figures "
                               "with the authors' evaluator; rerun the benchmark with metrics.rule=paper")
    for d in dirs:
        prov = Path(d) / "provenance.json"
        data = json.loads(prov.read_text()).get("data set") if prov.is_file() else None
        if data != "multipie":
            raise errors.UserError(f"published=...: run dir {d} was benchmarked on {data or 'an unknown data set'}, "
                                   "not Multi-PIE; the paper's rows go beside Multi-PIE runs (difareli-multipie)")


#: What difareli-table writes into ``out`` (a rerun replaces all of them, never some).
OUTPUTS = ("table.md", "table.csv", "table.tex", "paired.md", "paired.csv")


def run(cfg: DictConfig) -> tables.Table:
    """Merge, print the Markdown table, write table.{md,csv,tex} (and paired.{md,csv}) into ``cfg.out``."""
    errors.check_int(cfg.digits, "digits", 0)
    errors.check_out_dir(cfg.out, "out")
    if not isinstance(cfg.runs, (str, ListConfig)):
        raise errors.UserError(f"runs={cfg.runs!r} is not a run dir, a glob or a list; e.g. 'runs=[logs/a,logs/b]'")
    runs = [cfg.runs] if isinstance(cfg.runs, str) else list(cfg.runs)
    if not runs:  # was a table of no rows, exit 0
        raise errors.UserError("runs=[] names no run dir; give difareli-benchmark run dirs or a glob of them, e.g. "
                               "'runs=[logs/a,logs/b]'")
    dirs = expand_runs(runs)
    sharding.check_complete(dirs)  # sharded benchmark runs: every shard of each job exactly once
    strata, bins, mode = check_strata(cfg)
    drop = errors.check_bool(cfg.get("drop_bad_rows", False), "drop_bad_rows")
    table, records = tables.merge_runs(dirs, methods=list(cfg.methods) if cfg.methods else None,
                                       drop_bad_rows=drop, strata=strata, bins=bins, with_records=True,
                                       labels=run_labels(cfg.get("label")))
    chosen = published_methods(cfg.get("published"))
    if chosen is not False:
        check_multipie(dirs, table.rule)
        published.add_to(table, chosen)
    out = Path(cfg.out)
    md = table.to_markdown(digits=int(cfg.digits))
    pmd = None
    if mode != "off":
        n_boot, seed = int(cfg.get("n_boot", paired.N_BOOT)), int(cfg.get("seed", 0))
        rows, notes = paired.compare(records, table.metrics, n_boot=n_boot, seed=seed, strict=mode == "strict",
                                     methods=table.methods, origins=origins(table.runs))
        pmd = paired.to_markdown(rows, notes, n_boot, seed)
    # Published together: a rerun never leaves one run's table beside another's paired comparisons.
    with staged_outputs(out, OUTPUTS) as stage:  # each file written by a writer that names it on a full disk
        write_text_atomic(stage / "table.md", md)
        table.to_csv(stage / "table.csv")
        write_text_atomic(stage / "table.tex", table.to_latex(digits=int(cfg.digits), caption=cfg.caption))
        if pmd is not None:
            write_text_atomic(stage / "paired.md", pmd)
            write_text_atomic(stage / "paired.csv", paired.to_csv(rows))
    print(f"{len(dirs)} run(s): " + ", ".join(str(d) for d in dirs) + "\n")
    print(md)
    written = f"written: {out / 'table.md'}, table.csv, table.tex"
    if pmd is not None:
        print("Paired comparisons\n\n" + pmd)
        written += ", paired.md, paired.csv"
    print(written)
    return table


def recorded_store(run_dir: Path) -> tuple[str | None, str]:
    """(the store identity ``run_dir`` records in its benchmark settings or None, the store as its provenance names
    it: path and identity)."""
    identity = read_json_mapping(run_dir / SETTINGS).get("store")
    identity = identity if isinstance(identity, str) else None
    return identity, str(read_json_mapping(run_dir / "provenance.json").get("store") or identity or "unrecorded")


def origins(runs: dict[str, list[Path]]) -> dict[str, paired.Origin]:
    """Where each method's rows were scored (paired comparisons join rows by record id: only rows of one store
    are the same pairs); the shards of one method on two stores are refused."""
    out = {}
    for method, dirs in runs.items():
        seen = {d: recorded_store(d) for d in dirs}
        ids = {i for i, _ in seen.values() if i}
        if len(ids) > 1:
            (a, (_, sa)), (b, (_, sb)) = [next((d, v) for d, v in seen.items() if v[0] == i) for i in sorted(ids)][:2]
            raise errors.UserError(f"{method}: run dirs {a} and {b}, shards of one job, were scored on different "
                                   f"stores ({sa}; {sb}); rerun every shard on one store")
        identity = next(iter(ids), None)
        store = next((s for i, s in seen.values() if i == identity), "unrecorded")
        out[method] = paired.Origin(", ".join(map(str, dirs)), identity, store)
    return out


def run_labels(value) -> list[str] | None:
    """``label``: null (the method names), or one name per run dir (a list; a string for one run dir)."""
    if value is None:
        return None
    if isinstance(value, (ListConfig, list)):
        return [str(v) for v in value]
    if isinstance(value, (str, int, float)) and not isinstance(value, bool):
        return [str(value)]
    raise errors.UserError(f"label={value!r}: give one name per run dir, e.g. 'label=[pp_604,pp_8212]' (null: the "
                           "method names)")


def check_strata(cfg: DictConfig) -> tuple[str | None, list[float], str]:
    """(``strata``, ``strata_bins``, paired mode ``auto|strict|off``) from the config, checked."""
    strata = cfg.get("strata")
    if strata is not None and strata not in paired.STRATA:
        raise errors.UserError(f"strata={strata!r}: give null or one of {', '.join(paired.STRATA)}")
    bins = cfg.get("strata_bins") or list(paired.SHADOW_BINS)
    try:
        bins = [float(b) for b in bins]
    except (TypeError, ValueError):
        raise errors.UserError(f"strata_bins={bins!r}: give a list of increasing numbers, e.g. "
                               f"{list(paired.SHADOW_BINS)}") from None
    mode = cfg.get("paired", "auto")
    mode = {True: "strict", False: "off", None: "off"}.get(mode, mode) if isinstance(mode, (bool, type(None))) else mode
    if mode not in ("auto", "strict", "off"):
        raise errors.UserError(f"paired={mode!r}: give auto (compare the methods scored on the same pairs, name the "
                               "others), strict (refuse mismatched pair sets) or off")
    errors.check_int(cfg.get("n_boot", paired.N_BOOT), "n_boot", 100)
    return strata, bins, mode


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="table")
@errors.cli_entry("table")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
