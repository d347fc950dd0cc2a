#!/usr/bin/env python3
"""Reference PSNR / SSIM values from scikit-image, for `trainer eval`'s parity test.

Usage: goldens_metrics.py OUT_DIR

Writes OUT_DIR/target/%05d.png, OUT_DIR/pred/%05d.png (the target with smooth distortions and
noise), OUT_DIR/mask/%05d.png (255 co-visible) and OUT_DIR/expected.json with, per frame,
skimage's peak_signal_noise_ratio and structural_similarity (data_range=1, channel_axis=-1) and
DyCheck's masked variants (KAIR-BAIR/dycheck `dycheck/core/metrics/image.py`, compute_psnr and
compute_ssim with `masked_mean` of `dycheck/nn/functional/common.py`). dycheck is not on PyPI
and needs JAX, so those two functions are written below from its code with numpy and
scipy.signal.convolve2d (mode "valid", as jax.scipy.signal.convolve2d); goldens_protocol.py uses
them too. Requires numpy, scipy, pillow and scikit-image (the project venv, scripts/setup.sh).
"""

import json
import sys
from pathlib import Path

import numpy as np
import scipy.signal
from PIL import Image
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

SEED = 20261124
FRAMES, H, W = 3, 40, 56


def masked_mean(x, mask):
    mask = np.broadcast_to(mask, x.shape)
    return (x * mask).sum() / np.clip(mask.sum(), 1e-6, None)


def dycheck_psnr(img0, img1, mask):
    with np.errstate(divide="ignore"):
        return float(-10.0 / np.log(10.0) * np.log(masked_mean((img0 - img1) ** 2, mask)))


def dycheck_ssim(img0, img1, mask, max_val=1.0, filter_size=11, filter_sigma=1.5, k1=0.01, k2=0.03):
    mask = mask[..., 0]
    hw = filter_size // 2
    shift = (2 * hw - filter_size + 1) / 2
    f_i = ((np.arange(filter_size) - hw + shift) / filter_sigma) ** 2
    filt = np.exp(-0.5 * f_i)
    filt /= np.sum(filt)

    def convolve2d(z, m, f):
        z_ = scipy.signal.convolve2d(z * m, f, mode="valid")
        m_ = scipy.signal.convolve2d(m, np.ones_like(f), mode="valid")
        safe = np.where(m_ != 0, m_, 1)
        return np.where(m_ != 0, z_ * np.ones_like(f).sum() / safe, 0), (m_ != 0).astype(z.dtype)

    def filt_fn(z, m):
        # filt_fn2 (the row filter) first, then filt_fn1 (the column filter), per channel.
        rows = [convolve2d(z[..., c], m, filt[None, :]) for c in range(z.shape[-1])]
        m2 = rows[0][1]
        cols = [convolve2d(r[0], m2, filt[:, None]) for r in rows]
        return np.stack([c[0] for c in cols], -1)

    mu0, mu1 = filt_fn(img0, mask), filt_fn(img1, mask)
    mu00, mu11, mu01 = mu0 * mu0, mu1 * mu1, mu0 * mu1
    sigma00 = np.maximum(0.0, filt_fn(img0**2, mask) - mu00)
    sigma11 = np.maximum(0.0, filt_fn(img1**2, mask) - mu11)
    sigma01 = filt_fn(img0 * img1, mask) - mu01
    sigma01 = np.sign(sigma01) * np.minimum(np.sqrt(sigma00 * sigma11), np.abs(sigma01))
    c1, c2 = (k1 * max_val) ** 2, (k2 * max_val) ** 2
    numer = (2 * mu01 + c1) * (2 * sigma01 + c2)
    denom = (mu00 + mu11 + c1) * (sigma00 + sigma11 + c2)
    return float((numer / denom).mean())


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
        m = (mask / 255.0)[..., None]
        expected.append(dict(
            psnr=peak_signal_noise_ratio(t, p, data_range=1),
            ssim=structural_similarity(t, p, data_range=1, channel_axis=-1),
            masked_psnr=dycheck_psnr(t, p, m),
            masked_ssim=dycheck_ssim(t, p, m),
        ))
    (out / "expected.json").write_text(json.dumps(expected, indent=1))


if __name__ == "__main__":
    main()
