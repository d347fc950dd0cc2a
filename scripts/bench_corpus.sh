#!/usr/bin/env bash
# Corpus throughput benchmark: `datagen build` on a generated corpus of synthetic
# videos in every dataset layout (SA-V mp4 + RLE masklets, TAO JPEGs + boxes, YouTube-VOS and
# DAVIS JPEGs + id PNGs, cog-nvs sequence folders), 2 sampled trajectories per clip, clips of 49
# frames. Prints pairs/s, MB/s written, peak RSS and where the time went.
# Usage: scripts/bench_corpus.sh [VIDEOS_PER_LAYOUT (2)] [WIDTH (720)] [HEIGHT (480)] [FRAMES (49)]
# Builds datagen at $PROFILE (default release); BENCH_PREBUILT=1 uses the binary already built there.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

videos="${1:-2}"
width="${2:-720}"
height="${3:-480}"
frames="${4:-49}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

profile="${PROFILE:-release}"
[[ -n "${BENCH_PREBUILT:-}" ]] || cargo build --profile "$profile" -p datagen --quiet
bin=target/$([[ "$profile" == dev ]] && echo debug || echo "$profile")/datagen
printf 'width = %s\nheight = %s\nframes = %s\n' "$width" "$height" "$frames" >"$work/scene.toml"
start=$(date +%s.%N)
"$bin" synth-corpus --out "$work/trees" --videos-per-layout "$videos" --config "$work/scene.toml" >/dev/null
echo "generated $((videos * 5)) videos of ${frames} frames at ${width}x${height} in $(awk -v s="$start" -v e="$(date +%s.%N)" 'BEGIN { printf "%.1f", e - s }') s"
/usr/bin/time -f '%e %M' -o "$work/time" "$bin" build --config "$work/trees/corpus.toml" --timings >"$work/stdout"
read -r wall rss <"$work/time"
cat "$work/stdout"
echo "build: ${wall} s wall, $((rss / 1024)) MiB peak RSS, $(nproc) cores"
"$bin" inspect "$work/trees/corpus" | head -12
