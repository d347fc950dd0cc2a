#!/usr/bin/env python3
"""One Wan LoRA test-time-finetune measurement of the GPU check (`scripts/gpu_check.sh`, stage
`wan_lora`): random weights of a Wan preset's shape, LoRA as the preset says, bf16 with gradient
checkpointing, steps of the rectified-flow objective, and the CUDA caching allocator's peaks, to
set beside `trainer plan`'s prediction for the same config.

Usage: gpu_check_wan.py --config PRESET.toml [--config ...] --configs-dir CONFIGS/wan [--device cuda]
           [--steps 2] [--frames F --height H --width W] [--tiny]

The preset's `[model]` names (`wan2.1-t2v-1.3b`, `wan2.1-i2v-14b`, `wan2.2-ti2v-5b` and the VAE's
`wan2.1`, `wan2.2`) map to the released diffusers configs under `--configs-dir`
(configs/wan/<model>/{transformer,vae}/config.json). The models are built on the meta device and
materialised on the target one in the working precision (a 14B model never exists in fp32), their
`_keep_in_fp32_modules` in fp32 as `from_pretrained` keeps them; the VAE encodes the random clip
once (no autograd) before the steps, as the trainer does per step. With `--tiny` the structures
are the Rust tests' tiny ones (`tiny-t2v`, `tiny-i2v`, the VAE's `tiny`) on the CPU, a
rehearsal of the path (no peaks there). Prints one JSON line per preset, in order, as each ends
(peaks in GiB, seconds per step; a preset out of memory is a line with `failed`, and the exit
status is then 1).

The trainer's own Wan LoRA step runs through `trainer pretrain` once it trains Wan; until then
this is diffusers + peft on the same shapes (the same module tree and operations).
"""

import argparse
import gc
import json
import math
import sys
import time
import tomllib
from pathlib import Path

import torch
from diffusers import AutoencoderKLWan, WanTransformer3DModel
from peft import LoraConfig

# `[model]` names of the presets → their folder under configs/wan/.
TRANSFORMERS = {
    "wan2.1-t2v-1.3b": "Wan2.1-T2V-1.3B",
    "wan2.1-i2v-14b": "Wan2.1-I2V-14B-480P",
    "wan2.2-ti2v-5b": "Wan2.2-TI2V-5B",
}
VAES = {"wan2.1": "Wan2.1-T2V-1.3B", "wan2.2": "Wan2.2-TI2V-5B"}
# The Rust presets `tiny-t2v` / `tiny-i2v` and the VAE's `tiny` (`WanTransformer3DModelConfig::tiny_*`,
# `AutoencoderKLWanConfig::tiny`).
TINY_T2V = dict(patch_size=[1, 2, 2], num_attention_heads=2, attention_head_dim=16, in_channels=4, out_channels=4,
                text_dim=16, freq_dim=32, ffn_dim=48, num_layers=2, rope_max_seq_len=32)
TINY_I2V = dict(TINY_T2V, in_channels=12, image_dim=24, added_kv_proj_dim=32)
TINY_VAE = dict(base_dim=8, z_dim=4, dim_mult=[1, 2, 2], num_res_blocks=1, temperal_downsample=[True, True],
                latents_mean=[0.0] * 4, latents_std=[1.0] * 4, scale_factor_spatial=4)
# Text tokens of the cross-attention context (umT5's padded length) and CLIP ViT-H/14 image
# tokens (Wan2.1 I2V), as the plan counts them.
TEXT_TOKENS = 512
IMAGE_TOKENS = 257
# Standard deviation of the random weights: any values do for memory and time; small ones keep
# bf16 activations finite through 40 blocks.
INIT_STD = 0.02


def materialise(model: torch.nn.Module, device: str, dtype: torch.dtype, keep_fp32: list[str]) -> torch.nn.Module:
    """A meta-device model on `device` with random weights in `dtype` (fp32 for `keep_fp32`)."""
    model = model.to_empty(device=device)
    with torch.no_grad():
        for name, p in model.named_parameters():
            kind = torch.float32 if any(part in keep_fp32 for part in name.split(".")) else dtype
            p.data = torch.empty(p.shape, device=device, dtype=kind).normal_(0.0, INIT_STD)
        for name, b in model.named_buffers():
            b.data = torch.zeros(b.shape, device=device, dtype=b.dtype)
    return model


def configs(preset: dict, configs_dir: Path, tiny: bool) -> tuple[dict, dict, bool]:
    """(transformer config, VAE config, image-to-video) of the preset's `[model]`."""
    name, vae = preset["model"]["transformer"], preset["model"]["vae"]
    if tiny:
        image = "-i2v-" in name  # not Wan2.2 TI2V's "ti2v"
        # Wan2.2's tiny VAE has 6 latent channels, which no tiny transformer takes: the rehearsal
        # runs its preset on Wan2.1's structure (`trainer plan` is given the same).
        return (TINY_I2V if image else TINY_T2V), TINY_VAE, image
    read = lambda folder, part: {
        k: v for k, v in json.loads((configs_dir / folder / part / "config.json").read_text()).items()
        if not k.startswith("_")
    }
    transformer = read(TRANSFORMERS[name], "transformer")
    return transformer, read(VAES[vae], "vae"), transformer.get("image_dim") is not None


def measure(config_path: Path, args: argparse.Namespace) -> dict:
    """One preset's steps: sizes, adapter count, seconds per step and (CUDA) the peaks."""
    preset = tomllib.loads(config_path.read_text())
    data = preset["data"]
    frames, height, width = args.frames or data["frames"], args.height or data["height"], args.width or data["width"]
    t_config, v_config, image = configs(preset, args.configs_dir, args.tiny)
    device = args.device
    dtype = torch.float32 if args.tiny else torch.bfloat16
    cuda = device.startswith("cuda")
    torch.manual_seed(0)

    with torch.device("meta"):
        transformer = WanTransformer3DModel(**t_config)
        vae = AutoencoderKLWan(**v_config)
    transformer = materialise(transformer, device, dtype, WanTransformer3DModel._keep_in_fp32_modules or [])
    vae = materialise(vae, device, dtype, []).eval().requires_grad_(False)
    transformer.requires_grad_(False)
    transformer.enable_gradient_checkpointing()
    lora = preset["lora"]
    rank = 4 if args.tiny else lora["rank"]
    transformer.add_adapter(LoraConfig(r=rank, lora_alpha=lora.get("alpha", rank),
                                       target_modules=lora["target_modules"], init_lora_weights=True))
    adapters = [p for n, p in transformer.named_parameters() if ".lora_" in n]
    for p in adapters:
        p.data = p.data.to(dtype)
        p.requires_grad_(True)
    optimizer = torch.optim.AdamW(adapters, lr=preset["optim"]["lr"], betas=(0.9, 0.95), weight_decay=1e-4)

    g = torch.Generator(device=device).manual_seed(0)
    video = torch.rand((1, 3, frames, height, width), generator=g, device=device) * 2 - 1
    text = torch.randn((1, TEXT_TOKENS, t_config["text_dim"]), generator=g, device=device, dtype=dtype)
    image_tokens = (torch.randn((1, IMAGE_TOKENS, t_config["image_dim"]), generator=g, device=device, dtype=dtype)
                    if image else None)
    # Wan2.2 TI2V trains with one timestep per token (`expand_timesteps`), the plan's assumption.
    per_token = v_config.get("is_residual", False)
    seconds = []
    for _ in range(args.steps):
        start = time.perf_counter()
        with torch.no_grad():
            latents = vae.encode(video.to(dtype)).latent_dist.sample(generator=g)
        noise = torch.randn(latents.shape, generator=g, device=device, dtype=dtype)
        sigma = torch.rand((), generator=g, device=device)
        noisy = ((1 - sigma) * latents + sigma * noise).to(dtype)
        extra = t_config["in_channels"] - noisy.shape[1]
        if extra > 0:  # mask and condition channels (I2V)
            noisy = torch.cat([noisy, torch.zeros_like(noisy[:, :1]).expand(-1, extra, -1, -1, -1)], dim=1)
        patch = t_config.get("patch_size", [1, 2, 2])
        tokens = math.prod(s // p for s, p in zip(noisy.shape[2:], patch))
        timestep = (sigma * 1000).expand(1, tokens) if per_token else (sigma * 1000).reshape(1)
        out = transformer(hidden_states=noisy, timestep=timestep, encoder_hidden_states=text,
                          encoder_hidden_states_image=image_tokens, return_dict=False)[0]
        loss = torch.nn.functional.mse_loss(out.float(), (noise - latents).float())
        loss.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=False)
        if cuda:
            torch.cuda.synchronize()
        seconds.append(time.perf_counter() - start)
    gib = lambda b: round(b / (1 << 30), 3)
    result = dict(preset=config_path.stem, frames=frames, height=height, width=width, tokens=tokens, adapters=sum(p.numel() for p in adapters),
                  first_step_s=round(seconds[0], 3), last_step_s=round(seconds[-1], 3), loss=float(loss.detach()))
    if cuda:
        result.update(peak_allocated_gib=gib(torch.cuda.max_memory_allocated()),
                      peak_reserved_gib=gib(torch.cuda.max_memory_reserved()))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", type=Path, action="append", required=True)
    parser.add_argument("--configs-dir", type=Path, required=True)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--frames", type=int)
    parser.add_argument("--height", type=int)
    parser.add_argument("--width", type=int)
    parser.add_argument("--tiny", action="store_true")
    args = parser.parse_args()
    failed = False
    for config_path in args.config:
        # Each preset's peaks are its own: what the last one left is freed first.
        gc.collect()
        if args.device.startswith("cuda"):
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats()
        try:
            result = measure(config_path, args)
        except torch.OutOfMemoryError as e:
            result, failed = dict(preset=config_path.stem, failed=f"out of memory: {str(e)[:200]}"), True
        print(json.dumps(result), flush=True)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
