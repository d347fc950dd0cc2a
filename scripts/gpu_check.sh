#!/usr/bin/env bash
# GPU check of issue 14 item 5 (and issue 13's NCCL at world size 1), in two parts.
#   scripts/gpu_check.sh build   (here, with Rust) = compile + bundle:
#     compile: torch==2.11.0 from PyPI into .gpu-check/site-packages (git-ignored), with the headers
#       of the nvidia wheels it pins under site-packages/nvidia (build.rs then compiles the shim's NCCL
#       half), torch-sys's wrapper patched for its headers (scripts/gpu_check_patch_torch_sys.py), and
#       trainer + datagen built against it in a copy of the workspace (CARGO_TARGET_DIR=target/gpu-check,
#       release).
#     bundle: .gpu-check/bundle.tar.xz (stripped binaries, FFmpeg libraries or stubs of them from
#       scripts/gpu_check_stub_libs.py, the diffusers wheel, these scripts) to carry (<= 60 MiB).
#   scripts/gpu_check.sh run [--tiny] [--steps N] [--bundle FILE] [--site-packages DIR]
#     (there, no Rust, no registry; PYTHON= the Python 3.12 with torch 2.11.0+cu130): unpacks the
#       bundle, runs `torchrun --nproc-per-node 1 --no-python trainer comm-check` (NCCL) and
#       `trainer comm-cost` (the overlapped exchange at world size 1: streams and events), then a few
#       bf16 training steps of the 5B transformer at 49x480x720 (random weights, random text
#       embedding, gradient checkpointing), LoRA and full, with this trainer and with diffusers, and
#       prints step time and peak device memory next to `trainer plan`'s prediction. --site-packages:
#       the torch 2.11 libraries to run against [default: $PYTHON's torch]. --tiny: the tiny presets
#       at 9x64x80 on the CPU (checks the path here, e.g. --site-packages .gpu-check/site-packages).
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

# Builds .gpu-check/site-packages/nvidia/ the way torch 2.11's wheel dependencies lay it out: the
# headers of the pinned versions above (build.rs finds nccl.h there and compiles the NCCL half), and
# the libraries as links into the venv's cu13 wheels (same sonames; here they are only loaded, for
# linking and for CPU runs, never called; the GPU machine uses its own).
nvidia_layout() {
    local py="$1" nv="$gc/site-packages/nvidia" venv_nv
    venv_nv="$("$py" -c 'import nvidia, os; print(os.path.dirname(nvidia.__path__[0]))')/nvidia"
    [[ -L "$nv" ]] && rm "$nv"  # an older layout linked the venv's nvidia/ whole
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

# Bundle size limit: what travels with one call to the GPU machine, less room for the working tree.
BUNDLE_LIMIT_BYTES=$((60 * 1024 * 1024))

bundle() {
    local bundle="$gc/bundle" archive="$gc/bundle.tar.xz"
    rm -rf "$bundle" && mkdir -p "$bundle/bin" "$bundle/lib" "$bundle/scripts" "$bundle/configs"
    for bin in trainer datagen; do
        strip -o "$bundle/bin/$bin" "$root/target/gpu-check/release/$bin"
    done
    # FFmpeg's full closure is ~230 MB: carry the libraries encoding and decoding an mp4 needs and
    # stubs of the rest (see the script's docstring).
    python3 "$root/scripts/gpu_check_stub_libs.py" "$bundle/lib" "$gc/site-packages/torch/lib" \
        "$bundle/bin/trainer" "$bundle/bin/datagen" | tail -1
    cp "$root"/scripts/gpu_check.sh "$root"/scripts/gpu_check_diffusers.py "$bundle/scripts/"
    cp "$root"/configs/finetune_5b_lora_1gpu.toml "$root"/configs/pretrain_tiny.toml \
        "$root"/configs/comm_cost_tiny.toml "$bundle/configs/"
    cp "$gc"/wheels/diffusers-*.whl "$bundle/"
    tar -C "$gc" -cf - bundle | xz -T0 -6 >"$archive"
    local size; size="$(stat -c %s "$archive")"
    echo "bundle: $(du -sh "$bundle" | cut -f1) unpacked, $archive $((size / 1048576)) MiB"
    (( size <= BUNDLE_LIMIT_BYTES )) || { echo "bundle over $((BUNDLE_LIMIT_BYTES / 1048576)) MiB" >&2; exit 1; }
}

run() {
    local tiny=0 steps=3 archive="" site=""
    while [[ $# -gt 0 ]]; do
        case "$1" in
            --tiny) tiny=1 ;;
            --steps) steps="$2"; shift ;;
            --bundle) archive="$2"; shift ;;
            --site-packages) site="$2"; shift ;;
            *) echo "unknown option $1" >&2; exit 2 ;;
        esac
        shift
    done
    local py="${PYTHON:-python3}"
    local work; work="$(mktemp -d)"; trap 'rm -rf "$work"' RETURN
    # The bundle: the archive given, else this script's own folder when it runs from an unpacked
    # bundle, else the repo's .gpu-check/bundle.tar.xz.
    local here; here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
    [[ -z "$archive" && ! -x "$here/bin/trainer" ]] && archive="$gc/bundle.tar.xz"
    if [[ -n "$archive" ]]; then
        python3 -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2])" "$archive" "$work"
        here="$work/bundle"
    fi
    # The torch 2.11 libraries: the given site-packages, else the Python's own torch.
    local torch_lib
    if [[ -n "$site" ]]; then torch_lib="$(cd "$site/torch/lib" && pwd)"
    else torch_lib="$("$py" -c 'import torch, os; print(os.path.join(os.path.dirname(torch.__file__), "lib"))')"; fi
    # Only the bundle's binaries see its libraries (the stubs must not shadow anything of Python's).
    local bin="$work/bin"; mkdir -p "$bin"
    for name in trainer datagen; do
        printf '#!/bin/sh\nLD_LIBRARY_PATH="%s:%s" exec "%s" "$@"\n' "$torch_lib" "$here/lib" "$here/bin/$name" >"$bin/$name"
        chmod +x "$bin/$name"
    done
    echo "binaries: $here/bin; libraries as the loader resolves them:"
    LD_LIBRARY_PATH="$torch_lib:$here/lib" ldd "$here/bin/trainer" \
        | grep -E 'libtorch_(cpu|cuda)|libc10\.|libnccl|libcudart|libavcodec|libx265|not found' | sed 's/ (0x.*//'
    # The pure-python diffusers wheel, unpacked (no pip, no registry).
    local wheel; wheel="$(ls "$here"/diffusers-*.whl | head -1)"
    python3 -c "import zipfile, sys; zipfile.ZipFile(sys.argv[1]).extractall(sys.argv[2])" "$wheel" "$work/py"
    local device=cuda frames=49 height=480 width=720 transformer=cognvs-5b vae=cogvideox-5b
    if (( tiny )); then device=cpu frames=9 height=64 width=80 transformer=tiny vae=tiny; fi
    "$bin/datagen" synth --width "$width" --height "$height" --frames "$frames" --out "$work/seq" >/dev/null
    printf '[clip]\nlength = %s\nstride = %s\n' "$frames" "$frames" >"$work/clips.toml"
    "$bin/datagen" pairs "$work/seq" --out "$work/pairs" --trajectories 1 --config "$work/clips.toml" >/dev/null
    local preset="$here/configs/finetune_5b_lora_1gpu.toml"
    # The distributed path at world size 1 under a launcher (comm-check creates the process group
    # even then): NCCL on the GPU, Gloo on the CPU. --standalone picks a free port for the store.
    echo "comm-check, torchrun --nproc-per-node 1, --device $device:"
    "$py" -m torch.distributed.run --standalone --nproc-per-node 1 --no-python "$bin/trainer" comm-check \
        --device "$device" --mib 256 || echo "comm-check failed" >&2
    # The overlapped exchange (bucket reductions during the backward, the ZeRO-2 gathers) on the
    # same process group: step times with real and no-op collectives, one JSON line.
    echo "comm-cost, torchrun --nproc-per-node 1, --device $device:"
    "$py" -m torch.distributed.run --standalone --nproc-per-node 1 --no-python "$bin/trainer" comm-cost \
        --config "$here/configs/comm_cost_tiny.toml" --device "$device" || echo "comm-cost failed" >&2
    printf '%-10s %-6s %12s %14s %14s\n' impl mode "step (s)" "peak (GB)" "plan"
    for mode in lora full; do
        sed -e "s|^transformer = .*|transformer = \"$transformer\"|" -e "s|^vae = .*|vae = \"$vae\"|" \
            -e "s|^frames = .*|frames = $frames|" -e "s|^height = .*|height = $height|" -e "s|^width = .*|width = $width|" \
            -e "s|^steps = .*|steps = $steps|" -e "s|^checkpoint_every = .*|checkpoint_every = 1000000|" "$preset" >"$work/$mode.toml"
        # The tiny model's 32-wide projections take rank 4 (alpha 2: the preset's alpha/rank of 1/2),
        # as gpu_check_diffusers.py --tiny does.
        (( tiny )) && sed -i -e 's|^precision = .*|precision = "fp32"|' -e 's|^rank = .*|rank = 4|' \
            -e 's|^alpha = .*|alpha = 2|' "$work/$mode.toml"
        [[ "$mode" == full ]] && sed -i '/^\[lora\]/,$d' "$work/$mode.toml"
        local plan; plan="$("$bin/trainer" plan --config "$work/$mode.toml" --device "$device" --world-size 1 \
            | sed -n 's/.*total (predicted peak) *//p')"
        local poll=""
        if [[ "$device" == cuda ]]; then
            nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 200 >"$work/$mode.smi" & poll=$!
        fi
        local timer=(/usr/bin/time -f '%M' -o "$work/$mode.rss"); [[ -x /usr/bin/time ]] || timer=()
        "${timer[@]}" "$bin/trainer" pretrain --config "$work/$mode.toml" \
            --shards "$work/pairs" --out "$work/run-$mode" --device "$device" >"$work/$mode.log" 2>&1 \
            || { grep -A1 '^Error' "$work/$mode.log" || tail -n 20 "$work/$mode.log"; echo "trainer $mode failed" >&2; }
        [[ -n "$poll" ]] && kill "$poll"
        local peak
        if [[ "$device" == cuda ]]; then peak="$(sort -n "$work/$mode.smi" | tail -1 | awk '{printf "%.1f", $1 * 1048576 / 1e9}')"
        else peak="$(tail -1 "$work/$mode.rss" 2>/dev/null | awk '{printf "%.2f", $1 * 1024 / 1e9}')"; fi
        local step; step="$(python3 -c "
import json, statistics, sys
s = [json.loads(l)['seconds'] for l in open(sys.argv[1])]
print(f'{statistics.median(s[1:] or s):.2f}')" "$work/run-$mode/metrics.jsonl" 2>/dev/null || echo n/a)"
        printf '%-10s %-6s %12s %14s %14s\n' trainer "$mode" "$step" "$peak" "$plan"
        PYTHONPATH="$work/py" "$py" "$here/scripts/gpu_check_diffusers.py" --mode "$mode" --steps "$steps" \
            --device "$device" $( (( tiny )) && echo --tiny ) | "$py" -c "
import json, sys
r = json.loads(sys.stdin.read().strip().splitlines()[-1])
peak = r['peak_reserved_gb']
print(f\"{'diffusers':<10} {r['mode']:<6} {r['median_step_s']:>12.2f} {('n/a' if peak is None else f'{peak:.2f}'):>14} {'':>14}\")"
    done
    echo "(peak: trainer nvidia-smi memory.used incl. the CUDA context, diffusers torch's max reserved; on the CPU both peak RSS)"
}

case "$cmd" in
    build) compile; bundle ;;
    compile | bundle) "$cmd" ;;
    run) run "$@" ;;
    *) echo "usage: scripts/gpu_check.sh build | compile | bundle | run [--tiny] [--steps N] [--bundle FILE] [--site-packages DIR]" >&2
       exit 2 ;;
esac
