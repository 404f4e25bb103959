#!/usr/bin/env bash
# The GPU checks in one short run (for a session lent a CUDA machine): the `gpu` tests, then the
# pipeline's throughput on the device (single pairs and process_batch) and the OpenCV comparison.
# Usage, from the repository root on the device machine:  bash scripts/gpu_check.sh [OUT_DIR]
# Prints everything and, with OUT_DIR, also keeps it in OUT_DIR/gpu_check.txt.
set -uo pipefail
out=${1:-}
run() {
  echo "== $*"
  if [ -n "$out" ]; then "$@" 2>&1 | tee -a "$out/gpu_check.txt"; else "$@"; fi
}
[ -n "$out" ] && mkdir -p "$out" && : > "$out/gpu_check.txt"
run nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
run python3.11 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')"
run python3.11 -m pytest -q -m gpu -p no:cacheprovider
run python3.11 benchmarks/bench_pipeline.py --device cuda --repeat 7 --batch 16
run python3.11 benchmarks/bench_vs_opencv.py --device cuda --repeat 7
run python3.11 benchmarks/bench_pipeline.py --device cpu --repeat 7 --batch 16
