#!/usr/bin/env bash
# The full test suite, exactly as CI runs it: formatting, lints (warnings are errors), and every
# test of every crate (unit, integration, end-to-end, numerical parity against diffusers).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

echo "==> cargo fmt --check"
cargo fmt --all --check
echo "==> cargo clippy (warnings are errors)"
cargo clippy --workspace --all-targets --locked -- -D warnings
echo "==> cargo test"
cargo test --workspace --locked
