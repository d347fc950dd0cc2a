#!/usr/bin/env bash
# Benchmark of `datagen pairs` end to end: a 49-frame 480×720 synthetic sequence
# (configs/synth_paper_size.toml), 2 sampled trajectories, video decode through shard write.
# Prints every run's wall time, peak RSS and phase split, then the median wall time and the
# largest peak RSS. Usage: scripts/bench_pairs.sh [RUNS (default 5)] [THREADS (default: all)]
# [ACCELERATOR: image-grids (default) | cwbvh, the obvhs BVH, for comparison]
# [SCENE: a `datagen synth` TOML (default configs/synth_paper_size.toml)]. Builds datagen at
# $PROFILE (default release); BENCH_PREBUILT=1 uses the binary already built there.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

runs="${1:-5}"
if [[ -n "${2:-}" ]]; then export RAYON_NUM_THREADS="$2"; fi
accelerator="${3:-image-grids}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
printf '[covisibility.mesh]\naccelerator = "%s"\n' "$accelerator" >"$work/pairs.toml"

profile="${PROFILE:-release}"
[[ -n "${BENCH_PREBUILT:-}" ]] || cargo build --profile "$profile" -p datagen --quiet
bin=target/$([[ "$profile" == dev ]] && echo debug || echo "$profile")/datagen
"$bin" synth --config "${4:-configs/synth_paper_size.toml}" --out "$work/seq" >/dev/null

walls=()
rss_max=0
for run in $(seq 1 "$runs"); do
    rm -rf "$work/out"
    /usr/bin/time -f '%e %M' -o "$work/time" "$bin" pairs "$work/seq" --out "$work/out" --trajectories 2 \
        --config "$work/pairs.toml" --timings >"$work/stdout" 2>"$work/stderr"
    read -r wall rss <"$work/time"
    walls+=("$wall")
    (( rss > rss_max )) && rss_max=$rss
    echo "run $run: ${wall} s wall, $((rss / 1024)) MiB peak RSS; $(grep '^timings' "$work/stderr")"
done
median=$(printf '%s\n' "${walls[@]}" | sort -g | awk '{a[NR]=$1} END {print (NR % 2) ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2}')
echo "$accelerator: median wall ${median} s over ${runs} runs; peak RSS $((rss_max / 1024)) MiB"
grep -v '^wrote' "$work/stdout" || true
