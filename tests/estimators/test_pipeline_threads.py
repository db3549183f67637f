"""The preprocessing pipeline runs its estimators on one torch thread and gives the caller's setting back."""

from __future__ import annotations

import numpy as np
import torch

from difareli.estimators.pipeline import Pipeline


class _Crop:
    size = 8

    def __call__(self, rgb):
        return {"image": rgb[:8, :8], "quad": np.zeros((4, 2)), "faces": 1, "box": [0, 0, 8, 8], "notes": []}


class _Probe:
    """An estimator that records torch's intra-op thread count while it runs."""

    provides = ("identity",)
    requires = ("image",)

    def __init__(self):
        self.seen = []

    def __call__(self, ctx, needed):
        self.seen.append(torch.get_num_threads())
        return {"identity": np.zeros(128, np.float32)}


def test_estimators_run_on_one_torch_thread_and_the_setting_is_restored():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        probe = _Probe()
        pipe = Pipeline(_Crop(), [probe], ["identity"])
        rgb = np.zeros((16, 16, 3), np.uint8)
        for _ in range(2):
            arrays, _, _ = pipe.process(rgb)
            assert arrays["identity"].shape == (128,)
            assert torch.get_num_threads() == 2
        assert probe.seen == [1, 1]
    finally:
        torch.set_num_threads(before)
