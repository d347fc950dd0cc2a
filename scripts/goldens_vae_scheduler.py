#!/usr/bin/env python3
"""Reference outputs of diffusers' CogVideoX VAE and schedulers, for the trainer's parity tests.

Usage: goldens_vae_scheduler.py OUT_DIR

Builds a tiny random `AutoencoderKLCogVideoX` (fixed seed) and the CogVideoX-5B scheduler
configuration, runs diffusers on fixed random inputs and writes everything the Rust tests
(`trainer/tests/integration/vae.rs`, `.../scheduler.rs`) compare against:

  OUT_DIR/vae/config.json                         diffusers' own `save_pretrained` output
  OUT_DIR/vae/diffusion_pytorch_model.safetensors
  OUT_DIR/vae_io.safetensors                      inputs and diffusers' outputs (fp32)
  OUT_DIR/vae_tiling.json                         the tile settings used for the tiled goldens
  OUT_DIR/vae_5b_shapes.json                      {state-dict key: shape} of the real 5B VAE
  OUT_DIR/vae_two_level/                          a 2-level VAE with temporal_compression_ratio 4
                                                  (diffusers compresses time by 2 only), saved
  OUT_DIR/vae_two_level_io.safetensors            its encode/decode inputs and outputs
  OUT_DIR/scheduler/scheduler_config.json         the CogVideoX-5B scheduler config
  OUT_DIR/scheduler_io.safetensors                schedule, add_noise, get_velocity, DPM/DDIM loops

Nothing here is committed: the tests run this script into a temporary folder (the whole run takes
a few seconds on a CPU). Requires torch and diffusers (the project venv, `scripts/setup.sh`).
"""

import json
import sys
from pathlib import Path

import torch
from safetensors.torch import save_file
from diffusers import AutoencoderKLCogVideoX, CogVideoXDDIMScheduler, CogVideoXDPMScheduler

SEED = 20261123

# Same structure as the CogVideoX VAE (4 blocks: 8x spatial, 4x temporal compression, 16 latent
# channels) with small widths; must equal the Rust `AutoencoderKLCogVideoXConfig::tiny()` preset.
TINY_VAE = dict(
    in_channels=3,
    out_channels=3,
    down_block_types=["CogVideoXDownBlock3D"] * 4,
    up_block_types=["CogVideoXUpBlock3D"] * 4,
    block_out_channels=[16, 32, 32, 64],
    latent_channels=16,
    layers_per_block=1,
    act_fn="silu",
    norm_eps=1e-6,
    norm_num_groups=8,
    temporal_compression_ratio=4,
    sample_height=64,
    sample_width=80,
    scaling_factor=0.7,
)

# Tile settings for the tiled goldens: small enough that a 64x80 clip splits into 2x3 tiles with a
# 2-latent-pixel blend (the default 1/6, 1/5 factors only blend at 480x720).
TILING = dict(
    tile_sample_min_height=48,
    tile_sample_min_width=48,
    tile_overlap_factor_height=1 / 3,
    tile_overlap_factor_width=1 / 3,
)

# The scheduler_config.json of THUDM/CogVideoX-5b-I2V.
SCHEDULER_5B = dict(
    beta_end=0.012,
    beta_schedule="scaled_linear",
    beta_start=0.00085,
    clip_sample=False,
    clip_sample_range=1.0,
    num_train_timesteps=1000,
    prediction_type="v_prediction",
    rescale_betas_zero_snr=True,
    sample_max_value=1.0,
    set_alpha_to_one=True,
    snr_shift_scale=1.0,
    steps_offset=0,
    timestep_spacing="trailing",
    trained_betas=None,
)


def randomize_(module: torch.nn.Module, generator: torch.Generator) -> None:
    """Non-trivial values for every parameter (GroupNorm affine included, which defaults to 1/0)."""
    with torch.no_grad():
        for name, p in module.named_parameters():
            if p.ndim == 1 and ("norm" in name):
                # Norm scales near 1, shifts near 0, but not exactly.
                base = 1.0 if name.endswith("weight") else 0.0
                p.copy_(base + 0.1 * torch.randn(p.shape, generator=generator))
            else:
                fan_in = p[0].numel() if p.ndim > 1 else p.numel()
                p.copy_(torch.randn(p.shape, generator=generator) / fan_in**0.5)


def vae_goldens(out: Path) -> None:
    g = torch.Generator().manual_seed(SEED)
    vae = AutoencoderKLCogVideoX(**TINY_VAE).eval()
    randomize_(vae, g)
    vae.save_pretrained(out / "vae", safe_serialization=True)

    tensors = {}
    with torch.no_grad():
        # 17 frames: diffusers encodes them in two temporal batches (9 + 8 frames) carrying the
        # causal-conv cache across; non-square 32x48 frames.
        sample = torch.rand((1, 3, 17, 32, 48), generator=g) * 2 - 1
        tensors["encode.sample"] = sample
        tensors["encode.latent"] = vae.encode(sample).latent_dist.mean

        # 5 latent frames: decoded in batches of 3 + 2 latent frames -> 9 + 8 = 17 frames.
        latent = torch.randn((1, 16, 5, 4, 6), generator=g)
        tensors["decode.latent"] = latent
        tensors["decode.sample"] = vae.decode(latent).sample

        # Batch of 2 and a single frame (the 1-frame path of the up/down samplers).
        sample1 = torch.rand((2, 3, 1, 16, 24), generator=g) * 2 - 1
        tensors["encode1.sample"] = sample1
        tensors["encode1.latent"] = vae.encode(sample1).latent_dist.mean
        latent1 = torch.randn((2, 16, 1, 2, 3), generator=g)
        tensors["decode1.latent"] = latent1
        tensors["decode1.sample"] = vae.decode(latent1).sample

        vae.enable_tiling(**TILING)
        tiled = torch.rand((1, 3, 9, 64, 80), generator=g) * 2 - 1
        tensors["tiled_encode.sample"] = tiled
        tensors["tiled_encode.latent"] = vae.encode(tiled).latent_dist.mean
        tiled_latent = torch.randn((1, 16, 3, 8, 10), generator=g)
        tensors["tiled_decode.latent"] = tiled_latent
        tensors["tiled_decode.sample"] = vae.decode(tiled_latent).sample

    save_file({k: v.contiguous() for k, v in tensors.items()}, str(out / "vae_io.safetensors"))
    (out / "vae_tiling.json").write_text(json.dumps(TILING, indent=2))

    # The real CogVideoX-5B VAE's parameter names and shapes, without allocating it.
    with torch.device("meta"):
        real = AutoencoderKLCogVideoX(scaling_factor=0.7)
    shapes = {k: list(v.shape) for k, v in real.state_dict().items()}
    (out / "vae_5b_shapes.json").write_text(json.dumps(shapes, indent=1, sort_keys=True))


# A config diffusers accepts although its levels cannot give the ratio it names: 2 levels, so
# only level 0 downsamples, and `compress_time = i < int(log2(4))` halves time once (ratio 2).
TWO_LEVEL_VAE = dict(
    TINY_VAE,
    down_block_types=["CogVideoXDownBlock3D"] * 2,
    up_block_types=["CogVideoXUpBlock3D"] * 2,
    block_out_channels=[16, 32],
)


def two_level_vae_goldens(out: Path) -> None:
    g = torch.Generator().manual_seed(SEED + 3)
    vae = AutoencoderKLCogVideoX(**TWO_LEVEL_VAE).eval()
    randomize_(vae, g)
    vae.save_pretrained(out / "vae_two_level", safe_serialization=True)
    tensors = {}
    with torch.no_grad():
        # 9 frames of 16x24 -> 5 latent frames of 8x12 (time halved once, space once).
        sample = torch.rand((1, 3, 9, 16, 24), generator=g) * 2 - 1
        tensors["encode.sample"] = sample
        tensors["encode.latent"] = vae.encode(sample).latent_dist.mean
        latent = torch.randn((1, 16, 5, 8, 12), generator=g)
        tensors["decode.latent"] = latent
        tensors["decode.sample"] = vae.decode(latent).sample
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(out / "vae_two_level_io.safetensors"))


def scheduler_goldens(out: Path) -> None:
    dpm = CogVideoXDPMScheduler(**SCHEDULER_5B)
    ddim = CogVideoXDDIMScheduler(**SCHEDULER_5B)
    # The released checkpoint ships the DDIM class name; the pipeline builds the DPM one from it.
    ddim.save_config(out / "scheduler")

    g = torch.Generator().manual_seed(SEED + 1)
    t = {}
    t["alphas_cumprod"] = dpm.alphas_cumprod.clone()  # float64

    # add_noise / get_velocity on [B, F, C, H, W] latents, timesteps covering both ends.
    x0 = torch.randn((3, 2, 4, 3, 5), generator=g)
    noise = torch.randn(x0.shape, generator=g)
    timesteps = torch.tensor([0, 500, 999], dtype=torch.int64)
    t["add_noise.original_samples"] = x0
    t["add_noise.noise"] = noise
    t["add_noise.timesteps"] = timesteps
    t["add_noise.noisy_samples"] = dpm.add_noise(x0, noise, timesteps)
    t["get_velocity.velocity"] = dpm.get_velocity(x0, noise, timesteps)

    for steps in (50, 7):
        dpm.set_timesteps(steps)
        t[f"set_timesteps.{steps}"] = dpm.timesteps.clone()

    # Full 50-step DPM loop with random "model outputs" (no model needed to check the update rule).
    # The noise the step draws is replayed from a twin generator: the step draws once on a
    # first-order step and twice (keeping the second draw) on a second-order one.
    dpm.set_timesteps(50)
    shape = (1, 2, 4, 3, 3)
    sample = torch.randn(shape, generator=g)
    t["dpm.initial_sample"] = sample
    step_gen = torch.Generator().manual_seed(SEED + 2)
    twin_gen = torch.Generator().manual_seed(SEED + 2)
    old_pred = None
    timesteps = dpm.timesteps
    for i, ts in enumerate(timesteps):
        ts = int(ts)
        back = int(timesteps[i - 1]) if i > 0 else None
        model_output = torch.randn(shape, generator=g)
        prev_t = ts - dpm.config.num_train_timesteps // dpm.num_inference_steps
        drawn = torch.randn(shape, generator=twin_gen)
        if old_pred is not None and prev_t >= 0:
            drawn = torch.randn(shape, generator=twin_gen)
        sample, old_pred = dpm.step(model_output, old_pred, ts, back, sample, generator=step_gen, return_dict=False)
        t[f"dpm.{i}.model_output"] = model_output
        t[f"dpm.{i}.noise"] = drawn
        t[f"dpm.{i}.prev_sample"] = sample
        t[f"dpm.{i}.pred_original_sample"] = old_pred

    ddim.set_timesteps(50)
    sample = torch.randn(shape, generator=g)
    t["ddim.initial_sample"] = sample
    for i, ts in enumerate(ddim.timesteps):
        model_output = torch.randn(shape, generator=g)
        sample, pred = ddim.step(model_output, int(ts), sample, return_dict=False)
        t[f"ddim.{i}.model_output"] = model_output
        t[f"ddim.{i}.prev_sample"] = sample
        t[f"ddim.{i}.pred_original_sample"] = pred

    save_file({k: v.contiguous() for k, v in t.items()}, str(out / "scheduler_io.safetensors"))


def main() -> None:
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(SEED)
    vae_goldens(out)
    two_level_vae_goldens(out)
    scheduler_goldens(out)


if __name__ == "__main__":
    main()
