#!/usr/bin/env bash
# Evidence that the trajectory bank changes the data: builds a synthetic corpus
# (`datagen synth-corpus`), harvests its cameras' own motion into a trajectory bank
# (`datagen trajectories collect`), builds the corpus twice, with the paper's spherical sampler and
# with `sampler = "bank"`, and prints the distributions of the trajectory parameters (azimuth and
# elevation span, radial change, path length) and of the co-visible fraction per pair side by side
# (n, mean, quartiles), with one SVG histogram per quantity under $OUT/plots.
#
# Usage: scripts/trajectory_stats.sh [OUT (default out/trajectory_stats)] [VIDEOS_PER_LAYOUT (default 4)]
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
out="${1:-$root/out/trajectory_stats}"
videos="${2:-4}"
# Trajectories per clip: enough pairs per corpus for quartiles to mean something.
trajectories=4

cd "$root"
# The features of the tests build (see scripts/demo.sh); BENCH_PREBUILT=1 uses the one built.
[[ -n "${BENCH_PREBUILT:-}" ]] || cargo build -q --workspace --bin datagen
datagen="$root/target/debug/datagen"

rm -rf "$out"
mkdir -p "$out"
"$datagen" synth-corpus --out "$out/data" --videos-per-layout "$videos"
"$datagen" trajectories collect --config "$out/data/corpus.toml" --out "$out/bank.parquet"

for sampler in spherical bank; do
  config="$out/corpus_$sampler.toml"
  sed -e "s/^trajectories = .*/trajectories = $trajectories/" "$out/data/corpus.toml" > "$config"
  if [[ $sampler == bank ]]; then
    printf '\n[pairs.trajectory]\nsampler = "bank"\nbank = "%s"\n' "$out/bank.parquet" >> "$config"
  fi
  "$datagen" build --config "$config" --out "$out/corpus_$sampler" | tail -1
done

"$datagen" trajectories stats spherical="$out/corpus_spherical" bank="$out/corpus_bank" --plots "$out/plots" \
  | tee "$out/stats.txt"
"$datagen" inspect "$out/corpus_bank" --report "$out/report_bank.html" | tail -1
