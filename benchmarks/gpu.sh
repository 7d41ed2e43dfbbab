#!/usr/bin/env bash
# The checks for a machine with an NVIDIA GPU (the project never needs one): the default test
# suite with JAX on the GPU, then the same estimates on the GPU and on this machine's CPU
# (benchmarks.backends), then Method I against the per-point scipy loop (benchmarks.local_bench).
# Usage, after `pip install -c constraints.txt -e ".[cuda,test]"`:
#   bash benchmarks/gpu.sh OUTDIR [extra pytest arguments]
# Time limits [s]: TEST_TIMEOUT (default 1800), BENCH_TIMEOUT (900), LOCAL_TIMEOUT (300);
# WORKERS: pytest-xdist workers (default: the number of cores, at most 16).
set -uo pipefail
out="${1:?usage: bash benchmarks/gpu.sh OUTDIR [pytest arguments]}"
shift
mkdir -p "$out"
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # several test processes share one GPU
export PYTHONUNBUFFERED=1
# one persistent compilation cache for every test worker and CLI subprocess of this run
export JAXREFL_CACHE="${JAXREFL_CACHE:-$(mktemp -d -t jaxrefl-gpu-cache-XXXX)}"
{ nvidia-smi -L 2>&1; python3 -c "import jax; print('JAX', jax.__version__, jax.default_backend(), jax.devices())"; } \
    | tee "$out/device.txt"
cores=$(nproc)
workers=()
python3 -c "import xdist" 2>/dev/null && workers=(-n "${WORKERS:-$(( cores < 16 ? cores : 16 ))}")
# SIGINT at the limit: pytest stops, prints its summary and writes the JUnit file of what ran
timeout -s INT -k 30 "${TEST_TIMEOUT:-1800}" python3 -m pytest -q -rfE -p no:cacheprovider --durations=15 \
    --junitxml="$out/junit.xml" "${workers[@]}" "$@" 2>&1 | tee "$out/tests.log" | tail -60
tests=${PIPESTATUS[0]}
timeout -k 10 "${BENCH_TIMEOUT:-900}" python3 -m benchmarks.backends --out "$out/RESULTS_backends.md" \
    --logs "${TMPDIR:-/tmp}/jaxrefl-backends-logs" --total-budget "$(( ${BENCH_TIMEOUT:-900} * 2 / 3 ))" --per-cell "$(( ${BENCH_TIMEOUT:-900} / 3 ))" 2>&1 | tail -20
timeout -k 10 "${LOCAL_TIMEOUT:-300}" python3 -m benchmarks.local_bench --points 100000 --subset 200 --repeats 3 \
    --out "$out/RESULTS_local_gpu.md" 2>&1 | tail -20
exit "$tests"
