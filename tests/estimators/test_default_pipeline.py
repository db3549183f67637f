"""The default estimators read from conf/preprocess.yaml equal Hydra's composition of it; their pipeline is built
once per process and aligner."""

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from difareli.configs import CONFIG_DIR
from difareli.estimators.pipeline import default_estimators, default_pipeline


@pytest.mark.parametrize("size", [64, 256])
def test_default_estimators_are_what_preprocess_composes(size):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("preprocess", overrides=["in_dir=x", "out_dir=y", f"size={size}"])
    assert default_estimators(size) == OmegaConf.to_container(cfg.estimators, resolve=True)


def test_default_block_has_every_role_at_its_size():
    est = default_estimators(64)
    assert set(est) == {"align", "geometry", "masks", "light", "identity", "shadow"}
    assert est["geometry"]["_target_"].endswith("BFMGeometry") and est["align"]["size"] == 64


def test_default_pipeline_is_built_once_per_names_size_and_aligner():
    pytest.importorskip("mediapipe")
    a = default_pipeline(["image", "masks"], 64)
    assert default_pipeline(["image", "masks", "masks"], 64) is a  # the same names, in order, once each
    assert default_pipeline(["image", "masks"], 96) is not a and a.size == 64
    frame = default_pipeline(["image", "masks"], 64, align={"_target_": "difareli.synth.estimated.FrameAligner",
                                                            "size": 64})
    assert frame is not a and type(frame.aligner).__name__ == "FrameAligner"
    assert a.encodings == ("image", "masks")
