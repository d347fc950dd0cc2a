#!/usr/bin/env bash
# The quickstart's main job on the embedded default input: generate the synthetic dynamic scene,
# turn it into training pairs, and export them for a look. Everything lands under out/.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
out="${1:-out}"
# The dev profile (optimised; see Cargo.toml) is the one the tests build too. The
# binary is built with the whole workspace selected (`--workspace --bin`, not `-p datagen`): Cargo
# enables a dependency's features by the packages selected, and `-p datagen` alone would leave out
# features the trainer turns on (serde's `alloc`, ...), giving serde, arrow, parquet, image and
# dozens more a second build in `scripts/test.sh`. Selected like this, the test build reuses them.
cargo build --workspace --bin datagen --quiet
datagen=./target/debug/datagen
echo "==> datagen synth: a ray-traced dynamic scene with exact ground truth"
"$datagen" synth --out "$out/synth"
echo "==> datagen pairs: 2 sampled trajectories, exact co-visibility masks, one shard"
rm -rf "$out/pairs" "$out/export"
"$datagen" pairs "$out/synth" --out "$out/pairs" --seed 0
echo "==> datagen inspect: statistics and an export of every pair"
"$datagen" inspect "$out/pairs" --export "$out/export" | tail -n 4
echo
echo "Open $out/export/*/contact_sheet.png: rows are frames; columns are target | co-visibility mask | conditioning (masked source) | novel-view render."
