#!/usr/bin/env bash
# Feature-extraction speed of `trainer eval` against the Python packages, same
# thread count, side by side: LPIPS (AlexNet, lpips package) on frame pairs and clean-fid "clean"
# Inception features (PIL resize to 299 + FID Inception), on FRAMES frames of 384×576 (the GCD
# protocol size). Weights are the random ones of scripts/goldens_eval.py (speed does not depend
# on the values). Ours is timed through the CLI: a PSNR/SSIM-only run is subtracted, so the
# figures are the network part only (frame decoding included on both sides).
# Usage: scripts/bench_eval.sh [FRAMES (default 32)] [THREADS (default 2)]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

frames="${1:-32}"
threads="${2:-2}"
export OMP_NUM_THREADS="$threads" MKL_NUM_THREADS="$threads" RAYON_NUM_THREADS="$threads"
py=.venv/bin/python
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

[[ -n "${BENCH_PREBUILT:-}" ]] || cargo build -p trainer --bin trainer --quiet
bin=target/debug/trainer
"$py" scripts/goldens_eval.py "$work/w" --weights-only
"$py" - "$work" "$frames" <<'PY'
import sys, numpy as np
from pathlib import Path
from PIL import Image
work, n = Path(sys.argv[1]), int(sys.argv[2])
rng = np.random.default_rng(0)
for sub in ("pred", "target"):
    (work / sub).mkdir()
    for i in range(n):
        Image.fromarray(rng.integers(0, 256, (384, 576, 3), dtype=np.uint8)).save(work / sub / f"{i:05d}.png")
PY

seconds() { local t0 t1; t0=$(date +%s.%N); "$@" >/dev/null 2>&1; t1=$(date +%s.%N); echo "$t1 - $t0" | bc -l; }
base=$(seconds "$bin" eval --pred "$work/pred" --target "$work/target" --metrics lpips --lpips-weights "$work/w/lpips_alex.safetensors" --protocol gcd)
plain=$(seconds "$bin" eval --pred "$work/pred" --target "$work/target" --protocol gcd)
incep=$(seconds "$bin" eval --pred "$work/pred" --target "$work/target" --metrics fid --inception-weights "$work/w/inception.safetensors" --protocol gcd)
ours_lpips=$(echo "$frames / ($base - $plain)" | bc -l)
# FID features are extracted for both sets: 2 × frames.
ours_incep=$(echo "2 * $frames / ($incep - $plain)" | bc -l)

read -r py_lpips py_incep < <("$py" - "$work" "$threads" <<'PY'
import sys, time, torch, lpips, numpy as np
from pathlib import Path
from PIL import Image
from cleanfid import fid as cfid
sys.path.insert(0, "scripts")
import goldens_eval as g
work, threads = Path(sys.argv[1]), int(sys.argv[2])
torch.set_num_threads(threads)
files = sorted((work / "pred").glob("*.png"))
load = lambda p: torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), dtype=np.float32) / 127.5 - 1).permute(2, 0, 1)[None]
model = lpips.LPIPS(pnet_rand=True, net="alex", verbose=False).eval()
t0 = time.time()
with torch.no_grad():
    for f in files:
        model(load(f), load(work / "target" / f.name))
lp = len(files) / (time.time() - t0)
net = g.CleanFeatures(g.fid_inception()).eval()
t0 = time.time()
for sub in ("pred", "target"):
    cfid.get_folder_features(str(work / sub), net, num_workers=0, batch_size=4, device=torch.device("cpu"), mode="clean", verbose=False)
inc = 2 * len(files) / (time.time() - t0)
print(lp, inc)
PY
)
printf '%-28s %12s %12s %8s\n' "threads=$threads, $frames frames" "ours f/s" "python f/s" "ratio"
printf '%-28s %12.2f %12.2f %8.2f\n' "LPIPS alex 384x576" "$ours_lpips" "$py_lpips" "$(echo "$ours_lpips / $py_lpips" | bc -l)"
printf '%-28s %12.2f %12.2f %8.2f\n' "Inception clean 299" "$ours_incep" "$py_incep" "$(echo "$ours_incep / $py_incep" | bc -l)"
