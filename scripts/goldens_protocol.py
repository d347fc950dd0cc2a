#!/usr/bin/env python3
"""Reference tables of the paper's evaluation protocols, for `trainer eval`'s protocol tests.

Usage: goldens_protocol.py OUT_DIR

Builds tiny inputs and scores them the way the official codes do, with small random networks
standing in for downloaded weights (those of scripts/goldens_eval.py):

- OUT_DIR/bundle/: an evaluation bundle as the CogNVS release lays it out
  (`<dataset>/<method>/*<scene>_<method>[_cam<k>].mp4`, `<dataset>/target_gt[_1x]/`,
  `dycheck/dycheck_<scene>_source_target_correspondence.txt`), videos of different lengths and
  of sizes above, below and at the protocol's size (lossless PNG-in-MP4, so every decoder reads
  the same pixels), scored by `evaluate_dataset` of the CogNVS repository's `eval/eval_metrics.py`
  step for step: cv2.VideoCapture, cv2.resize to the protocol size, skimage PSNR/SSIM, lpips,
  frames written as PNGs and clean-fid's `compute_kid` on the two folders (its feature extractor
  replaced by the random Inception; FID is `compute_fid`'s value on the same features, its matrix
  square root's trace taken exactly: see goldens_eval.py's `exact_fid`), every list pooled with
  np.mean. The script itself is not on PyPI, so its steps are written here from its code; every
  metric call is the real package's.
- OUT_DIR/masked/{pred,target,mask}/<video>/%05d.png: two videos with masks with holes, one
  frame with no co-visible pixel, scored by DyCheck's masked metrics
  (KAIR-BAIR/dycheck `dycheck/core/metrics/image.py`: compute_psnr, compute_ssim,
  get_compute_lpips; `masked_mean` of `dycheck/nn/functional/common.py`; the plain mean over
  frames of `NovelView.finalize`). dycheck is not on PyPI and needs JAX, so compute_ssim's
  partial convolution is written here with scipy.signal.convolve2d (mode "valid", as
  jax.scipy.signal.convolve2d), following its code line by line; LPIPS is the lpips package's
  own `spatial=True` model on `lpips.im2tensor` of the masked images.
- OUT_DIR/lpips_alex.safetensors, OUT_DIR/inception.safetensors: the random weights.
- OUT_DIR/expected.json: {"kubric_4d", "pardom_4d", "dycheck_360p"}: the bundle tables (psnr,
  ssim, lpips, frames; fid, kid and kid_float64 (clean-fid's kernel_distance on the same features
  in float64) for Kubric-4D; JSON null for an infinite mean) and
  {"masked"}: per video and pooled.
"""

import json
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import lpips
import numpy as np
import torch
from cleanfid import fid as cfid
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

sys.path.insert(0, str(Path(__file__).resolve().parent))
import goldens_eval  # noqa: E402  (the random LPIPS / Inception weights)
from goldens_metrics import dycheck_psnr, dycheck_ssim, masked_mean  # noqa: E402

SEED = 20261207
# (width, height) of the official protocols: GCD 384x576, DyCheck 360p 480x360 (HxW).
GCD = (576, 384)
DYCHECK_360P = (360, 480)
FPS = 10

# Kubric-4D: scene -> (frames, target size, prediction size, prediction file prefix). Sizes
# below, at and above the protocol's, a non-integer and an exact-halving resize, and a file
# name with text before the scene (the official glob's leading `*`).
KUBRIC = {
    "scn02900": (2, GCD, (360, 240), ""),
    "scn02901": (3, (720, 480), (720, 480), "000_"),
    "scn02907": (1, GCD, (1152, 768), ""),
}
# DyCheck at 360p: scene -> cameras -> (target frames, prediction frames, correspondence
# target frames, prediction size): 2x enlargement and 2x reduction.
DYCHECK = {
    "apple": {1: (3, 6, [1, 3, 4], (180, 240)), 2: (2, 6, [0, 5], (180, 240))},
    "block": {1: (3, 4, [0, 1, 3], (720, 960))},
}
# ParallelDomain-4D: one scene at the protocol size whose first frame is predicted exactly.
PARDOM_SCENE = "scene_000048"
# DyCheck masked metrics: video -> frames; the last frame of "b" has no co-visible pixel.
MASKED = {"a": 3, "b": 2}
MASKED_SIZE = (64, 48)


def pattern(rng, size, frame):
    """A smooth RGB frame with noise, (H, W, 3) uint8 at size (W, H)."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([np.sin(xx / (7 + 2 * c) + frame) * np.cos(yy / (9 + c) - frame / 3) for c in range(3)], -1)
    return np.clip(127 + 100 * base + rng.normal(0, 12, (h, w, 3)), 0, 255).astype(np.uint8)


def distort(rng, frame, amount):
    shifted = np.roll(frame.astype(float), 2, axis=1)
    out = 0.75 * frame + 0.25 * shifted + rng.normal(0, amount, frame.shape)
    return np.clip(out, 0, 255).round().astype(np.uint8)


def write_video(path, frames):
    """RGB frames as a lossless PNG-in-MP4 video."""
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"png "), FPS, (w, h))
    assert writer.isOpened(), path
    for f in frames:
        writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    writer.release()


def resized(frame, size):
    return frame if frame.shape[1::-1] == tuple(size) else cv2.resize(frame, size)


def build_bundle(root, rng):
    kubric = root / "kubric_4d"
    for scene, (count, target_size, pred_size, prefix) in KUBRIC.items():
        target = [pattern(rng, target_size, f) for f in range(count)]
        pred = [resized(distort(rng, f, 6 + 3 * i), pred_size) for i, f in enumerate(target)]
        write_video(kubric / "target_gt" / f"{scene}_gt.mp4", target)
        write_video(kubric / "cognvs" / f"{prefix}{scene}_cognvs.mp4", pred)
    # A scene the official list does not hold: ignored.
    write_video(kubric / "cognvs" / "scn03000_cognvs.mp4", [pattern(rng, GCD, 0)])
    write_video(kubric / "target_gt" / "scn03000_gt.mp4", [pattern(rng, GCD, 1)])

    pardom = root / "pardom_4d"
    target = [pattern(rng, GCD, f) for f in range(2)]
    write_video(pardom / "target_gt" / f"{PARDOM_SCENE}_gt.mp4", target)
    write_video(pardom / "cognvs" / f"{PARDOM_SCENE}_cognvs.mp4", [target[0], distort(rng, target[1], 9)])

    dycheck = root / "dycheck"
    for scene, cameras in DYCHECK.items():
        lines = [f"0_{i:05d}.png" for i in range(3)]
        for cam, (count, pred_count, chosen, pred_size) in cameras.items():
            target = [pattern(rng, DYCHECK_360P, 10 * cam + f) for f in range(count)]
            pred = [resized(pattern(rng, DYCHECK_360P, 50 + f), pred_size) for f in range(pred_count)]
            for t, p in zip(target, chosen):
                pred[p] = resized(distort(rng, t, 5 + cam), pred_size)
            write_video(dycheck / "target_gt" / f"{scene}_gt_cam{cam}.mp4", target)
            write_video(dycheck / "cognvs" / f"{scene}_cognvs_cam{cam}.mp4", pred)
            lines += [f"{cam}_{i:05d}.png" for i in chosen]
        (dycheck / f"dycheck_{scene}_source_target_correspondence.txt").write_text("\n".join(lines) + "\n")


# --- evaluate_dataset of eval/eval_metrics.py, step for step ---------------------------------

def read_video(path, size):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        if frame.shape[:2] != (size[1], size[0]):
            frame = cv2.resize(frame, size)
        rgb = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        frames.append((rgb.astype(np.float32) / 255.0).transpose(2, 0, 1))
    cap.release()
    return np.stack(frames, axis=0)


def correspondence(path, camera):
    targets = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line:
            continue
        prefix, index = line.replace(".png", "").split("_")
        if prefix == str(camera):
            targets.append(int(index))
    return targets


def official_table(pairs, size, lpips_fn, feature_model, dycheck_dir=None):
    psnrs, ssims, lpipss = [], [], []
    work = Path(tempfile.mkdtemp())
    gt_dir, pred_dir = work / "tmp_gt", work / "tmp_pred"
    gt_dir.mkdir()
    pred_dir.mkdir()
    index = 0
    for scene, pred_path, gt_path in pairs:
        pred, gt = read_video(pred_path, size), read_video(gt_path, size)
        if dycheck_dir is not None:
            camera = int(str(gt_path).split("_cam")[-1].split(".")[0])
            file = dycheck_dir / f"dycheck_{scene}_source_target_correspondence.txt"
            if file.exists():
                pred = pred[correspondence(file, camera)]
        assert pred.shape[0] == gt.shape[0]
        for p, g in zip(pred, gt):
            with np.errstate(divide="ignore"):
                psnrs.append(peak_signal_noise_ratio(p, g, data_range=1.0))
            ssims.append(structural_similarity(p, g, data_range=1.0, channel_axis=0))
            to_tensor = lambda x: torch.tensor(x).unsqueeze(0).to(torch.float32) * 2 - 1  # noqa: E731
            with torch.no_grad():
                lpipss.append(lpips_fn(to_tensor(p), to_tensor(g)).item())
            for frame, folder in ((g, gt_dir), (p, pred_dir)):
                png = (frame.transpose(1, 2, 0) * 255).astype(np.uint8)
                cv2.imwrite(str(folder / f"{index:05d}.png"), cv2.cvtColor(png, cv2.COLOR_RGB2BGR))
            index += 1
    table = {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)), "lpips": float(np.mean(lpipss)),
             "frames": index}
    if feature_model is not None:
        # clean-fid's own folder pipeline, its Inception replaced by the random one: compute_kid
        # extracts both folders' features (as compute_fid would, with the same arguments); they
        # are kept for FID and for the float64 KID below.
        cfid.build_feature_extractor = lambda *args, **kwargs: feature_model
        extract, seen = cfid.get_folder_features, {}

        def keep(fdir, *args, **kwargs):
            seen[Path(fdir).name] = extract(fdir, *args, **kwargs)
            return seen[Path(fdir).name]

        cfid.get_folder_features = keep
        options = dict(mode="clean", num_workers=0, batch_size=4, device=torch.device("cpu"), verbose=False)
        table["kid"] = float(cfid.compute_kid(str(gt_dir), str(pred_dir), **options))
        cfid.get_folder_features = extract
        t, p = seen["tmp_gt"].astype(np.float64), seen["tmp_pred"].astype(np.float64)
        table["fid"] = goldens_eval.exact_fid(t, p)
        # compute_kid works on float32 features; the random Inception's features are large, so its
        # cubic kernel sums lose digits to float32 rounding (and vary with the subset order).
        # kernel_distance on the same features in float64 is the value without that rounding.
        table["kid_float64"] = float(cfid.kernel_distance(t, p))
    shutil.rmtree(work)
    return {k: (v if np.isfinite(v) else None) for k, v in table.items()}


def masked_goldens(out, rng, lpips_fn, spatial_fn):
    w, h = MASKED_SIZE
    yy, xx = np.mgrid[0:h, 0:w]
    result, pooled = {}, {k: [] for k in ("psnr", "ssim", "lpips", "masked_psnr", "masked_ssim", "masked_lpips")}
    for video, count in MASKED.items():
        values = {k: [] for k in pooled}
        for f in range(count):
            target = pattern(rng, MASKED_SIZE, f + 7 * len(video))
            pred = distort(rng, target, 10 + 4 * f)
            # Holes: a diagonal band and a disc; the last frame of "b" is all hidden.
            keep = ((xx + 2 * yy + 5 * f) % 17 < 11) & ((xx - 20) ** 2 + (yy - 20) ** 2 > 60)
            if video == "b" and f == count - 1:
                keep[:] = False
            mask = keep.astype(np.uint8) * 255
            for name, image in (("target", target), ("pred", pred), ("mask", mask)):
                path = out / "masked" / name / video / f"{f:05d}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(path), image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            # DyCheck's to_quantized_float32: the 8-bit values over 255.
            rgb, pred_rgb = target.astype(np.float32) / 255, pred.astype(np.float32) / 255
            m = (mask.astype(np.float32) / 255)[..., None]
            values["psnr"].append(peak_signal_noise_ratio(rgb, pred_rgb, data_range=1.0))
            values["ssim"].append(structural_similarity(pred_rgb, rgb, data_range=1.0, channel_axis=-1))
            values["masked_psnr"].append(dycheck_psnr(rgb, pred_rgb, m))
            values["masked_ssim"].append(dycheck_ssim(rgb, pred_rgb, m))
            with torch.no_grad():
                t = lambda x: torch.tensor(x.transpose(2, 0, 1)[None]) * 2 - 1  # noqa: E731
                values["lpips"].append(lpips_fn(t(pred_rgb), t(rgb)).item())
                a = lpips.im2tensor(np.array(rgb * m), factor=1 / 2)
                b = lpips.im2tensor(np.array(pred_rgb * m), factor=1 / 2)
                values["masked_lpips"].append(float(masked_mean(spatial_fn(a, b).cpu().numpy()[0, 0, ..., None], m)))
        for k, v in values.items():
            pooled[k] += v
        result[video] = {k: float(np.mean(v)) for k, v in values.items()}
    with np.errstate(invalid="ignore"):
        result["mean"] = {k: float(np.mean(v)) for k, v in pooled.items()}
    return {name: {k: (v if np.isfinite(v) else None) for k, v in row.items()} for name, row in result.items()}


def main():
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(SEED)
    lpips_fn = goldens_eval.lpips_model(out, "alex")
    spatial_fn = lpips.LPIPS(pnet_rand=True, net="alex", version="0.1", spatial=True, verbose=False).eval()
    spatial_fn.load_state_dict(lpips_fn.state_dict())
    features = goldens_eval.CleanFeatures(goldens_eval.save_inception(out)).eval()
    root = out / "bundle"
    build_bundle(root, rng)
    kubric = [(s, root / "kubric_4d" / "cognvs" / f"{p}{s}_cognvs.mp4", root / "kubric_4d" / "target_gt" / f"{s}_gt.mp4")
              for s, (_, _, _, p) in KUBRIC.items()]
    pardom = [(PARDOM_SCENE, root / "pardom_4d" / "cognvs" / f"{PARDOM_SCENE}_cognvs.mp4",
               root / "pardom_4d" / "target_gt" / f"{PARDOM_SCENE}_gt.mp4")]
    dycheck = [(s, root / "dycheck" / "cognvs" / f"{s}_cognvs_cam{c}.mp4",
                root / "dycheck" / "target_gt" / f"{s}_gt_cam{c}.mp4")
               for s, cams in DYCHECK.items() for c in sorted(cams)]
    expected = {
        "kubric_4d": official_table(kubric, GCD, lpips_fn, features),
        "pardom_4d": official_table(pardom, GCD, lpips_fn, None),
        # FID/KID once (Kubric-4D): the Inception passes dominate the script's time.
        "dycheck_360p": official_table(dycheck, DYCHECK_360P, lpips_fn, None, root / "dycheck"),
        "masked": masked_goldens(out, rng, lpips_fn, spatial_fn),
    }
    (out / "expected.json").write_text(json.dumps(expected, indent=1))


if __name__ == "__main__":
    main()
