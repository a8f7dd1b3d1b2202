#!/usr/bin/env bash
# Runs bench/gpu.py on the lent GPU machine (issue 17) as one command, after bench/gpu_carry.sh prepared
# .gpu_carry/ here: installs the carried wheels beside the image's PyTorch, points the data at the carried mic,
# and leaves gpu.json, gpu.png and the log in $OUT (the device tool brings them back).
set -uo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
    .gpu_carry/whl/*.whl || exit 3
export PYTHONPATH="/tmp/site:$PWD" PYTHONUNBUFFERED=1 VOXE_DATA_ROOT="$PWD/.gpu_carry/shared/data" HF_HUB_OFFLINE=1
OUT=${OUT:-/tmp/gpu_out}
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 | tee "$OUT/gpu.log"
python3 -c "import torch, diffusers; print('torch', torch.__version__, 'diffusers', diffusers.__version__)" \
    2>&1 | tee -a "$OUT/gpu.log"
timeout "${GPU_BENCH_SECONDS:-540}" python3 bench/gpu.py "$@" 2>&1 | tee -a "$OUT/gpu.log"
rc=${PIPESTATUS[0]}
cp bench/results/gpu.json bench/results/gpu.png "$OUT/" 2>/dev/null
exit "$rc"
