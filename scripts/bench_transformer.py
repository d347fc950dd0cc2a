#!/usr/bin/env python3
"""Transformer step time: this project's tch port against diffusers (PyTorch), same model.

Usage: bench_transformer.py [--threads 2] [--steps 5] [--warmup 2] [--repeats 3]
                            [--configs tiny,mid] [--mode train|forward] [--device cpu|cuda]
                            [--dtype f32|bf16] [--out results.json]

For each config the same CogVideoXTransformer3DModel (config, batch, latent size, text length)
runs a forward + backward step (loss = mean squared error against a random target; gradients
zeroed in place between steps) in two fresh processes: the Rust example `bench_transformer`
(release build, built here first; PROFILE=dev builds the test profile, BENCH_PREBUILT=1 uses the one
already built) and diffusers. Both use the same thread count and the rotary
table of the CogNVS trainer (grid_type="slice"), computed outside the timed region. Runs
alternate between the two implementations `--repeats` times; the figure per implementation is the
median over repeats of each run's median step time. Prints a table with the ratio tch / PyTorch
and the peak RSS of each process, and writes the raw numbers to --out.

Configs:
  tiny  the `tiny` preset (2 blocks, 2 heads x 16), 2 x 3 x 32 x 8 x 10 latents, 8 text tokens
  mid   8 blocks, 12 heads x 64 (768 wide), text width 4096 with 226 tokens (the real text
        length), 1 x 5 x 32 x 16 x 24 latents (480 video tokens)
  5b    the released CogNVS config (cognvs-5b) at 49 x 480 x 720 (13 x 60 x 90 latents): only on
        a GPU (`--device cuda --dtype bf16 --mode forward`)
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

TINY = dict(
    num_attention_heads=2, attention_head_dim=16, in_channels=32, out_channels=16, time_embed_dim=32,
    text_embed_dim=16, num_layers=2, sample_width=10, sample_height=8, sample_frames=9,
    max_text_seq_length=8, use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True,
)
MID = dict(
    num_attention_heads=12, attention_head_dim=64, in_channels=32, out_channels=16, time_embed_dim=512,
    text_embed_dim=4096, num_layers=8, sample_width=24, sample_height=16, sample_frames=17,
    max_text_seq_length=226, use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True,
)
COGNVS_5B = dict(
    num_attention_heads=48, in_channels=32, num_layers=42,
    use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True,
)
# name -> (config, batch, latent frames, latent height, latent width, text tokens)
CASES = {
    "tiny": (TINY, 2, 3, 8, 10, 8),
    "mid": (MID, 1, 5, 16, 24, 226),
    "5b": (COGNVS_5B, 1, 13, 60, 90, 226),
}


def peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def worker(args) -> None:
    """The PyTorch half: one process, prints one JSON line like the Rust example."""
    import torch
    from diffusers import CogVideoXTransformer3DModel
    from diffusers.models.embeddings import get_3d_rotary_pos_embed

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    config, batch, frames, height, width, text_len = CASES[args.case]
    device = torch.device(args.device)
    dtype = torch.bfloat16 if args.dtype == "bf16" else torch.float32
    model = CogVideoXTransformer3DModel(**config).to(device=device, dtype=dtype)
    train = args.mode == "train"
    model.train(train)
    c = model.config
    hidden = torch.randn(batch, frames, c.in_channels, height, width, device=device, dtype=dtype)
    text = torch.randn(batch, text_len, c.text_embed_dim, device=device, dtype=dtype)
    target = torch.randn(batch, frames, c.out_channels, height, width, device=device, dtype=dtype)
    timestep = torch.full((batch,), 500, dtype=torch.int64, device=device)
    grid = (height // c.patch_size, width // c.patch_size)
    rope = get_3d_rotary_pos_embed(c.attention_head_dim, None, grid, frames, grid_type="slice", max_size=grid, device=device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    times = []
    for step in range(args.warmup + args.steps):
        start = time.perf_counter()
        if train:
            out = model(hidden, text, timestep, image_rotary_emb=rope, return_dict=False)[0]
            loss = ((out - target) ** 2).float().mean()
            loss.backward()
            model.zero_grad(set_to_none=False)
        else:
            with torch.no_grad():
                model(hidden, text, timestep, image_rotary_emb=rope, return_dict=False)
        if device.type == "cuda":
            torch.cuda.synchronize()
        if step >= args.warmup:
            times.append(time.perf_counter() - start)
    result = dict(impl="torch", mode=args.mode, median_s=statistics.median(times), step_s=times,
                  peak_rss_mb=peak_rss_mb(), threads=torch.get_num_threads())
    if device.type == "cuda":
        result["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    print(json.dumps(result))


def run_json(cmd, env=None) -> dict:
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--configs", default="tiny,mid")
    p.add_argument("--mode", choices=["train", "forward"], default="train")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    p.add_argument("--dtype", choices=["f32", "bf16"], default="f32")
    p.add_argument("--out", type=Path)
    p.add_argument("--worker", dest="case", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.case:
        return worker(args)

    target_dir = Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target"))
    profile = os.environ.get("PROFILE", "release")
    if not os.environ.get("BENCH_PREBUILT"):
        subprocess.run(["cargo", "build", "--profile", profile, "--quiet", "-p", "trainer", "--example", "bench_transformer"],
                       cwd=ROOT, check=True)
    rust = target_dir / ("debug" if profile == "dev" else profile) / "examples" / "bench_transformer"
    # Both processes get the same thread settings; OpenMP must not spin on cores the other uses.
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads))
    results = {}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.configs.split(","):
            config, batch, frames, height, width, text_len = CASES[name]
            cfg = Path(tmp) / f"{name}.json"
            cfg.write_text(json.dumps(dict(config, _class_name="CogVideoXTransformer3DModel")))
            rust_cmd = [str(rust), str(cfg), str(batch), str(frames), str(height), str(width), str(text_len),
                        str(args.steps), str(args.warmup), str(args.threads), args.device, args.dtype, args.mode]
            torch_cmd = [sys.executable, __file__, "--worker", name, "--threads", str(args.threads), "--steps",
                         str(args.steps), "--warmup", str(args.warmup), "--mode", args.mode, "--device", args.device,
                         "--dtype", args.dtype]
            runs = {"tch": [], "torch": []}
            for r in range(args.repeats):
                order = [("tch", rust_cmd), ("torch", torch_cmd)]
                for impl, cmd in order if r % 2 == 0 else order[::-1]:
                    runs[impl].append(run_json(cmd, env))
            med = {k: statistics.median(x["median_s"] for x in v) for k, v in runs.items()}
            rss = {k: max(x["peak_rss_mb"] for x in v) for k, v in runs.items()}
            tokens = frames * (height // 2) * (width // 2)
            rows.append((name, tokens, text_len, med["tch"], med["torch"], med["tch"] / med["torch"], rss["tch"], rss["torch"]))
            results[name] = dict(runs=runs, median_s=med, ratio=med["tch"] / med["torch"], peak_rss_mb=rss)
    print(f"transformer {args.mode} step, {args.device} {args.dtype}, {args.threads} threads, "
          f"{args.steps} steps after {args.warmup} warm-up, {args.repeats} alternating repeats")
    print(f"{'config':8} {'video tok':>9} {'text tok':>8} {'tch s':>9} {'torch s':>9} {'ratio':>6} {'tch RSS MB':>10} {'torch RSS MB':>12}")
    for row in rows:
        print(f"{row[0]:8} {row[1]:9d} {row[2]:8d} {row[3]:9.4f} {row[4]:9.4f} {row[5]:6.3f} {row[6]:10.0f} {row[7]:12.0f}")
    if args.out:
        args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
