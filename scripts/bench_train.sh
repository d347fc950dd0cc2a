#!/usr/bin/env bash
# Training step time and peak RSS of `trainer pretrain` on this CPU (issue 6 §7): the tiny preset
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

profile="${PROFILE:-release}"
cargo build --profile "$profile" -p datagen -p trainer --quiet
bin_dir=target/$([[ "$profile" == dev ]] && echo debug || echo "$profile")
datagen=$bin_dir/datagen
trainer=$bin_dir/trainer
"$datagen" synth --width 80 --height 64 --frames 33 --out "$work/seq" >/dev/null
printf '[clip]\nlength = 9\nstride = 4\n' >"$work/clips.toml"
"$datagen" pairs "$work/seq" --out "$work/pairs" --trajectories 2 --config "$work/clips.toml" >/dev/null

cat >"$work/mid.json" <<'JSON'
{"_class_name": "CogVideoXTransformer3DModel", "num_attention_heads": 12, "attention_head_dim": 64,
 "in_channels": 32, "out_channels": 16, "num_layers": 8, "text_embed_dim": 4096, "max_text_seq_length": 226,
 "sample_width": 10, "sample_height": 8, "sample_frames": 9,
 "use_rotary_positional_embeddings": true, "use_learned_positional_embeddings": true}
JSON

for model in tiny mid mid-checkpointed; do
    transformer="tiny"
    [[ "$model" == mid* ]] && transformer="$work/mid.json"
    sed -e "s|^transformer = .*|transformer = \"$transformer\"|" -e "s|^steps = .*|steps = $steps|" \
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
