#!/usr/bin/env bash
# The one prepared GPU check of jaxelastic, for an offline H200 machine
# (docs/guide/gpu.md describes it).
#
#   bash scripts/gpu_check.sh fetch   # on a CPU machine with network: the wheels of the
#                                     # pure-Python deps the GPU image lacks -> out/wheels
#   bash scripts/gpu_check.sh         # on the GPU machine (offline), with out/wheels copied:
#                                     # install them, bench_devices.py, GPU tests, bench_vmap.py
#
# Everything lands in $OUT (at most 8 files): gpu_check.log (all output), env.txt,
# devices.json, tests.log, vmap.json. Each phase has its own time limit so the whole check
# stays under ~7 minutes (a time limit of 470 s covers it); override with
# DEVICES_BUDGET_S, TESTS_TIMEOUT_S, VMAP_TIMEOUT_S.
set -u
cd "$(dirname "$0")/.."
WHEELS=out/wheels

if [ "${1:-}" = "fetch" ]; then
    # pure-Python (and one cp312 manylinux) wheels the 'cuda' image does not have; versions
    # as in this project's venv. --no-deps: each needed one is named.
    mkdir -p "$WHEELS"
    python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
        --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        --platform manylinux1_x86_64 -d "$WHEELS" \
        meshio==5.3.5 pydantic==2.14.4 pydantic_core==2.50.5 annotated-types==0.8.0 \
        typing-inspection==0.4.5 typing_extensions==4.16.0
    du -sh "$WHEELS"
    exit $?
fi

OUT="${OUT:-out/gpu_check}"
mkdir -p "$OUT"
exec > >(tee "$OUT/gpu_check.log") 2>&1
export PYTHONUNBUFFERED=1
# one process at a time holds the GPU; don't let XLA grab 75% of it up front, so the
# allocator's peak (memory_stats) is what the solve needs
export XLA_PYTHON_CLIENT_PREALLOCATE=false
PY="${PY:-python3}"  # on the H200 image: the python3 that has JAX with CUDA
t_start=$(date +%s)
stamp() { echo "=== $(date -u +%H:%M:%S) (+$(($(date +%s) - t_start)) s) $*"; }

stamp "install wheels"
if ls "$WHEELS"/*.whl >/dev/null 2>&1; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site "$WHEELS"/*.whl || echo "wheel install FAILED"
    export PYTHONPATH="/tmp/site:$PWD"
else
    echo "no wheels in $WHEELS (bash scripts/gpu_check.sh fetch, then carry out/wheels)"
    export PYTHONPATH="$PWD"
fi

stamp "environment"
{
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv 2>&1
    $PY - <<'EOF'
import jax, sys
print("python", sys.version.split()[0], "jax", jax.__version__, "backend", jax.default_backend())
print("devices", jax.devices())
for mod in ("jaxlib", "numpy", "scipy", "optax", "meshio", "pydantic", "pyamg", "cholespy"):
    try:
        m = __import__(mod)
        print(mod, getattr(m, "__version__", "?"))
    except ImportError as e:
        print(mod, "MISSING", e)
import jaxelastic
print("jaxelastic", jaxelastic.__version__, jaxelastic.__file__)
EOF
} 2>&1 | tee "$OUT/env.txt"

stamp "bench_devices.py (twist to ~1M dofs, f32 + f64, device solver)"
timeout $((${DEVICES_BUDGET_S:-220} + 30)) $PY scripts/bench_devices.py \
    --budget-s "${DEVICES_BUDGET_S:-220}" --sizes "${DEVICES_SIZES:-10,30,69}" --max-dofs 1100000 \
    --precisions float32,float64 \
    --repeat 3 --out "$OUT/devices.json" || echo "bench_devices exit $?"

stamp "GPU tests (one process, x64 as conftest sets it)"
tests=""
for t in tests/test_multilevel.py tests/test_vmap.py tests/test_float32.py \
    tests/test_lean_import.py; do
    [ -f "$t" ] && tests="$tests $t"
done
# -n 0: pyproject's addopts ask for xdist workers, which would each take the GPU
timeout "${TESTS_TIMEOUT_S:-100}" $PY -m pytest -v -n 0 -p no:cacheprovider -m "not slow" \
    --durations=15 $tests 2>&1 | tee "$OUT/tests.log" | tail -40
echo "pytest exit ${PIPESTATUS[0]} (124: killed at TESTS_TIMEOUT_S)"

stamp "bench_vmap.py (64 cantilevers: one vmapped solve vs a loop)"
timeout "${VMAP_TIMEOUT_S:-60}" $PY scripts/bench_vmap.py --batch 64 --sizes 1,16,64 \
    --repeat 2 --out "$OUT/vmap.json" || echo "bench_vmap exit $?"

stamp "done"
sleep 1  # let tee flush the log
