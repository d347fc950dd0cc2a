#!/usr/bin/env bash
# The GPU check: the trainer's 5B figures (test-time finetuning steps with LoRA and full weights,
# sampling, NCCL) beside diffusers' on the same shapes and beside `trainer plan`'s prediction, in
# one short run on a GPU machine that has Python with torch 2.11.0+cu130 but no Rust and no
# package registry.
#
#   scripts/gpu_check.sh build      here: compile + bundle
#     compile: torch==2.11.0 from PyPI into .gpu-check/site-packages (git-ignored) with the headers
#       of the nvidia wheels it pins (build.rs then compiles the shim's NCCL half), torch-sys's
#       wrapper patched for its headers (scripts/gpu_check_patch_torch_sys.py), trainer + datagen
#       built against it in a copy of the workspace (CARGO_TARGET_DIR=target/gpu-check, release);
#     bundle: .gpu-check/bundle.tar.xz (stripped binaries, the FFmpeg and zstd libraries the runs
#       load plus stubs of the rest from scripts/gpu_check_stub_libs.py, the diffusers wheel, these
#       scripts and configs), at most 60 MiB.
#   scripts/gpu_check.sh run [--tiny] [--out DIR] [--deadline SECONDS] [--bundle FILE] [--site-packages DIR]
#     there: the stages below, each under its own timeout and all within the deadline (default
#     540 s), each appending one JSON line to OUT/results.jsonl the moment it ends (a run cut short
#     still returns what finished); OUT/env.txt first, OUT/summary.txt last. A stage that fails or
#     times out is recorded and the next one runs; the exit status is 0 when every stage that ran
#     passed. PYTHON= the Python with torch (default python3). --tiny: the same stages on tiny
#     models on the CPU (9 x 64 x 80 clips), the rehearsal.
#   scripts/gpu_check.sh rehearse   here, in CI: bundles the dev build (target/debug, built by the
#     tests) with its stubs exactly as `build` does and runs `run --tiny` from it against the venv's
#     torch, failing if any stage fails (a library the runs need that the bundle only stubs aborts).
#
# The one call on the GPU machine (the device tool; bundle ~25 MiB, the working tree travels too):
#   run(command="bash scripts/gpu_check.sh run --bundle .gpu-check/bundle.tar.xz --out $OUT",
#       carry=[".gpu-check/bundle.tar.xz"], timeout_s=600)
# then give the machine back. Results: $OUT/results.jsonl, env.txt, summary.txt, logs/.
#
# Stages, in order of value (GPU time limits in brackets):
#   data          a 49x480x720 synthetic clip and its training pair (datagen synth + pairs) [60 s]
#   lora_ours     5B LoRA test-time-finetune steps, bf16, checkpointing: step, VAE encode and
#                 transformer time (medians of 5 after a warm-up), allocator peaks, plan [120 s]
#   lora_diffusers  the same shapes with diffusers + peft (model built on the GPU) [90 s]
#   wan_lora      the Wan presets (configs/finetune_wan*.toml: Wan2.1-T2V-1.3B, Wan2.2-TI2V-5B,
#                 Wan2.1-I2V-14B at their own clip sizes): `trainer plan`'s predicted peak beside the
#                 allocator peaks of LoRA finetune steps on random weights of each preset's shape
#                 (diffusers + peft, bf16, checkpointing; scripts/gpu_check_wan.py), one preset
#                 after another, each recorded as it ends [240 s]
#   full_ours / full_diffusers  the same with all weights trained [150 s / 120 s]
#   sampling      50 DPM steps with guidance against another embedding and the VAE decode at
#                 49x480x720, diffusers (the public procedure) then ours on the same random
#                 weights and seed; timings, peaks, plan and the frames' difference [300 s]
#   nccl          torchrun --nproc-per-node 1 trainer comm-check (NCCL at world size 1) and
#                 trainer comm-cost (the overlapped exchange: streams, events, no-op baseline) [60 s]
#   parity        tiny models, sampled by both on the device in bf16: frame differences [90 s]
#   benchmark     trainer benchmark on synthetic scenes in the DyCheck and Kubric-4D layouts with
#                 the sampling stage's random 5B-shaped weights, no finetuning, 10 denoising steps:
#                 seconds per scene (sampling and whole) at the protocols' sizes. The released
#                 checkpoint and the datasets cannot be reached from the GPU machine, so the
#                 metrics say nothing about CogNVS; the stage times the path [240 s]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
gc="$root/.gpu-check"
cmd="${1:-}"; shift || true

# The nvidia wheels torch 2.11.0 pins (its METADATA: cuda-toolkit==13.0.2, nvidia-nccl-cu13==2.28.9;
# cuda-toolkit 13.0.2's METADATA pins the rest). Only their headers are used: the NCCL half of the
# c10d shim includes nccl.h and cuda_runtime_api.h, which pull in crt/ (nvcc, crt) and cuda/std
# (cccl); torch's ATen/cuda/CUDAContextLight.h includes cublas_v2.h, cublasLt.h, cusparse.h and
# cusolverDn.h.
NVIDIA_HEADER_WHEELS=(nvidia-cuda-runtime==13.0.96 nvidia-cuda-nvcc==13.0.88 nvidia-cuda-crt==13.0.88
    nvidia-cuda-cccl==13.0.85 nvidia-nccl-cu13==2.28.9 nvidia-cublas==13.1.0.3 nvidia-cusparse==12.6.3.3
    nvidia-cusolver==12.0.4.66)
# Library folders libtorch_cuda.so's RPATH names ($ORIGIN/../../nvidia/X/lib).
NVIDIA_LIB_DIRS=(cu13 nccl cudnn cusparselt nvshmem)
# What travels with one call, less room for the working tree.
BUNDLE_LIMIT_BYTES=$((60 * 1024 * 1024))

# Builds .gpu-check/site-packages/nvidia/ the way torch 2.11's wheel dependencies lay it out: the
# headers of the pinned versions above (build.rs finds nccl.h there and compiles the NCCL half), and
# the libraries as links into the venv's cu13 wheels (same sonames; here they are only loaded, for
# linking and for CPU runs, never called; the GPU machine uses its own).
nvidia_layout() {
    local py="$1" nv="$gc/site-packages/nvidia" venv_nv
    venv_nv="$("$py" -c 'import nvidia, os; print(os.path.dirname(nvidia.__path__[0]))')/nvidia"
    [[ -L "$nv" ]] && rm "$nv"
    [[ "$(cat "$nv/.headers" 2>/dev/null)" == "${NVIDIA_HEADER_WHEELS[*]}" ]] && return
    mkdir -p "$gc/wheels/nvidia"
    "$py" -m pip download --no-deps -q -d "$gc/wheels/nvidia" "${NVIDIA_HEADER_WHEELS[@]}"
    for wheel in "$gc"/wheels/nvidia/*.whl; do
        unzip -q -o "$wheel" 'nvidia/*/include/*' -d "$gc/site-packages"
    done
    for dir in "${NVIDIA_LIB_DIRS[@]}"; do
        mkdir -p "$nv/$dir/lib"
        for lib in "$venv_nv/$dir"/lib/*.so*; do ln -sf "$lib" "$nv/$dir/lib/"; done
    done
    echo "${NVIDIA_HEADER_WHEELS[*]}" >"$nv/.headers"
}

compile() {
    local py="$root/.venv/bin/python"
    mkdir -p "$gc/wheels" "$gc/site-packages"
    if [[ ! -d "$gc/site-packages/torch/lib" ]]; then
        "$py" -m pip download torch==2.11.0 --no-deps --python-version 3.12 --only-binary=:all: \
            --platform manylinux_2_28_x86_64 -d "$gc/wheels"
        (cd "$gc/site-packages" && unzip -q -o "$gc"/wheels/torch-2.11.0-*.whl 'torch/lib/*' 'torch/include/*' \
            'torch/share/*' 'torch/version.py')
    fi
    compgen -G "$gc/wheels/diffusers-*.whl" >/dev/null || "$py" -m pip download diffusers==0.42.1 --no-deps -d "$gc/wheels"
    nvidia_layout "$py"
    local torch_sys
    torch_sys="$(ls -d "$HOME"/.cargo/registry/src/*/torch-sys-0.26.0 | head -1)"
    # Patched once: re-copying would touch every file and make cargo rebuild the wrapper.
    grep -qs 'stubbed by gpu_check' "$gc/torch-sys/libtch/torch_api_generated.cpp" \
        || python3 "$root/scripts/gpu_check_patch_torch_sys.py" "$torch_sys" "$gc/torch-sys" "$gc/site-packages/torch"
    # A copy of the working tree, so the shared Cargo.toml / Cargo.lock never see the patch.
    rm -rf "$gc/ws" && mkdir -p "$gc/ws"
    (cd "$root" && git ls-files --cached --others --exclude-standard -z | grep -zv '^\.gpu-check/' \
        | while IFS= read -r -d '' f; do [[ -e "$f" ]] && printf '%s\0' "$f"; done \
        | xargs -0 cp -p --parents -t "$gc/ws")
    printf '\n[patch.crates-io]\ntorch-sys = { path = "../torch-sys" }\n' >>"$gc/ws/Cargo.toml"
    (cd "$gc/ws" && LIBTORCH="$gc/site-packages/torch" LIBTORCH_BYPASS_VERSION_CHECK=1 \
        TRAINER_NO_NCCL="${TRAINER_NO_NCCL:-0}" CARGO_TARGET_DIR="$root/target/gpu-check" \
        cargo build --release -p trainer -p datagen --bins)
}

# bundle BINARIES_DIR TORCH_LIB OUT_DIR: the folder `run` unpacks (binaries, libraries, scripts,
# configs, the diffusers wheel when one was downloaded).
bundle_dir() {
    local binaries="$1" torch_lib="$2" bundle="$3"
    rm -rf "$bundle" && mkdir -p "$bundle/bin" "$bundle/lib" "$bundle/scripts" "$bundle/configs"
    for bin in trainer datagen; do
        strip -o "$bundle/bin/$bin" "$binaries/$bin"
    done
    # FFmpeg's full closure is ~230 MB: carry the libraries an mp4 round trip and the shards load,
    # and stubs of the rest (see the script's docstring).
    python3 "$root/scripts/gpu_check_stub_libs.py" "$bundle/lib" "$torch_lib" "$bundle/bin/trainer" \
        "$bundle/bin/datagen" | tail -1
    cp "$root"/scripts/{gpu_check.sh,gpu_check_diffusers.py,gpu_check_wan.py,goldens_sampling.py} "$bundle/scripts/"
    cp "$root"/configs/{finetune_5b_lora_1gpu.toml,finetune_5b_full_1gpu.toml,comm_cost_tiny.toml} "$bundle/configs/"
    cp "$root"/configs/finetune_wan*.toml "$bundle/configs/"
    cp -r "$root/configs/wan" "$bundle/configs/"
    if compgen -G "$gc/wheels/diffusers-*.whl" >/dev/null; then cp "$gc"/wheels/diffusers-*.whl "$bundle/"; fi
}

bundle() {
    bundle_dir "$root/target/gpu-check/release" "$gc/site-packages/torch/lib" "$gc/bundle"
    local archive="$gc/bundle.tar.xz"
    tar -C "$gc" -cf - bundle | xz -T0 -6 >"$archive"
    local size; size="$(stat -c %s "$archive")"
    echo "bundle: $(du -sh "$gc/bundle" | cut -f1) unpacked, $archive $((size / 1048576)) MiB"
    (( size <= BUNDLE_LIMIT_BYTES )) || { echo "bundle over $((BUNDLE_LIMIT_BYTES / 1048576)) MiB" >&2; exit 1; }
}

rehearse() {
    local py="$root/.venv/bin/python" site out="$root/target/gpu-check-rehearsal"
    site="$("$py" -c 'import os, torch; print(os.path.dirname(os.path.dirname(torch.__file__)))')"
    [[ -x "$root/target/debug/trainer" && -x "$root/target/debug/datagen" ]] \
        || (cd "$root" && cargo build --workspace --bins --quiet)
    bundle_dir "$root/target/debug" "$site/torch/lib" "$out/bundle"
    rm -rf "$out/results"
    PYTHON="$py" bash "$out/bundle/scripts/gpu_check.sh" run --tiny --site-packages "$site" --out "$out/results" \
        --deadline "${GPU_CHECK_REHEARSAL_DEADLINE:-600}"
}

# ------------------------------------------------------------------------------------------------
# run: the stages on the GPU machine (or, with --tiny, here)
# ------------------------------------------------------------------------------------------------

# Appends one stage's line to results.jsonl: name, status, seconds and the stage's own fields.
record() {
    "$PY" - "$OUT/results.jsonl" "$1" "$2" "$3" "$4" <<'PY'
import json, sys
path, name, status, seconds, fields = sys.argv[1:6]
try:
    extra = json.load(open(fields))
except (OSError, ValueError):
    extra = {}
with open(path, "a") as f:
    f.write(json.dumps({"stage": name, "status": status, "seconds": round(float(seconds), 1), **extra}) + "\n")
PY
}

# stage NAME LIMIT: runs `gpu_check.sh _stage NAME` under min(LIMIT, what the deadline leaves),
# its output in logs/NAME.log, its fields in NAME.json, and records it.
stage() {
    local name="$1" limit="$2"
    local left=$((DEADLINE_AT - $(date +%s) - 5))
    if ((left < 15)); then
        record "$name" skipped 0 /dev/null
        echo "stage $name: skipped (deadline)"
        return 0
    fi
    ((limit > left)) && limit=$left
    local start status=ok
    start=$(date +%s%N)
    echo '{}' >"$WORK/$name.json"
    timeout --kill-after=15 "$limit" bash "$SELF" _stage "$name" >"$OUT/logs/$name.log" 2>&1 || {
        local rc=$?
        if ((rc == 124 || rc == 137)); then status=timeout; else status=failed; fi
    }
    record "$name" "$status" "$((($(date +%s%N) - start) / 1000000))e-3" "$WORK/$name.json"
    echo "stage $name: $status ($(tail -n 1 "$OUT/results.jsonl" | cut -c1-220))"
    [[ $status == ok ]] || FAILED=1
}

# Merges KEY=VALUE fields (JSON values or plain strings) into the running stage's JSON.
fields() {
    "$PY" - "$WORK/$STAGE.json" "$@" <<'PY'
import json, sys
path, pairs = sys.argv[1], sys.argv[2:]
data = json.load(open(path))
for pair in pairs:
    key, value = pair.split("=", 1)
    try:
        data[key] = json.loads(value)
    except ValueError:
        data[key] = value
json.dump(data, open(path, "w"))
PY
}

# The predicted peak of `trainer plan ARGS...`, in GiB.
plan_gib() {
    "$BIN/trainer" plan "$@" | "$PY" -c '
import re, sys
m = re.search(r"total \(predicted peak\)\s+([\d.]+) (GiB|MiB)", sys.stdin.read())
print(round(float(m[1]) / (1024 if m[2] == "MiB" else 1), 3))'
}

# A training config for the measurement: PRESET's settings at the check's size, nothing saved.
training_config() {
    local preset="$1" mode="$2" out="$3"
    "$PY" - "$preset" "$mode" "$out" "$TINY" "$FRAMES" "$HEIGHT" "$WIDTH" "$TRAIN_STEPS" <<'PY'
import sys, tomllib
preset, mode, out, tiny, frames, height, width, steps = sys.argv[1:9]
config = tomllib.load(open(preset, "rb"))
config["model"].update(zero_text_embedding=True)
config["data"].update(frames=int(frames), height=int(height), width=int(width), batch_size=1)
config["loop"].update(steps=int(steps), checkpoint_every=1_000_000, validate_every=0, save_checkpoints=False)
if tiny == "1":
    transformer = config["model"]["transformer"]
    if transformer.startswith("wan"):
        # Wan's tiny structures (Wan2.2's preset on Wan2.1's VAE structure: no tiny transformer
        # takes the tiny Wan2.2 VAE's channels); the text-to-video presets train CogNVS-widened
        # models, as `tiny-cognvs` is.
        config["model"].update(transformer="tiny-i2v" if "-i2v-" in transformer else "tiny-cognvs", vae="tiny")
    else:
        config["model"].update(transformer="tiny", vae="tiny")
    config["loop"]["precision"] = "fp32"
    if "lora" in config:
        config["lora"].update(rank=4, alpha=2)  # the preset's alpha/rank of 1/2 on 32-wide layers
if mode == "full":
    config.pop("lora", None)
def value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v + '"'
    if isinstance(v, list):
        return "[" + ", ".join(value(x) for x in v) + "]"
    return repr(v)
with open(out, "w") as f:
    for table, entries in config.items():
        f.write(f"[{table}]\n" + "".join(f"{k} = {value(v)}\n" for k, v in entries.items()) + "\n")
PY
}

stage_env() {
    {
        echo "date: $(date -u +%FT%TZ)   deadline: ${DEADLINE}s   tiny: $TINY"
        uname -a
        nproc
        free -g || true
        df -h /tmp "$WORK" || true
        nvidia-smi || echo "no nvidia-smi"
        nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm,power.limit --format=csv || true
        PYTHONPATH="$PYPATH" "$PY" -c '
import torch
print("torch", torch.__version__, "cuda", torch.version.cuda, "cudnn", torch.backends.cudnn.version())
print("nccl", torch.cuda.nccl.version() if torch.cuda.is_available() else None)
print("gpu", torch.cuda.get_device_name(0) if torch.cuda.is_available() else None)
import diffusers, transformers; print("diffusers", diffusers.__version__, "transformers", transformers.__version__)' || true
        echo "libraries the trainer loads:"
        LD_LIBRARY_PATH="$LIBPATH" ldd "$HERE/bin/trainer"
        echo "bundle:"
        ls -la "$HERE" "$HERE/lib" | head -80
    } >"$OUT/env.txt" 2>&1
    fields "gpu=$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1 || echo none)"
}

stage_data() {
    "$BIN/datagen" synth --width "$WIDTH" --height "$HEIGHT" --frames "$FRAMES" --out "$WORK/seq"
    printf '[clip]\nlength = %s\nstride = %s\n' "$FRAMES" "$FRAMES" >"$WORK/clips.toml"
    "$BIN/datagen" pairs "$WORK/seq" --out "$WORK/pairs" --trajectories 1 --config "$WORK/clips.toml"
    fields "frames=$FRAMES" "height=$HEIGHT" "width=$WIDTH"
}

# Our training steps: plan, run, medians of the steps after the first.
train_ours() {
    local mode="$1" preset="$2" config="$WORK/$1.toml"
    training_config "$preset" "$mode" "$config"
    fields "plan_gib=$(plan_gib --config "$config" --world-size 1 --device "$DEVICE")"
    "$BIN/trainer" pretrain --config "$config" --shards "$WORK/pairs" --out "$WORK/run-$mode" --device "$DEVICE"
    "$PY" - "$WORK/run-$mode/metrics.jsonl" "$WORK/$STAGE.json" <<'PY'
import json, statistics, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
later = rows[1:] or rows
gib = lambda b: None if b is None else b / (1 << 30)
peak = lambda key: max((r.get(key) or 0 for r in rows), default=0) or None
data = json.load(open(sys.argv[2]))
data.update(steps=len(rows), warmup_step_s=rows[0]["seconds"],
            median_step_s=statistics.median(r["seconds"] for r in later),
            median_encode_s=statistics.median(r["encode_seconds"] for r in later),
            median_transformer_step_s=statistics.median(r["seconds"] - r["encode_seconds"] for r in later),
            peak_allocated_gib=gib(peak("cuda_peak_allocated")), peak_reserved_gib=gib(peak("cuda_peak_reserved")))
json.dump(data, open(sys.argv[2], "w"))
PY
}

train_diffusers() {
    local mode="$1" line
    line="$(PYTHONPATH="$PYPATH" "$PY" "$HERE/scripts/gpu_check_diffusers.py" --mode "$mode" --steps "$TRAIN_STEPS" \
        --device "$DEVICE" $( ((TINY)) && echo --tiny) | tail -n 1)"
    echo "$line"
    "$PY" -c 'import json, sys; d = json.load(open(sys.argv[1])); d.update(json.loads(sys.argv[2])); json.dump(d, open(sys.argv[1], "w"))' \
        "$WORK/$STAGE.json" "$line"
}

stage_lora_ours() { train_ours lora "$HERE/configs/finetune_5b_lora_1gpu.toml"; }

# Each Wan preset at its own clip size (the check's tiny size with --tiny): the plan's predicted
# peak and a diffusers + peft LoRA step's measured peaks, as `PRESET={...}` fields, all presets in
# one Python process (one import of torch and diffusers). A preset that runs out of memory is
# recorded and the next one still runs; the stage then fails.
stage_wan_lora() {
    local name config plans=() configs=() size=() steps=2 status=0
    # The rehearsal: every preset's plan, and one step of the image-to-video one on the tiny
    # shapes (the path, image cross-attention's adapters included; the tiny presets are alike).
    ((TINY)) && size=(--tiny --frames "$FRAMES" --height "$HEIGHT" --width "$WIDTH") steps=1
    for name in finetune_wan21_1.3b_lora_24gb finetune_wan22_ti2v_5b_lora_1gpu finetune_wan21_i2v_14b_lora_80gb; do
        config="$HERE/configs/$name.toml"
        [[ $TINY == 0 || $name == finetune_wan21_i2v_14b_lora_80gb ]] && configs+=(--config "$config")
        if ((TINY)); then
            config="$WORK/$name.toml"
            training_config "$HERE/configs/$name.toml" lora "$config"
        fi
        plans+=("$name=$(plan_gib --config "$config" --world-size 1 --device "$DEVICE")")
    done
    PYTHONPATH="$PYPATH" "$PY" "$HERE/scripts/gpu_check_wan.py" "${configs[@]}" --configs-dir "$HERE/configs/wan" \
        --device "$DEVICE" --steps "$steps" "${size[@]}" | tee "$WORK/wan_lora.out" || status=1
    "$PY" - "$WORK/wan_lora.out" "$WORK/$STAGE.json" "${plans[@]}" <<'PY'
import json, sys
out, fields, plans = sys.argv[1], sys.argv[2], dict(p.split("=", 1) for p in sys.argv[3:])
data = json.load(open(fields))
for line in open(out):
    if line.startswith("{"):
        row = json.loads(line)
        data[row["preset"]] = dict(row, plan_gib=float(plans.pop(row["preset"])))
data.update({name: dict(plan_gib=float(gib)) for name, gib in plans.items()})  # planned, not run
json.dump(data, open(fields, "w"))
PY
    return "$status"
}

stage_lora_diffusers() { train_diffusers lora; }
stage_full_ours() { train_ours full "$HERE/configs/finetune_5b_full_1gpu.toml"; }
stage_full_diffusers() { train_diffusers full; }

# Compares two folders of PNG frames: mean and max difference, share beyond 1 and 4 levels.
compare_frames() {
    "$PY" - "$1" "$2" <<'PY'
import json, sys
from pathlib import Path
import numpy as np
from PIL import Image
read = lambda d: np.stack([np.asarray(Image.open(p), dtype=np.int16) for p in sorted(Path(d).glob("*.png"))])
a, b = read(sys.argv[1]), read(sys.argv[2])
if a.shape != b.shape:
    print(json.dumps({"shapes": [list(a.shape), list(b.shape)]}))
    sys.exit(1)
d = np.abs(a - b)
print(json.dumps({"mean_levels": float(d.mean()), "max_levels": int(d.max()),
                  "beyond_1": float((d > 1).mean()), "beyond_4": float((d > 4).mean())}))
PY
}

# Samples the golden case CASE (goldens_sampling.py's folder) with ours: flags as the case says.
sample_ours() {
    local folder="$1" out="$2" meta
    meta="$(cat "$folder/case.json")"
    local steps seed guidance extra=()
    steps="$("$PY" -c 'import json,sys; print(json.loads(sys.argv[1])["steps"])' "$meta")"
    seed="$("$PY" -c 'import json,sys; print(json.loads(sys.argv[1])["seed"])' "$meta")"
    guidance="$("$PY" -c 'import json,sys; print(json.loads(sys.argv[1])["guidance"])' "$meta")"
    [[ -f "$folder/negative.safetensors" ]] && extra+=(--negative-text-embedding "$folder/negative.safetensors")
    grep -q '"tiling": false' "$folder/case.json" && extra+=(--no-vae-tiling)
    local frames size
    frames="$(ls "$folder/cond" | wc -l)"
    size="$("$PY" -c 'import sys; from PIL import Image; w, h = Image.open(sys.argv[1]).size; print(f"{w}x{h}")' "$folder/cond/00000.png")"
    "$BIN/trainer" sample --ckpt "$folder/transformer" --base-model "$folder" \
        --text-embedding "$folder/text.safetensors" --cond "$folder/cond" --out "$out" --steps "$steps" \
        --seed "$seed" --guidance "$guidance" --dtype "$DTYPE" --device "$DEVICE" --frames "$frames" \
        --size "$size" "${extra[@]}"
}

stage_sampling() {
    local case=cognvs_5b
    ((TINY)) && case=cognvs
    PYTHONPATH="$PYPATH" "$PY" "$HERE/scripts/goldens_sampling.py" "$WORK/sampling" --device "$DEVICE" \
        --dtype "$DTYPE" --cases "$case"
    local folder="$WORK/sampling/$case"
    fields "diffusers=$(cat "$folder/case.json")"
    # Both embeddings differ: real classifier-free guidance, a batch of two.
    local config="$WORK/sampling.toml"
    training_config "$HERE/configs/finetune_5b_lora_1gpu.toml" full "$config"
    sed -i "s/^frames = .*/frames = $(ls "$folder/cond" | wc -l)/" "$config"
    if ((TINY)); then
        sed -i -e "s|^transformer = .*|transformer = \"$folder/transformer\"|" -e "s|^vae = .*|vae = \"$folder/vae\"|" \
            -e "s/^height = .*/height = 96/" "$config"
    fi
    fields "plan_gib=$(plan_gib --config "$config" --sampling --guided --device "$DEVICE")"
    sample_ours "$folder" "$WORK/sampling/ours" | tee "$WORK/sampling/ours.log"
    "$PY" - "$WORK/sampling/ours.log" "$WORK/$STAGE.json" <<'PY'
import json, re, sys
text = open(sys.argv[1]).read()
data = json.load(open(sys.argv[2]))
m = re.search(r"seconds: encode ([\d.]+), denoise ([\d.]+), decode ([\d.]+)", text)
ours = dict(seconds=dict(encode=float(m[1]), denoise=float(m[2]), decode=float(m[3])))
m = re.search(r"peak allocated ([\d.]+) GiB, peak reserved ([\d.]+) GiB", text)
if m:
    ours.update(peak_allocated_gib=float(m[1]), peak_reserved_gib=float(m[2]))
data["ours"] = ours
json.dump(data, open(sys.argv[2], "w"))
PY
    fields "frames_vs_diffusers=$(compare_frames "$WORK/sampling/ours" "$folder/expected")"
}

stage_nccl() {
    "$PY" -m torch.distributed.run --standalone --nproc-per-node 1 --no-python "$BIN/trainer" comm-check \
        --device "$DEVICE" --mib 256 --iterations 10 | tee "$WORK/comm.log"
    fields "comm_check=$(grep -m1 'MiB over' "$WORK/comm.log" | "$PY" -c 'import json,sys; print(json.dumps(sys.stdin.read().strip()))')"
    # The overlapped exchange on the same process group (bucket reductions during the backward on
    # the communication stream, ZeRO-2's gathers): step times with real and no-op collectives.
    "$PY" -m torch.distributed.run --standalone --nproc-per-node 1 --no-python "$BIN/trainer" comm-cost \
        --config "$HERE/configs/comm_cost_tiny.toml" --device "$DEVICE" | tee "$WORK/cost.log"
    fields "comm_cost=$(grep '^{' "$WORK/cost.log" | tail -n 1)"
}

stage_parity() {
    # All four cases on the GPU; on the CPU the tests cover them, the rehearsal runs the two quickest.
    local cases=cognvs,same_prompt,rotary_only,long
    ((TINY)) && cases=same_prompt,rotary_only
    PYTHONPATH="$PYPATH" "$PY" "$HERE/scripts/goldens_sampling.py" "$WORK/parity" --device "$DEVICE" --dtype "$DTYPE" \
        --cases "$cases"
    local folder result all=()
    for folder in "$WORK"/parity/*/; do
        folder="${folder%/}"
        sample_ours "$folder" "$folder/ours"
        result="$(compare_frames "$folder/ours" "$folder/expected")"
        all+=("$(basename "$folder")=$result")
    done
    fields "${all[@]}"
}

# trainer benchmark on one synthetic scene per layout with the sampling stage's models (random
# weights: the figures are times, not quality).
stage_benchmark() {
    local case=cognvs_5b
    ((TINY)) && case=cognvs
    local folder="$WORK/sampling/$case"
    [[ -d "$folder/transformer" ]] || { echo "no models: the sampling stage did not write $folder" >&2; exit 1; }
    fields "note=random 5B-shaped weights on synthetic scenes: the released checkpoint and the datasets cannot be reached from this machine"
    local layout extra=()
    ((TINY)) && extra+=(--eval-size "${WIDTH}x${HEIGHT}")
    for layout in dycheck kubric4d; do
        local cameras=2 held=1
        # Kubric-4D's split takes view 4 as the input: five views, scored on view 3.
        [[ $layout == kubric4d ]] && cameras=5 held=3
        "$BIN/datagen" synth --width "$WIDTH" --height "$HEIGHT" --frames "$FRAMES" --cameras "$cameras" \
            --format "$layout" --out "$WORK/bench-$layout/scene0"
        "$BIN/trainer" benchmark --dataset "$layout" --root "$WORK/bench-$layout" --init "$folder/transformer" \
            --base-model "$folder" --text-embedding "$folder/text.safetensors" --held-out-camera "$held" --steps 0 \
            --sample-steps 10 --frames "$FRAMES" --dtype "$DTYPE" --device "$DEVICE" --out "$WORK/bench-$layout/out" \
            "${extra[@]}"
        "$PY" - "$WORK/bench-$layout/out" "$layout" "$WORK/$STAGE.json" <<'PY'
import json, sys
out, layout, fields = sys.argv[1:4]
report = json.load(open(f"{out}/report.json"))
result = json.load(open(f"{out}/results/scene0.json"))
data = json.load(open(fields))
data[layout] = dict(eval_size=report["eval_size"], frames=result["frames"], psnr=report["mean"]["psnr"],
                    sample_s=result["seconds"]["sample"], scene_s=result["seconds"]["total"])
json.dump(data, open(fields, "w"))
PY
    done
}

summary() {
    "$PY" - "$OUT/results.jsonl" <<'PY' | tee "$OUT/summary.txt"
import json, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
print(f"{'stage':<16} {'status':<8} {'seconds':>8}  figures")
for r in rows:
    figures = {k: v for k, v in r.items() if k not in ("stage", "status", "seconds")}
    text = ", ".join(f"{k}={round(v, 3) if isinstance(v, float) else v}" for k, v in figures.items())
    print(f"{r['stage']:<16} {r['status']:<8} {r['seconds']:>8}  {text[:400]}")
PY
}

run() {
    local tiny=0 archive="" site="" out="" deadline=540
    while [[ $# -gt 0 ]]; do
        case "$1" in
            --tiny) tiny=1 ;;
            --bundle) archive="$2"; shift ;;
            --site-packages) site="$2"; shift ;;
            --out) out="$2"; shift ;;
            --deadline) deadline="$2"; shift ;;
            *) echo "unknown option $1" >&2; exit 2 ;;
        esac
        shift
    done
    export PY="${PYTHON:-python3}" TINY="$tiny" DEADLINE="$deadline"
    export DEADLINE_AT=$(($(date +%s) + deadline)) SELF
    SELF="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)/$(basename "${BASH_SOURCE[0]}")"
    export OUT="${out:-$(mktemp -d)}"
    mkdir -p "$OUT/logs"
    : >"$OUT/results.jsonl"
    export WORK; WORK="$(mktemp -d)"
    # The bundle: the archive given, else this script's own folder when it runs from an unpacked
    # bundle, else the repo's .gpu-check/bundle.tar.xz.
    local here; here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
    [[ -z "$archive" && ! -x "$here/bin/trainer" ]] && archive="$gc/bundle.tar.xz"
    if [[ -n "$archive" ]]; then
        "$PY" -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2])" "$archive" "$WORK"
        here="$WORK/bundle"
    fi
    export HERE="$here"
    # The torch libraries: the given site-packages', else the Python's own.
    local torch_lib
    if [[ -n "$site" ]]; then torch_lib="$(cd "$site/torch/lib" && pwd)"
    else torch_lib="$("$PY" -c 'import torch, os; print(os.path.join(os.path.dirname(torch.__file__), "lib"))')"; fi
    # Only the bundle's binaries see its libraries (the stubs must not shadow anything of Python's).
    export BIN="$WORK/bin" LIBPATH="$torch_lib:$here/lib"; mkdir -p "$BIN"
    for name in trainer datagen; do
        printf '#!/bin/sh\nLD_LIBRARY_PATH="%s" exec "%s" "$@"\n' "$LIBPATH" "$here/bin/$name" >"$BIN/$name"
        chmod +x "$BIN/$name"
    done
    # The pure-Python diffusers wheel, unpacked (no pip, no registry), else the Python's own.
    export PYPATH="${PYTHONPATH:-}"
    local wheel
    wheel="$(ls "$here"/diffusers-*.whl 2>/dev/null | head -1 || true)"
    if [[ -n "$wheel" ]]; then
        "$PY" -c "import zipfile, sys; zipfile.ZipFile(sys.argv[1]).extractall(sys.argv[2])" "$wheel" "$WORK/py"
        PYPATH="$WORK/py${PYPATH:+:$PYPATH}"
    fi
    if ((tiny)); then
        export DEVICE=cpu DTYPE=fp32 FRAMES=9 HEIGHT=64 WIDTH=80 TRAIN_STEPS=3
    else
        export DEVICE=cuda DTYPE=bf16 FRAMES=49 HEIGHT=480 WIDTH=720 TRAIN_STEPS=6
    fi
    FAILED=0
    stage env 30
    stage data 60
    stage lora_ours 120
    stage lora_diffusers 90
    stage wan_lora 240
    stage full_ours 150
    stage full_diffusers 120
    stage sampling 300
    stage nccl 60
    stage parity 90
    stage benchmark 240
    summary
    rm -rf "$WORK"
    return "$FAILED"
}

case "$cmd" in
    build) compile; bundle ;;
    compile | bundle | rehearse) "$cmd" ;;
    run) run "$@" ;;
    _stage) STAGE="$1"; export STAGE; "stage_$1" ;;
    *) echo "usage: scripts/gpu_check.sh build | compile | bundle | rehearse | run [--tiny] [--out DIR] [--deadline S] [--bundle FILE] [--site-packages DIR]" >&2
       exit 2 ;;
esac
