#!/usr/bin/env bash
# The GPU checks in one short run (issue 36, for a session lent a CUDA machine): the `gpu` tests,
# a 1920 px pair on the device at batch sizes 1, 8 and 32 with its CPU parity, `cbh reprocess` on
# a few hundred pairs (GPU actors, then CPU actors), and the OpenCV comparison on the device.
#
# Usage, from the repository root on the device machine:  bash scripts/gpu_check.sh [OUT_DIR]
# Prints everything and, with OUT_DIR, also keeps it in OUT_DIR/gpu_check.txt (+ bench_gpu.json).
#
# The device image has Python, torch, OpenCV, pandas, xarray, pyarrow and typer but not the rest
# of cbh's dependencies, and no network: they travel as wheels in .whl/ (git-ignored through
# .git/info/exclude; see docs/accuracy.md "On a GPU" for how they were fetched). Ray's wheel is
# over the 64 MiB carry limit, so .whl/ray.tar.xz holds it without its Java jars, RLlib, Tune,
# Train, Serve and LLM; .whl/site/pvlib holds pvlib's spa.py alone (all cbh takes from pvlib here).
set -uo pipefail
export PYTHONUNBUFFERED=1
out=${1:-}
py=python3  # the device image's Python (3.12, with torch); python3.11 elsewhere
command -v python3.11 >/dev/null && ! $py -c "import torch" 2>/dev/null && py=python3.11
run() {
  echo "== $*"
  if [ -n "$out" ]; then "$@" 2>&1 | tee -a "$out/gpu_check.txt"; else "$@"; fi
}
[ -n "$out" ] && mkdir -p "$out" && : > "$out/gpu_check.txt"
if [ -d .whl ]; then
  t0=$(date +%s)
  $py -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && tar xJf .whl/ray.tar.xz -C /tmp/site && cp -r .whl/site/* /tmp/site/ \
    && $py -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --target /tmp/site . \
    || { echo "installing the carried wheels failed"; exit 1; }
  export PYTHONPATH=/tmp/site
  echo "dependencies installed in $(( $(date +%s) - t0 )) s"
fi
run nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
run $py -c "import torch, cv2, ray; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '', 'opencv', cv2.__version__, 'ray', ray.__version__)"
run timeout 120 $py -m pytest -q -m gpu -p no:cacheprovider tests/test_torch_parity.py
run timeout 300 $py benchmarks/bench_gpu.py --pairs 240 --distinct 48 ${out:+--json "$out/bench_gpu.json"}
run timeout 60 $py benchmarks/bench_vs_opencv.py --device cuda --repeat 5
# the real 241 m station's pairs as a run processes them (its clock offset carried on the sky maps),
# against the simulated 50 m pair, on this machine's CPU cores (issue 36's real / simulated bar)
run timeout 120 $py benchmarks/bench_baselines.py --as-run 6
