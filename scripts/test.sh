#!/usr/bin/env bash
# The full test suite, exactly as CI runs it: formatting, lints (warnings are errors), and every
# test of every crate (unit, integration, end-to-end, numerical parity against diffusers), then
# every benchmark script at its smallest size (scripts/bench_smoke.sh), then a one-node Slurm
# cluster started and stopped by scripts/test_slurm.sh (needs root, as setup does), then the GPU
# check's rehearsal on the CPU.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

echo "==> cargo fmt --check"
cargo fmt --all --check
echo "==> no module imports one that imports it back"
python3 scripts/check_module_cycles.py --self-test
python3 scripts/check_module_cycles.py --layers docs/ARCHITECTURE.md --workspace Cargo.toml
# Clippy runs as the compiler of the workspace's own crates during the test build (what `cargo
# clippy` does inside a `cargo check`), so it lints every target the tests compile (libraries,
# binaries, tests, examples) without `cargo clippy`'s second, check-mode build of every dependency
# (8 of a fresh machine's minutes). CLIPPY_ARGS is how `cargo clippy -- ARGS` hands ARGS to it.
echo "==> cargo test, every workspace crate linted by clippy as it compiles (warnings are errors)"
clippy_driver="$(rustc --print sysroot)/bin/clippy-driver"
[[ -x "$clippy_driver" ]] || { echo "clippy-driver not found at $clippy_driver: rustup component add clippy" >&2; exit 1; }
RUSTC_WORKSPACE_WRAPPER="$clippy_driver" CLIPPY_ARGS="-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__" \
    cargo test --workspace --locked
echo "==> every benchmark script at its smallest size, on the test build"
bash scripts/bench_smoke.sh
echo "==> one-node Slurm: corpus build array and a 2-task srun of trainer pretrain"
bash scripts/test_slurm.sh
# The GPU check as the GPU machine runs it (bundle, library stubs, stage deadlines), on tiny models
# on the CPU: a library the runs need that the bundle only stubs, or a broken stage, fails here.
echo "==> GPU check rehearsal: scripts/gpu_check.sh run --tiny from a bundle of the dev build"
bash scripts/gpu_check.sh rehearse
