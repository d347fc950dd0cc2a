#!/usr/bin/env bash
# The memory plan against measurement: for the tiny preset and the mid-size
# transformer of scripts/bench_train.sh (8 blocks, 12 heads x 64, 226 text tokens of width 4096,
# tiny VAE, batch 1 of 9 frames at 64x80), with and without activation checkpointing, prints
# `trainer plan --device cpu`'s predicted peak next to the peak RSS `/usr/bin/time -f %M` measures
# for `trainer pretrain` on this CPU, and their relative difference (target: within 15 %). Then
# the 5B presets on paper: the plan's per-GPU peak next to the published anchors (CogVideo's
# finetune README / cogvideox-factory / finetrainers for CogVideoX-5B at 49x480x720 with
# checkpointing: LoRA rank 128 about 20-24 GB, full SFT about 42 GB per GPU under ZeRO-2 on 8).
# Usage: scripts/bench_plan.sh [STEPS (6)]   (PROFILE=release to use the release build)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

steps="${1:-6}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

PROFILE="${PROFILE:-dev}" source scripts/bench_common.sh

# Bytes of the plan's "total (predicted peak)" line.
predicted() {
    "$trainer" plan --config "$1" --device "$2" ${3:+--world-size "$3"} | python3 -c "
import re, sys
text = sys.stdin.read()
value, unit = re.search(r'total \(predicted peak\)\s+([0-9.]+) (GiB|MiB)', text).groups()
print(int(float(value) * (1 << (30 if unit == 'GiB' else 20))))"
}
mib() { python3 -c "print(f'{$1 / 2**20:.0f}')"; }

/usr/bin/time -f '%M' -o "$work/baseline.rss" "$trainer" --help >/dev/null
echo "process baseline (trainer --help): $(( $(cat "$work/baseline.rss") / 1024 )) MiB peak RSS" \
    "(the plan counts 912 MiB of runtime: libraries + thread pools, calibrated on the tiny row)"
printf '%-18s %14s %14s %9s\n' config predicted measured error
for model in tiny tiny-checkpointed mid mid-checkpointed; do
    transformer="tiny"
    [[ "$model" == mid* ]] && transformer="$work/mid.json"
    sed -e "s|^transformer = .*|transformer = \"$transformer\"\nzero_text_embedding = true|" -e "s|^steps = .*|steps = $steps|" \
        -e "s|^batch_size = .*|batch_size = 1|" -e "s|^checkpoint_every = .*|checkpoint_every = 1000000|" \
        -e "s|^validate_every = .*|validate_every = 0|" \
        configs/pretrain_tiny.toml >"$work/$model.toml"
    [[ "$model" == *-checkpointed ]] && echo "gradient_checkpointing = true" >>"$work/$model.toml"
    plan=$(predicted "$work/$model.toml" cpu)
    /usr/bin/time -f '%M' -o "$work/$model.rss" "$trainer" pretrain --config "$work/$model.toml" \
        --shards "$work/pairs" --out "$work/run-$model" >/dev/null 2>&1
    measured=$(( $(cat "$work/$model.rss") * 1024 ))
    printf '%-18s %10s MiB %10s MiB %8s\n' "$model" "$(mib "$plan")" "$(mib "$measured")" \
        "$(python3 -c "print(f'{($plan - $measured) / $measured * 100:+.1f} %')")"
done

echo
echo "5B presets on paper (per GPU; bf16, checkpointing, 49x480x720):"
printf '%-28s %6s %14s   %s\n' preset ranks predicted "published anchor"
for row in "finetune_5b_lora_1gpu 1 LoRA r128: about 20-24 GB" "finetune_5b_full 8 full SFT ZeRO-2 x8: about 42 GB" \
    "pretrain_cognvs_5b 8 full SFT ZeRO-2 x8: about 42 GB"; do
    read -r preset ranks anchor <<<"$row"
    plan=$(predicted "configs/$preset.toml" cuda "$ranks")
    printf '%-28s %6s %10s GB   %s\n' "$preset" "$ranks" "$(python3 -c "print(f'{$plan / 1e9:.1f}')")" "$anchor"
done
