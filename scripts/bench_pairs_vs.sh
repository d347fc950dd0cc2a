#!/usr/bin/env bash
# Side-by-side benchmark of `datagen pairs`: the working tree against commit REV on
# the job of scripts/bench_pairs.sh (configs/synth_paper_size.toml: 49 frames at 480×720, 2
# sampled trajectories, video decode through shard write). REV is built from `git archive REV`
# under target/bench_vs/REV with its own CARGO_TARGET_DIR, the working tree's datagen (release)
# under target/bench_vs/working-tree-target (the shared target/ is not locked by the benchmark).
# Runs alternate A B A B ... so that load from other processes on the machine hits both alike;
# prints every run (wall, peak RSS, the --timings split), the medians, ranges and largest peak
# RSS of each, the ratio of medians, the median of the per-run ratios, and whether the decoded
# masks of the two programs are identical (every run's shards are compared; needs .venv with
# pyarrow and Pillow).
# Usage: scripts/bench_pairs_vs.sh [REV (aee6d46)] [RUNS (5)] [THREADS (default: all)]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

rev="${1:-aee6d46}"
runs="${2:-5}"
if [[ -n "${3:-}" ]]; then export RAYON_NUM_THREADS="$3"; fi
commit="$(git rev-parse --short=12 "$rev^{commit}")"
base="target/bench_vs/$rev"
root="$PWD"

if [[ ! -f "$base/src/Cargo.toml" || "$(cat "$base/commit" 2>/dev/null)" != "$commit" ]]; then
    rm -rf "$base/src"
    mkdir -p "$base/src"
    git archive "$commit" | tar -x -C "$base/src"
    echo "$commit" >"$base/commit"
fi
# Revisions before the workspace narrowed ffmpeg-next's features (aee6d46 among them) build it with
# its defaults, which also link libavfilter, libavdevice and libswresample: scripts/setup.sh
# installs only the four libraries the working tree needs, so the others are installed here,
# as setup installs its packages, when pkg-config lacks them.
bench_packages=(libavfilter-dev libavdevice-dev libswresample-dev)
if ! pkg-config --exists libavfilter libavdevice libswresample; then
    echo "installing ${bench_packages[*]} (FFmpeg libraries that older revisions link) ..."
    sudo_cmd=()
    [[ $(id -u) -ne 0 ]] && sudo_cmd=(sudo)
    "${sudo_cmd[@]}" apt-get update -qq
    DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq "${bench_packages[@]}"
fi
echo "building $rev ($commit) in $base (release) ..."
(cd "$base/src" && CARGO_TARGET_DIR="$root/$base/target" cargo build --release -p datagen --quiet)
cp "$base/target/release/datagen" "$base/datagen-$commit"
# The working tree builds in a target folder of its own (the path crates of both trees get the same
# artifact names, so one folder would mix them), seeded with REV's compiled dependencies (the same
# versions) minus the two path crates, so the dependencies do not compile a second time.
tree_target="$root/target/bench_vs/working-tree-target"
if [[ ! -d "$tree_target" ]]; then
    cp -a "$base/target" "$tree_target"
    rm -rf "$tree_target"/release/{.fingerprint,deps}/{lib,}{schemas,datagen}-* "$tree_target/release/datagen"
fi
echo "building the working tree (release) ..."
CARGO_TARGET_DIR="$tree_target" cargo build --release -p datagen --quiet
bin_a="$base/datagen-$commit"
bin_b="$tree_target/release/datagen"

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
printf '[covisibility.mesh]\naccelerator = "image-grids"\n' >"$work/pairs.toml"
"$bin_b" synth --config configs/synth_paper_size.toml --out "$work/seq" >/dev/null

python=.venv/bin/python
compare_masks() {
    "$python" - "$1" "$2" <<'EOF'
import io, sys
import numpy as np, pyarrow.parquet as pq
from PIL import Image
a, b = (pq.read_table(p).to_pylist() for p in sys.argv[1:3])
decode = lambda png: np.asarray(Image.open(io.BytesIO(png)))
pairs = [(x, y) for ra, rb in zip(a, b) for ta, tb in zip(ra["trajectories"], rb["trajectories"])
         for x, y in zip(ta["covisible_mask"], tb["covisible_mask"])]
same = len(a) == len(b) and len(pairs) > 0 and all(np.array_equal(decode(x), decode(y)) for x, y in pairs)
print("identical" if same else "DIFFERENT", len(pairs), "masks")
EOF
}

declare -A walls rss_max
walls=([a]="" [b]="")
rss_max=([a]=0 [b]=0)
mask_report=""
for run in $(seq 1 "$runs"); do
    for side in a b; do
        bin="bin_$side"
        rm -rf "$work/out_$side"
        /usr/bin/time -f '%e %M' -o "$work/time" "${!bin}" pairs "$work/seq" --out "$work/out_$side" \
            --trajectories 2 --config "$work/pairs.toml" --timings >"$work/stdout" 2>"$work/stderr"
        read -r wall rss <"$work/time"
        walls[$side]+="$wall "
        (( rss > rss_max[$side] )) && rss_max[$side]=$rss
        label=$([[ $side == a ]] && echo "$rev" || echo "working tree")
        echo "run $run $label: ${wall} s wall, $((rss / 1024)) MiB peak RSS; $(grep '^timings' "$work/stderr")"
    done
    if [[ -x "$python" ]]; then
        result="$(compare_masks "$work/out_a/seq.parquet" "$work/out_b/seq.parquet")"
        echo "run $run masks: $result"
        [[ "$result" == identical* ]] || mask_report="masks DIFFER in run $run"
    fi
done

stats() {
    printf '%s\n' $1 | sort -g | awk '{a[NR]=$1} END {
        m = (NR % 2) ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2; printf "%.3f %.3f %.3f", m, a[1], a[NR] }'
}
read -r med_a min_a max_a <<<"$(stats "${walls[a]}")"
read -r med_b min_b max_b <<<"$(stats "${walls[b]}")"
echo "$rev: median ${med_a} s (range ${min_a}–${max_a} s), peak RSS $((rss_max[a] / 1024)) MiB over $runs runs"
echo "working tree: median ${med_b} s (range ${min_b}–${max_b} s), peak RSS $((rss_max[b] / 1024)) MiB over $runs runs"
awk -v a="$med_a" -v b="$med_b" 'BEGIN { printf "speed-up of medians: %.2f×\n", a / b }'
# Each run's two sides ran back to back, so their ratio cancels most of the load that drifts
# between runs: the median of those per-run ratios is the steadier figure when the load moves.
read -r -a list_a <<<"${walls[a]}"
read -r -a list_b <<<"${walls[b]}"
ratios=""
for i in "${!list_a[@]}"; do ratios+="$(awk -v a="${list_a[$i]}" -v b="${list_b[$i]}" 'BEGIN { printf "%.4f", a / b }') "; done
read -r med_r min_r max_r <<<"$(stats "$ratios")"
echo "speed-up run by run (${rev} ÷ working tree, same run): median ${med_r}× (range ${min_r}–${max_r}×)"
echo "${mask_report:-masks: identical in every run}"
echo "$(nproc) cores, RAYON_NUM_THREADS=${RAYON_NUM_THREADS:-all}; other load on the machine moves every figure:"
echo "only figures from one interleaved run compare."
