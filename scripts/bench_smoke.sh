#!/usr/bin/env bash
# Every benchmark script of this checkout at its smallest size, on the binaries the test build
# made (PROFILE=dev, BENCH_PREBUILT=1), so that none breaks unnoticed: a failing script fails the
# test command with its output. Figures from these runs mean nothing; run the scripts at their
# default sizes to measure. (`bench_pairs_vs.sh` builds another commit and is not run here.)
# Usage: scripts/bench_smoke.sh (after `cargo test --workspace`, as scripts/test.sh runs it)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
# The mid-size training config with one block instead of 8 (same widths and text shape).
export PROFILE=dev BENCH_PREBUILT=1 BENCH_MID_LAYERS=1
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
printf 'width = 64\nheight = 48\nframes = 9\n' >"$work/scene.toml"

smoke() {
    local name="$1"
    shift
    local start=$SECONDS
    if ! "$@" >"$work/$name.log" 2>&1; then
        cat "$work/$name.log"
        echo "bench smoke: $name FAILED: $*" >&2
        exit 1
    fi
    echo "bench smoke: $name ok ($((SECONDS - start)) s)"
}

smoke pairs bash scripts/bench_pairs.sh 1 2 image-grids "$work/scene.toml"
smoke pairs-cwbvh bash scripts/bench_pairs.sh 1 2 cwbvh "$work/scene.toml"
smoke corpus bash scripts/bench_corpus.sh 1 64 48 9
smoke trajectory-stats bash scripts/trajectory_stats.sh "$work/trajectory_stats" 1
smoke train bash scripts/bench_train.sh 3
smoke plan bash scripts/bench_plan.sh 3
smoke checkpoint bash scripts/bench_checkpoint.sh 1 1 1
COST_ROUNDS=1 COST_STEPS=1 CHECK_MIB=1 CHECK_ITERATIONS=2 smoke distributed bash scripts/bench_distributed.sh 3
smoke eval bash scripts/bench_eval.sh 1 2
smoke transformer .venv/bin/python scripts/bench_transformer.py --configs tiny --steps 1 --warmup 0 --repeats 1
