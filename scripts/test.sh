#!/usr/bin/env bash
# The full test suite, exactly as CI runs it: formatting, lints (warnings are errors), and every
# test of every crate (unit, integration, end-to-end, numerical parity against diffusers), then a
# one-node Slurm cluster started and stopped by scripts/test_slurm.sh (needs root, as setup does).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

echo "==> cargo fmt --check"
cargo fmt --all --check
echo "==> cargo clippy (warnings are errors)"
cargo clippy --workspace --all-targets --locked -- -D warnings
echo "==> cargo test"
cargo test --workspace --locked
echo "==> one-node Slurm: corpus build array and a 2-task srun of trainer pretrain"
bash scripts/test_slurm.sh
