#!/usr/bin/env bash
# The checks for a machine with an NVIDIA GPU (the project never needs one): the default
# test suite with JAX on the GPU, then Method I's speed benchmark there.
# Usage, after `pip install -c constraints.txt -e ".[cuda,test]"`:
#   bash benchmarks/gpu.sh OUTDIR [extra pytest arguments]
# TEST_TIMEOUT (seconds, default 1800) bounds the test run.
set -uo pipefail
out="${1:?usage: bash benchmarks/gpu.sh OUTDIR [pytest arguments]}"
shift
mkdir -p "$out"
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # several test processes share one GPU
export PYTHONUNBUFFERED=1
python3 -c "import jax; print('JAX', jax.__version__, jax.default_backend(), jax.devices())" | tee "$out/device.txt"
# pytest-xdist where installed: outside JAX the suite is CPU-bound (Embree, NumPy).
workers=()
python3 -c "import xdist" 2>/dev/null && workers=(-n 8)
timeout "${TEST_TIMEOUT:-1800}" python3 -m pytest -q -p no:cacheprovider "${workers[@]}" "$@" 2>&1 \
    | tee "$out/tests.log" | tail -40
tests=${PIPESTATUS[0]}
python3 -m benchmarks.local_bench --points 100000 --subset 200 --repeats 3 --out "$out/RESULTS_local_gpu.md" \
    2>&1 | tail -20
exit "$tests"
