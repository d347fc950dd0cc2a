#!/usr/bin/env bash
# Checkpoint write speed on this machine's disk, through the trainer's own checkpoint code: a
# transformer of the 5B model's width (48 heads x 64, time embedding 512, 226 text tokens of
# width 4096) with LAYERS of its 42 blocks (default 2: ~1 GB of fp32 weights, ~3 GB per
# checkpoint with the AdamW moments) on the tiny VAE's 64x80 frames, trained STEPS steps with a
# checkpoint after each (`keep_last = 1`). Every write streams the tensors through the BLAKE3
# digest to disk and fsyncs each file and the folder. Interleaved with each run, `dd` writes the
# same number of bytes with one fsync at the end (the disk's plain sequential rate). Prints the
# seconds per GB of both, and what they mean for a checkpoint of the paper's model (22.5 GB of
# fp32 weights + 45 GB of AdamW moments; under ZeRO-2 on 8 ranks rank 0 writes the weights and
# its 1/8 of the moments). Check `uptime` first: other jobs share the disk.
# Usage: scripts/bench_checkpoint.sh [LAYERS (2)] [STEPS (3)] [RUNS (2)]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

layers="${1:-2}"
steps="${2:-3}"
runs="${3:-2}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

source scripts/bench_common.sh

cat >"$work/wide.json" <<JSON
{"_class_name": "CogVideoXTransformer3DModel", "num_attention_heads": 48, "attention_head_dim": 64,
 "in_channels": 32, "out_channels": 16, "num_layers": $layers, "text_embed_dim": 4096, "max_text_seq_length": 226,
 "time_embed_dim": 512, "sample_width": 10, "sample_height": 8, "sample_frames": 9,
 "use_rotary_positional_embeddings": true, "use_learned_positional_embeddings": true}
JSON
sed -e "s|^transformer = .*|transformer = \"$work/wide.json\"\nzero_text_embedding = true|" -e "s|^steps = .*|steps = $steps|" \
    -e "s|^batch_size = .*|batch_size = 1|" -e "s|^checkpoint_every = .*|checkpoint_every = 1|" \
    -e "s|^keep_last = .*|keep_last = 1|" -e "s|^validate_every = .*|validate_every = 0|" \
    configs/pretrain_tiny.toml >"$work/wide.toml"
echo "load before: $(uptime)"
: >"$work/trainer.txt"
: >"$work/dd.txt"
for run in $(seq "$runs"); do
    rm -rf "$work/run"
    "$trainer" pretrain --config "$work/wide.toml" --shards "$work/pairs" --out "$work/run" 2>&1 >/dev/null \
        | sed -n 's/^checkpoint .*: \([0-9.]*\) GB in \([0-9.]*\) s .*/\1 \2/p' | tee -a "$work/trainer.txt"
    bytes=$(python3 -c "print(int(float('$(tail -n 1 "$work/trainer.txt" | cut -d' ' -f1)') * 1e9))")
    rm -rf "$work/run"
    started=$(date +%s.%N)
    dd if=/dev/zero of="$work/dd.bin" bs=64M count=$((bytes / (64 << 20) + 1)) conv=fsync status=none
    echo "$(python3 -c "print($bytes / 1e9, $(date +%s.%N) - $started)")" | tee -a "$work/dd.txt"
    rm -f "$work/dd.bin"
done
echo "load after: $(uptime)"
python3 - "$work/trainer.txt" "$work/dd.txt" <<'EOF'
import statistics, sys

def per_gb(path):
    rows = [tuple(map(float, line.split())) for line in open(path) if line.strip()]
    return statistics.median(s / gb for gb, s in rows), len(rows), rows[0][0]

ckpt, n, gb = per_gb(sys.argv[1])
dd, m, _ = per_gb(sys.argv[2])
print(f"checkpoint writes: {ckpt:.2f} s/GB ({1 / ckpt:.2f} GB/s; median of {n} writes of {gb:.2f} GB)")
print(f"dd with fsync:     {dd:.2f} s/GB ({1 / dd:.2f} GB/s; median of {m})")
# The paper's model: 5B fp32 weights 22.5 GB + AdamW moments 45 GB.
weights, moments, ranks = 22.5, 45.0, 8
for what, gigabytes in [("ZeRO-0, rank 0 writes all", weights + moments),
                        (f"ZeRO-2 on {ranks} ranks, rank 0's share", weights + moments / ranks)]:
    print(f"5B checkpoint, {what}: {gigabytes:.1f} GB -> {gigabytes * ckpt / 60:.1f} min at this rate")
EOF
