#!/usr/bin/env python3
"""Reference PSNR / SSIM values from scikit-image, for `trainer eval`'s parity test.

Usage: goldens_metrics.py OUT_DIR

Writes OUT_DIR/target/%05d.png, OUT_DIR/pred/%05d.png (the target with smooth distortions and
noise), OUT_DIR/mask/%05d.png (255 co-visible) and OUT_DIR/expected.json with, per frame,
skimage's peak_signal_noise_ratio and structural_similarity (data_range=1, channel_axis=-1) and
their masked variants: PSNR from the MSE over co-visible pixels, SSIM as the mean of the full SSIM
map over co-visible pixels at least 3 pixels from the border. Requires numpy, pillow and
scikit-image (the project venv, scripts/setup.sh).
"""

import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

SEED = 20261124
FRAMES, H, W = 3, 40, 56
PAD = 3  # (win_size 7 - 1) / 2: skimage crops this border from the SSIM map


def main() -> None:
    out = Path(sys.argv[1])
    for sub in ("target", "pred", "mask"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(SEED)
    yy, xx = np.mgrid[0:H, 0:W]
    expected = []
    for f in range(FRAMES):
        base = np.stack([np.sin(xx / (4 + c) + f) * np.cos(yy / (5 + c)) for c in range(3)], axis=-1)
        target = np.clip(0.5 + 0.4 * base + 0.05 * rng.standard_normal((H, W, 3)), 0, 1)
        target = (target * 255).round().astype(np.uint8)
        shift = np.roll(target.astype(float), 1, axis=1)
        pred = np.clip(0.8 * target + 0.2 * shift + rng.normal(0, 6 + 4 * f, (H, W, 3)), 0, 255).round().astype(np.uint8)
        mask = ((xx + 2 * yy + 7 * f) % 23 < 14).astype(np.uint8) * 255
        Image.fromarray(target).save(out / "target" / f"{f:05d}.png")
        Image.fromarray(pred).save(out / "pred" / f"{f:05d}.png")
        Image.fromarray(mask).save(out / "mask" / f"{f:05d}.png")
        t, p = target / 255.0, pred / 255.0
        keep = mask > 0
        ssim, smap = structural_similarity(t, p, data_range=1, channel_axis=-1, full=True)
        inner = np.zeros_like(keep)
        inner[PAD:H - PAD, PAD:W - PAD] = True
        masked_mse = ((t - p) ** 2)[keep].mean()
        expected.append(dict(
            psnr=peak_signal_noise_ratio(t, p, data_range=1),
            ssim=ssim,
            masked_psnr=10 * np.log10(1 / masked_mse),
            masked_ssim=smap.mean(axis=-1)[keep & inner].mean(),
        ))
    (out / "expected.json").write_text(json.dumps(expected, indent=1))


if __name__ == "__main__":
    main()
