#!/usr/bin/env bash
# GPU readiness report in one command (scripts/gpu_check.py): writes gpu_check.json + gpu_check.md to $OUT when
# set, else docs/perf/. On a CUDA machine it fits 8 minutes; without CUDA (or with --small) it runs toy sizes.
#   bash scripts/gpu_check.sh [--small] [--modes fp32 bf16 ...] [--budget SECONDS] [--out DIR]
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
export PYTHONPATH="$here/../src${PYTHONPATH:+:$PYTHONPATH}"
exec "${PYTHON:-python}" "$here/gpu_check.py" "$@"
