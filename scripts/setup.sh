#!/usr/bin/env bash
# One-step, idempotent set-up of a fresh Debian machine for this workspace:
#   1. Debian packages: FFmpeg development libraries and CLI, clang/libclang, pkg-config,
#      libzstd-dev (Parquet's zstd links it: see `.cargo/config.toml`), time and bc (the bench
#      scripts measure peak RSS with /usr/bin/time and do their arithmetic with bc),
#      chromium (headless, renders `datagen inspect --report` pages in a test); gloo's headers (the
#      c10d shim of `trainer` compiles against them); slurm-wlm and munge (a one-node Slurm that
#      `scripts/test_slurm.sh` starts and stops);
#   2. a project-local Python venv (.venv, git-ignored) with torch==2.13.0 (the libtorch that
#      tch 0.26 links against) and the Python packages the tests use for interoperability checks;
#   3. the `.venv/libtorch` link that `.cargo/config.toml` points LIBTORCH at.
# Safe to re-run: every step checks before it acts, and a set-up machine is left unchanged.
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

step() { printf '\n==> %s\n' "$*"; }
fail() { printf '\nsetup.sh: FAILED at step: %s\n' "$*" >&2; exit 1; }

TORCH_VERSION="2.13.0"
# FFmpeg: the command-line tool, and the development files of the four libraries `ffmpeg-next`
# links with the features the workspace enables (avcodec, avformat, avutil, swscale).
APT_PACKAGES=(
  pkg-config clang libclang-dev ffmpeg
  libavcodec-dev libavformat-dev libavutil-dev libswscale-dev
  libzstd-dev
  time bc
  chromium
  libgloo-dev slurm-wlm munge
)
# torch: libtorch for tch; diffusers + safetensors: numerical reference for the model port;
# numpy, pyarrow, duckdb, datasets, pillow: interoperability checks of the shards; pycocotools:
# reference RLE encoder for the SA-V mask decoder; scikit-image: reference PSNR/SSIM for `trainer eval`;
# peft: diffusers' LoRA loader, the reference our LoRA files are checked against; torchvision,
# lpips, clean-fid: reference LPIPS, Inception features, FID and KID for `trainer eval`;
# tensorboard: its own event reader checks our training event files; nvidia-cuda-nvcc and
# nvidia-cuda-cccl: headers only (crt/, cuda/std), which the NCCL half of the c10d shim needs
# beside the CUDA runtime and NCCL headers the torch wheel already pulls in (same CUDA 13.0);
# transformers + sentencepiece: scripts/encode_prompt.py (T5 text embeddings) and its reference;
# opencv-python-headless: reference resizes of the public CogNVS demo (cv2.INTER_AREA/LINEAR);
# rerun-sdk: scripts/rerun_view.py writes `datagen view`'s .rrd recordings, and the test opens them.
PY_PACKAGES=(
  "torch==${TORCH_VERSION}" "diffusers>=0.35" "safetensors>=0.4"
  "numpy>=1.26" "pyarrow>=17" "duckdb>=1.1" "datasets>=3" "pillow>=10" "pycocotools>=2"
  "scikit-image>=0.22" "peft>=0.15"
  "torchvision==0.28.0" "lpips==0.1.4" "clean-fid==0.1.35" "tensorboard>=2.16"
  "nvidia-cuda-nvcc==13.0.88" "nvidia-cuda-cccl==13.0.85"
  "transformers>=4.44" "sentencepiece>=0.2" "opencv-python-headless>=4.8" "rerun-sdk>=0.41"
)

step "Debian packages: ${APT_PACKAGES[*]}"
missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "installing: ${missing[*]}"
  sudo_cmd=()
  [[ $(id -u) -ne 0 ]] && sudo_cmd=(sudo)
  "${sudo_cmd[@]}" apt-get update -qq || fail "apt-get update"
  DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq "${missing[@]}" \
    || fail "apt-get install ${missing[*]}"
else
  echo "all present"
fi

step "Rust toolchain"
command -v cargo >/dev/null || fail "cargo not found: install Rust with rustup first"
cargo --version

step "Python venv at .venv with ${PY_PACKAGES[*]}"
if [[ ! -x .venv/bin/python ]]; then
  python3 -m venv .venv || fail "python3 -m venv .venv"
fi
if .venv/bin/python - "${PY_PACKAGES[@]}" <<'PY' 2>/dev/null
import sys
from importlib.metadata import version, PackageNotFoundError
try:
    from packaging.requirements import Requirement
except ImportError:
    from pip._vendor.packaging.requirements import Requirement
for spec in sys.argv[1:]:
    req = Requirement(spec)
    try:
        if not req.specifier.contains(version(req.name), prereleases=True):
            sys.exit(1)
    except PackageNotFoundError:
        sys.exit(1)
PY
then
  echo "all present"
else
  .venv/bin/python -m pip install -q --upgrade pip || fail "pip upgrade"
  .venv/bin/python -m pip install -q "${PY_PACKAGES[@]}" || fail "pip install ${PY_PACKAGES[*]}"
fi

step "libtorch link .venv/libtorch"
torch_dir="$(.venv/bin/python -c 'import os, torch; print(os.path.dirname(torch.__file__))')" \
  || fail "import torch from .venv"
[[ -f "$torch_dir/lib/libtorch_cpu.so" ]] || fail "libtorch_cpu.so missing under $torch_dir/lib"
if [[ "$(readlink .venv/libtorch 2>/dev/null)" != "$torch_dir" ]]; then
  ln -sfn "$torch_dir" .venv/libtorch
  echo "linked .venv/libtorch -> $torch_dir"
else
  echo "present: .venv/libtorch -> $torch_dir"
fi

step "done: plain cargo build/test/run now work in this checkout"
