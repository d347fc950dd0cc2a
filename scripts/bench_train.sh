#!/usr/bin/env bash
# Training step time and peak RSS of `trainer pretrain` on this CPU: the tiny preset
# and a mid-size transformer (8 blocks, 12 heads x 64, 226 text tokens of width 4096) with the
# tiny VAE, batch 1 of 9 frames at 64x80 from synthetic pairs. Prints the median step time over
# the steps after warm-up and the process's peak RSS, for the mid size also with activation
# checkpointing (`[loop] gradient_checkpointing = true`) and the ratio of the two peaks.
# Usage: scripts/bench_train.sh [STEPS (8)]   (PROFILE=dev builds the test profile instead of
# release: the same memory figures without a second full build)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

steps="${1:-8}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

PROFILE="${PROFILE:-release}" source scripts/bench_common.sh

for model in tiny mid mid-checkpointed; do
    transformer="tiny"
    [[ "$model" == mid* ]] && transformer="$work/mid.json"
    sed -e "s|^transformer = .*|transformer = \"$transformer\"\nzero_text_embedding = true|" -e "s|^steps = .*|steps = $steps|" \
        -e "s|^batch_size = .*|batch_size = 1|" -e "s|^checkpoint_every = .*|checkpoint_every = 1000000|" \
        -e "s|^validate_every = .*|validate_every = 0|" \
        configs/pretrain_tiny.toml >"$work/$model.toml"
    [[ "$model" == *-checkpointed ]] && echo "gradient_checkpointing = true" >>"$work/$model.toml"
    /usr/bin/time -f '%M' -o "$work/$model.rss" "$trainer" pretrain --config "$work/$model.toml" \
        --shards "$work/pairs" --out "$work/run-$model" >/dev/null
    median=$(python3 -c "
import json, statistics, sys
s = [json.loads(l)['seconds'] for l in open('$work/run-$model/metrics.jsonl')][2:]
print(f'{statistics.median(s):.3f}')")
    echo "$model: median step ${median} s (after 2 warm-up steps, $steps steps), peak RSS $(( $(cat "$work/$model.rss") / 1024 )) MiB, $(nproc) cores"
done
mid=$(cat "$work/mid.rss"); checkpointed=$(cat "$work/mid-checkpointed.rss")
echo "mid peak RSS with checkpointing / without: $(python3 -c "print(f'{$checkpointed / $mid:.2f}')")"
