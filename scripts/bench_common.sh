# Sourced by the training benchmarks (bench_train.sh, bench_plan.sh, bench_distributed.sh): builds
# datagen and trainer at $PROFILE (default: the test profile, dev), makes synthetic pairs (33
# frames at 80x64, clips of 9, 2 trajectories) in $work/pairs, and writes the mid-size transformer
# config (8 blocks, 12 heads x 64, 226 text tokens of width 4096; the tiny VAE's 64x80 frames) to
# $work/mid.json. Sets $datagen and $trainer. Needs $work (a scratch folder) and the repo root as
# the working directory. BENCH_PREBUILT=1 uses the binaries already built at $PROFILE, and
# BENCH_MID_LAYERS (default 8) sets the mid-size config's blocks (the test command's smoke runs:
# scripts/bench_smoke.sh).
profile="${PROFILE:-dev}"
[[ -n "${BENCH_PREBUILT:-}" ]] || cargo build --profile "$profile" -p datagen -p trainer --quiet
bin_dir=target/$([[ "$profile" == dev ]] && echo debug || echo "$profile")
datagen=$bin_dir/datagen
trainer=$bin_dir/trainer
"$datagen" synth --width 80 --height 64 --frames 33 --out "$work/seq" >/dev/null
printf '[clip]\nlength = 9\nstride = 4\n' >"$work/clips.toml"
"$datagen" pairs "$work/seq" --out "$work/pairs" --trajectories 2 --config "$work/clips.toml" >/dev/null
cat >"$work/mid.json" <<JSON
{"_class_name": "CogVideoXTransformer3DModel", "num_attention_heads": 12, "attention_head_dim": 64,
 "in_channels": 32, "out_channels": 16, "num_layers": ${BENCH_MID_LAYERS:-8}, "text_embed_dim": 4096, "max_text_seq_length": 226,
 "sample_width": 10, "sample_height": 8, "sample_frames": 9,
 "use_rotary_positional_embeddings": true, "use_learned_positional_embeddings": true}
JSON
