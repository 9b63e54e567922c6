#!/usr/bin/env bash
# One call of a GPU machine: set up (bench/gpu/setup.sh), run the GPU tests, then the table of
# bench/gpu/table.py on one sequence, within GSC_GPU_BUDGET_S seconds (default 420: a run still
# going then stops after its frame, and the call ends within 8 minutes). Results go to OUT
# (default bench_out/gpu): setup.json, gpu_tests.txt, gpu_SEQ.json (rewritten after every run)
# and gpu_SEQ.log (all of this script's output).
#
#   bash bench/gpu/table.sh                # tabletop, 50 frames, 640x480, paper preset, gsplat:
#                                          # unpruned, then PWAS pruning; and pytest -m gpu
#   bash bench/gpu/table.sh --cpu-smoke    # the same steps on the CPU, tiny (3 frames, 64x48)
#   bash bench/gpu/table.sh --seq frag1 --no-tests   # (bench/gpu/sequences.sh)
#   bash bench/gpu/table.sh -- --set mapping.final_iters=1000   # after --: table.py's options
#
# Carry bench/gpu/wheels (fetch_wheels.sh) and bench/gpu/data (stage_data.sh) with the tree.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
smoke=()
seq=tabletop
tests=1
table_args=()
while [ $# -gt 0 ]; do
    case $1 in
        --cpu-smoke) smoke=(--cpu-smoke) ;;
        --seq) seq=$2; shift ;;
        --no-tests) tests=0 ;;
        --parallel) table_args+=(--parallel) ;;
        --) shift; table_args+=("$@"); break ;;
        *) echo "usage: table.sh [--cpu-smoke] [--seq NAME] [--no-tests] [--parallel] [-- TABLE_PY_OPTIONS]" >&2; exit 2 ;;
    esac
    shift
done
export OUT=${OUT:-$root/bench_out/gpu}
build=${GSC_GPU_BUILD:-$root/bench/gpu/.build}
budget=${GSC_GPU_BUDGET_S:-420}
start=$(date +%s)
mkdir -p "$OUT"
name=$(basename "$seq")
exec > >(tee -a "$OUT/gpu_$name.log") 2>&1
cd "$root"
echo "table.sh: $(date -u +%FT%TZ) ${smoke[*]:-gpu} $seq, budget $budget s"

bash "$here/setup.sh" "${smoke[@]}"
# shellcheck source=/dev/null
source "$build/env.sh"

tests_outcome="not run (--no-tests)"
if [ "$tests" = 1 ]; then
    # gsplat against the torch and cpu backends, and the SLAM on CUDA against the CPU's
    t0=$(date +%s)
    rc=0
    timeout "${GSC_GPU_TEST_TIMEOUT:-180}" "$GSC_GPU_PY" -m pytest -q -m gpu -p no:cacheprovider \
        tests/test_render.py tests/test_cuda.py >"$OUT/gpu_tests.txt" 2>&1 || rc=$?
    cat "$OUT/gpu_tests.txt"
    summary=$(grep -E "passed|failed|skipped|error" "$OUT/gpu_tests.txt" | tail -n 1 || true)
    tests_outcome="exit $rc in $(( $(date +%s) - t0 )) s: ${summary:-no summary}"
    echo "table.sh: pytest -m gpu: $tests_outcome"
fi

left=$(( budget - ($(date +%s) - start) ))
if [ "$left" -lt 60 ]; then
    echo "table.sh: only $left s left of $budget: no table" >&2
    exit 1
fi
"$GSC_GPU_PY" "$here/table.py" "$seq" "${smoke[@]}" --deadline-s "$(( left - 10 ))" \
    --json-out "$OUT/gpu_$name.json" --setup-json "$OUT/setup.json" \
    --gpu-tests "$tests_outcome" "${table_args[@]}"
echo "table.sh: done in $(( $(date +%s) - start )) s"
