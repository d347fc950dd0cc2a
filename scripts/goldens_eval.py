#!/usr/bin/env python3
"""Reference LPIPS, Inception features, FID and KID from the `lpips` and `clean-fid` packages, for
`trainer eval`'s parity tests. Nothing is downloaded: the backbones have random weights, the
LPIPS linear heads are the v0.1 files the `lpips` wheel ships.

Usage: goldens_eval.py OUT_DIR [--weights-only]

With --weights-only it writes only lpips_alex.safetensors and inception.safetensors (what
scripts/bench_eval.sh needs).

Writes
- OUT_DIR/{pred,target}/%05d.png: two small frame sets (the target a smooth pattern, the
  prediction a distorted copy), OUT_DIR/mask/%05d.png (255 = co-visible);
- OUT_DIR/lpips_{alex,vgg}.safetensors: `lpips.LPIPS(pnet_rand=True, net=...)`'s weights under
  torchvision's backbone names (`features.{i}.weight`) plus the heads (`lin{k}.model.1.weight`),
  the layout scripts/convert_eval_weights.py writes from users' files;
- OUT_DIR/inception.safetensors: clean-fid's FID Inception (`cleanfid.inception_pytorch`, the
  pytorch-fid port of the TF 2015-12-05 graph) built with random weights and random batch-norm
  statistics, torchvision names;
- OUT_DIR/features.safetensors: `pred` and `target` [N, 2048] from clean-fid's own folder pipeline
  (`get_folder_features`, mode "clean": PIL bicubic float resize to 299, (x - 128) / 128, pool);
- OUT_DIR/expected.json: per-frame LPIPS (alex, vgg), masked LPIPS (the mean of
  `LPIPS(spatial=True)`'s map over co-visible pixels, DyCheck's mLPIPS), FID
  (`cleanfid.fid.frechet_distance`'s value on the two sets' means and covariances, its matrix
  square root's trace taken exactly: see `exact_fid`, which is checked against frechet_distance
  itself here) and KID (`cleanfid.fid.kernel_distance`; with as few frames as here its subsets
  are the whole sets).
"""

import json
import sys
from pathlib import Path

import lpips
import numpy as np
import torch
import torchvision
from cleanfid import fid as cfid
from cleanfid import inception_pytorch as cinc
from PIL import Image
from safetensors.torch import save_file

SEED = 20261125
FRAMES, H, W = 6, 48, 64
# Batch-norm statistics drawn so that every BN layer is exercised, not left at (0, 1).
BN_MEAN_STD, BN_VAR_RANGE = 0.1, (0.5, 1.5)
# Feature columns on which `exact_fid` is checked against clean-fid's frechet_distance (its scipy
# sqrtm is instant at this width; the sets stay rank-deficient, as the full 2048 are), and the
# largest relative difference allowed (what sqrtm's float64 rounding leaves on such a product).
FID_CHECK_COLUMNS, FID_CHECK_TOL = 64, 1e-6


def frames(out: Path) -> None:
    rng = np.random.default_rng(SEED)
    yy, xx = np.mgrid[0:H, 0:W]
    for sub in ("target", "pred", "mask"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for f in range(FRAMES):
        base = np.stack([np.sin(xx / (3 + c) + f) * np.cos(yy / (4 + c) - f / 2) for c in range(3)], axis=-1)
        target = np.clip(0.5 + 0.4 * base + 0.05 * rng.standard_normal((H, W, 3)), 0, 1)
        target = (target * 255).round().astype(np.uint8)
        shift = np.roll(target.astype(float), 2, axis=1)
        pred = 0.7 * target + 0.3 * shift + rng.normal(0, 8 + 3 * f, (H, W, 3))
        pred = np.clip(pred, 0, 255).round().astype(np.uint8)
        mask = ((xx + 2 * yy + 5 * f) % 19 < 12).astype(np.uint8) * 255
        Image.fromarray(target).save(out / "target" / f"{f:05d}.png")
        Image.fromarray(pred).save(out / "pred" / f"{f:05d}.png")
        Image.fromarray(mask).save(out / "mask" / f"{f:05d}.png")


def load_rgb(path: Path) -> torch.Tensor:
    """[1, 3, H, W] in [-1, 1], as lpips.im2tensor makes it."""
    x = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0
    return torch.from_numpy(x * 2 - 1).permute(2, 0, 1)[None].float()


def lpips_model(out: Path, net: str) -> torch.nn.Module:
    """The random-backbone LPIPS of `net`, its weights saved as OUT/lpips_{net}.safetensors."""
    torch.manual_seed(SEED + len(net))
    model = lpips.LPIPS(pnet_rand=True, net=net, version="0.1", verbose=False).eval()
    tensors = {}
    for name, value in model.state_dict().items():
        if name.startswith("net.slice"):
            # net.slice{k}.{i}.weight -> features.{i}.weight (torchvision's AlexNet/VGG16 names)
            tensors["features." + name.split(".", 2)[2]] = value
        elif name.startswith("lin") and not name.startswith("lins."):
            tensors[name] = value.clone()
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(out / f"lpips_{net}.safetensors"))
    return model


def lpips_goldens(out: Path, net: str) -> tuple[list, list]:
    model = lpips_model(out, net)
    spatial = lpips.LPIPS(pnet_rand=True, net=net, version="0.1", spatial=True, verbose=False).eval()
    spatial.load_state_dict(model.state_dict())
    plain, masked = [], []
    with torch.no_grad():
        for f in range(FRAMES):
            p, t = load_rgb(out / "pred" / f"{f:05d}.png"), load_rgb(out / "target" / f"{f:05d}.png")
            plain.append(float(model(p, t).item()))
            keep = torch.from_numpy(np.asarray(Image.open(out / "mask" / f"{f:05d}.png")) > 0)
            masked.append(float(spatial(p, t)[0, 0][keep].mean().item()))
    return plain, masked


class CleanFeatures(torch.nn.Module):
    """clean-fid's InceptionV3W 'clean' forward, (x - 128) / 128 then the pool features, around
    the randomly initialised FID Inception."""

    def __init__(self, net: torch.nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x):
        x = (x - 128) / 128
        for name in ["Conv2d_1a_3x3", "Conv2d_2a_3x3", "Conv2d_2b_3x3", "maxpool1", "Conv2d_3b_1x1",
                     "Conv2d_4a_3x3", "maxpool2", "Mixed_5b", "Mixed_5c", "Mixed_5d", "Mixed_6a", "Mixed_6b",
                     "Mixed_6c", "Mixed_6d", "Mixed_6e", "Mixed_7a", "Mixed_7b", "Mixed_7c", "avgpool"]:
            x = getattr(self.net, name)(x)
        return x.flatten(1)


def fid_inception() -> torch.nn.Module:
    """cleanfid.inception_pytorch.fid_inception_v3() without its weight download."""
    torch.manual_seed(SEED)
    net = torchvision.models.inception_v3(weights=None, num_classes=1008, aux_logits=False, init_weights=False)
    net.Mixed_5b = cinc.FIDInceptionA(192, pool_features=32)
    net.Mixed_5c = cinc.FIDInceptionA(256, pool_features=64)
    net.Mixed_5d = cinc.FIDInceptionA(288, pool_features=64)
    net.Mixed_6b = cinc.FIDInceptionC(768, channels_7x7=128)
    net.Mixed_6c = cinc.FIDInceptionC(768, channels_7x7=160)
    net.Mixed_6d = cinc.FIDInceptionC(768, channels_7x7=160)
    net.Mixed_6e = cinc.FIDInceptionC(768, channels_7x7=192)
    net.Mixed_7b = cinc.FIDInceptionE_1(1280)
    net.Mixed_7c = cinc.FIDInceptionE_2(2048)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.normal_(0, BN_MEAN_STD)
            m.running_var.uniform_(*BN_VAR_RANGE)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.normal_(0, 0.1)
        if isinstance(m, torch.nn.Conv2d):
            # Kaiming-like scale keeps activations O(1) through 90+ layers.
            torch.nn.init.normal_(m.weight, 0, (2.0 / (m.in_channels * m.kernel_size[0] * m.kernel_size[1])) ** 0.5)
    return net.eval()


def save_inception(out: Path) -> torch.nn.Module:
    """The random FID Inception, its weights saved as OUT/inception.safetensors."""
    net = fid_inception()
    save_file({k: v.contiguous() for k, v in net.state_dict().items()
               if not k.endswith("num_batches_tracked") and not k.startswith("fc.")},
              str(out / "inception.safetensors"))
    return net


def exact_fid(f1, f2):
    """clean-fid's frechet_distance of features f1, f2 ([n, d] float64) with np.mean and np.cov,
    |mu1 - mu2|^2 + tr S1 + tr S2 - 2 tr sqrt(S1 S2), with tr sqrt(S1 S2) taken exactly instead
    of through scipy's d x d sqrtm (at d = 2048 ~45 s of CPU, and only approximate on these
    rank-deficient products): with D1, D2 the centred features, S1 S2 = D1' D1 D2' D2 /
    ((n1 - 1)(n2 - 1)) has the nonzero eigenvalues of G G' for G = D1 D2', so tr sqrt(S1 S2) is
    G's singular-value sum over sqrt((n1 - 1)(n2 - 1))."""
    d1, d2 = f1 - f1.mean(0), f2 - f2.mean(0)
    n1, n2 = len(f1) - 1, len(f2) - 1
    diff = f1.mean(0) - f2.mean(0)
    tr_covmean = np.linalg.svd(d1 @ d2.T, compute_uv=False).sum() / np.sqrt(n1 * n2)
    return float(diff @ diff + (d1 * d1).sum() / n1 + (d2 * d2).sum() / n2 - 2 * tr_covmean)


def checked_exact_fid(p, t):
    """`exact_fid` of the full features, after checking it against clean-fid's own
    frechet_distance on their first FID_CHECK_COLUMNS columns."""
    a, b = p[:, :FID_CHECK_COLUMNS], t[:, :FID_CHECK_COLUMNS]
    theirs = float(cfid.frechet_distance(a.mean(0), np.cov(a, rowvar=False), b.mean(0), np.cov(b, rowvar=False)))
    ours = exact_fid(a, b)
    if abs(ours - theirs) > FID_CHECK_TOL * abs(theirs):
        sys.exit(f"exact_fid {ours} differs from clean-fid's frechet_distance {theirs}")
    return exact_fid(p, t)


def main() -> None:
    out = Path(sys.argv[1])
    if sys.argv[2:] == ["--weights-only"]:
        out.mkdir(parents=True, exist_ok=True)
        lpips_model(out, "alex")
        save_inception(out)
        return
    frames(out)
    expected = {}
    for net in ("alex", "vgg"):
        expected[f"lpips_{net}"], expected[f"masked_lpips_{net}"] = lpips_goldens(out, net)
    net = save_inception(out)
    model = CleanFeatures(net).eval()
    feats = {}
    for name in ("pred", "target"):
        feats[name] = cfid.get_folder_features(str(out / name), model, num_workers=0, batch_size=4,
                                               device=torch.device("cpu"), mode="clean", verbose=False)
    save_file({k: torch.from_numpy(v).contiguous() for k, v in feats.items()}, str(out / "features.safetensors"))
    p, t = feats["pred"].astype(np.float64), feats["target"].astype(np.float64)
    expected["fid"] = checked_exact_fid(p, t)
    expected["kid"] = cfid.kernel_distance(p, t)
    (out / "expected.json").write_text(json.dumps(expected, indent=1))


if __name__ == "__main__":
    main()
