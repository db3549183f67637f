"""difareli-teacher-pairs: a teacher relights every training record toward another record's light."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from difareli import errors
from difareli.checkpoints import loading
from difareli.cli import common
from difareli.render.sun_fit import TARGET_SUNS
from difareli.data.store import EncodingStore
from difareli.relight.relightable import DiffusionRelightable


def run(cfg: DictConfig) -> dict:
    """Generate (or resume) the pair store as configured; returns the counts and pairs/s."""
    from difareli.jobs.teacher_pairs import generate_teacher_pairs
    from difareli.relight.relighter import Relighter
    common.check_relighting(cfg)
    loading.resolve(cfg.checkpoint, "checkpoint")  # a file or a shipped name, as in every other CLI
    errors.check_int(cfg.batch_size, "batch_size", 1)
    errors.check_int(cfg.per_record, "per_record", 1)
    errors.check_int(cfg.limit, "limit", 1, allow_none=True)
    errors.check_choice(cfg.target_sun, "target_sun", TARGET_SUNS)
    relighter = Relighter(cfg.checkpoint, cfg.sampler, runtime=cfg.runtime, mean_matching=cfg.mean_matching)
    if not isinstance(relighter.model, DiffusionRelightable):
        raise errors.UserError(f"checkpoint {cfg.checkpoint} is not a diffusion teacher "
                               f"({type(relighter.model).__name__}); "
                               "give a difareli-train model=difareli_pp checkpoint")
    return generate_teacher_pairs(relighter, EncodingStore.open(cfg.store), cfg.out, split=cfg.split,
                                  per_record=cfg.per_record, limit=cfg.limit, batch_size=cfg.batch_size,
                                  seed=cfg.seed, progress=cfg.progress, target_sun=cfg.target_sun)


@hydra.main(version_base="1.3", config_path=common.CONFIG_PATH, config_name="teacher_pairs")
@errors.cli_entry("teacher-pairs")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
