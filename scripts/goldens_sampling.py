#!/usr/bin/env python3
"""Reference videos of the public CogNVS sampling procedure, for `trainer sample`'s parity tests.

Usage: goldens_sampling.py OUT_DIR [--device cpu|cuda] [--dtype fp32|bf16] [--cases a,b,...]

`--cases cognvs_5b` (never by default) samples the public demo's job at full size with random
weights (the CogNVS transformer and the 5B VAE, 49 x 480 x 720, 50 steps): the GPU check's
reference, with its timings and peak memory in case.json.

For each case, builds tiny random diffusers models (a CogVideoX transformer with 32 input
channels, a CogVideoX VAE, the CogVideoX-5B scheduler config), random text embeddings and a
conditioning clip, and samples the clip the way the public CogNVS pipeline does, written here from
diffusers' components step by step:

  1. the conditioning (uint8 frames -> x / 127.5 - 1) is VAE-encoded (tiling where the case says)
     and the posterior is *sampled* with the generator; the sample is cast to the model's dtype,
     put frames-first and multiplied by the VAE's scaling factor;
  2. the initial latents (1, F', 16, h, w) are drawn with the generator in the model's dtype;
  3. CogVideoXDPMScheduler steps (trailing spacing): noisy and condition latents concatenated on
     channels, negative and positive text embeddings as one batch of two when guidance > 1, the
     transformer's output cast to float32 and guided (uncond + g * (cond - uncond)), the scheduler
     step drawing its noise with the generator, the latents cast back to the model's dtype;
  4. latents * (1 / scaling_factor) decoded, then diffusers' video post-processing to uint8.

The generator is `torch.Generator(device).manual_seed(seed)`. Writes, per case, a folder usable as
a CogVideoX pipeline folder plus what the Rust test compares:

  OUT_DIR/<case>/transformer/        diffusers' save_pretrained
  OUT_DIR/<case>/vae/                diffusers' save_pretrained
  OUT_DIR/<case>/scheduler/          the 5B scheduler config
  OUT_DIR/<case>/text.safetensors    `encoder_hidden_states` [S, D] of the prompt
  OUT_DIR/<case>/negative.safetensors   of the negative prompt (only cases with one)
  OUT_DIR/<case>/cond/%05d.png       the conditioning frames
  OUT_DIR/<case>/expected/%05d.png   the sampled frames
  OUT_DIR/<case>/case.json           steps, seed, guidance, tiling, dtype

Nothing here is committed: the tests run this script into a temporary folder.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from safetensors.torch import save_file
from diffusers import AutoencoderKLCogVideoX, CogVideoXDPMScheduler, CogVideoXTransformer3DModel
from diffusers.models.embeddings import get_3d_rotary_pos_embed
from diffusers.utils.torch_utils import randn_tensor
from diffusers.video_processor import VideoProcessor

# The scheduler_config.json of THUDM/CogVideoX-5b-I2V.
SCHEDULER_5B = dict(
    beta_end=0.012, beta_schedule="scaled_linear", beta_start=0.00085, clip_sample=False, clip_sample_range=1.0,
    num_train_timesteps=1000, prediction_type="v_prediction", rescale_betas_zero_snr=True, sample_max_value=1.0,
    set_alpha_to_one=True, snr_shift_scale=1.0, steps_offset=0, timestep_spacing="trailing", trained_betas=None,
)

# A small CogVideoX VAE of the real structure (8x spatial, 4x temporal, 16 latent channels). Its
# nominal 96x80 frame makes diffusers' default tiles (half the frame, overlaps 1/6 and 1/5) land on
# whole latent pixels, as 480x720 does for the real VAE.
VAE = dict(
    in_channels=3, out_channels=3, down_block_types=["CogVideoXDownBlock3D"] * 4,
    up_block_types=["CogVideoXUpBlock3D"] * 4, block_out_channels=[16, 32, 32, 64], latent_channels=16,
    layers_per_block=1, act_fn="silu", norm_eps=1e-6, norm_num_groups=8, temporal_compression_ratio=4,
    sample_height=96, sample_width=80, scaling_factor=0.7,
)

# Small transformers of the CogNVS shape (32 channels in: noisy + condition latents).
COGNVS = dict(
    num_attention_heads=2, attention_head_dim=16, in_channels=32, out_channels=16, time_embed_dim=32,
    text_embed_dim=24, num_layers=2, sample_width=10, sample_height=12, sample_frames=9, max_text_seq_length=7,
    use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True,
)
ROTARY_ONLY = dict(COGNVS, num_attention_heads=3, num_layers=1, use_learned_positional_embeddings=False)

# The released CogNVS transformer and the CogVideoX-5B VAE at full size (random weights), for the
# GPU check only: built on the device, about 11 GB of weights in bf16.
COGNVS_5B = dict(num_attention_heads=48, attention_head_dim=64, in_channels=32, out_channels=16, num_layers=42,
                 use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True)
VAE_5B = dict(scaling_factor=0.7)

# name: (transformer config, VAE config, frames, height, width, steps, seed, guidance, negative
# prompt, tiling)
CASES = {
    # The released model's structure at its own size, real guidance, VAE tiles (the demo's).
    "cognvs": (COGNVS, VAE, 9, 96, 80, 4, 7, 6.0, True, True),
    # The empty prompt on both sides (what CogNVS samples with): guidance returns the one branch.
    "same_prompt": (COGNVS, VAE, 9, 96, 80, 3, 11, 6.0, False, True),
    # Rotary positions only, a grid of another aspect (cropped rotary table), 5 frames, no tiles.
    "rotary_only": (ROTARY_ONLY, VAE, 5, 48, 96, 6, 3, 4.5, True, False),
    # More frames than the positional table's 9 (its sin-cos fallback), guidance off.
    "long": (COGNVS, VAE, 17, 96, 80, 2, 5, 1.0, False, True),
}
# Only when named: the demo's job at full size (49 x 480 x 720, 50 steps, real guidance).
FULL_SIZE = {"cognvs_5b": (COGNVS_5B, VAE_5B, 49, 480, 720, 50, 42, 6.0, True, True)}


def crop_region(grid_h, grid_w, base_h, base_w):
    """The base grid's region the pipeline maps a (grid_h, grid_w) latent grid to: the grid's
    aspect fitted inside the base grid, centred (python's round, half to even)."""
    if grid_h / grid_w > base_h / base_w:
        size_h, size_w = base_h, int(round(base_h / grid_h * grid_w))
    else:
        size_h, size_w = int(round(base_w / grid_w * grid_h)), base_w
    top, left = int(round((base_h - size_h) / 2.0)), int(round((base_w - size_w) / 2.0))
    return (top, left), (top + size_h, left + size_w)


def synchronize(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def sample(transformer, vae, scheduler, frames_u8, text, negative, steps, guidance, seed, device, dtype, timings):
    """The sampled frames; `timings` gets the seconds of the encode, the denoising and the decode."""
    synchronize(device)
    clock = time.perf_counter()
    generator = torch.Generator(device=device).manual_seed(seed)
    video = torch.from_numpy(frames_u8).permute(0, 3, 1, 2).unsqueeze(0).float().div(127.5).sub(1.0).to(device)
    video = VideoProcessor(vae_scale_factor=8).preprocess_video(video, height=video.shape[-2], width=video.shape[-1])
    video = video.to(device, dtype=dtype)  # [1, 3, F, H, W]
    scale = vae.config.scaling_factor
    posterior = vae.encode(video).latent_dist
    condition = posterior.sample(generator).to(dtype).permute(0, 2, 1, 3, 4)
    condition = scale * condition
    synchronize(device)
    timings["encode"], clock = time.perf_counter() - clock, time.perf_counter()
    _, frames, _, h, w = condition.shape
    latents = randn_tensor((1, frames, transformer.config.out_channels, h, w), generator=generator,
                           device=device, dtype=dtype)
    latents = latents * scheduler.init_noise_sigma
    c = transformer.config
    grid = (h // c.patch_size, w // c.patch_size)
    crops = crop_region(grid[0], grid[1], c.sample_height // c.patch_size, c.sample_width // c.patch_size)
    rotary = get_3d_rotary_pos_embed(c.attention_head_dim, crops, grid, frames, device=device)
    guided = guidance > 1.0
    embeds = torch.cat([negative, text]) if guided else text
    scheduler.set_timesteps(steps, device=device)
    timesteps = scheduler.timesteps
    previous_x0 = None
    with torch.no_grad():
        for i, t in enumerate(timesteps):
            noisy = torch.cat([latents, latents]) if guided else latents
            cond = torch.cat([condition, condition]) if guided else condition
            model_input = torch.cat([scheduler.scale_model_input(noisy, t), cond], dim=2)
            v = transformer(hidden_states=model_input, encoder_hidden_states=embeds,
                            timestep=t.expand(model_input.shape[0]), image_rotary_emb=rotary,
                            return_dict=False)[0].float()
            if guided:
                v_uncond, v_text = v.chunk(2)
                v = v_uncond + guidance * (v_text - v_uncond)
            back = timesteps[i - 1] if i > 0 else None
            latents, previous_x0 = scheduler.step(v, previous_x0, t, back, latents, generator=generator,
                                                  return_dict=False)
            latents = latents.to(dtype)
        synchronize(device)
        timings["denoise"], clock = time.perf_counter() - clock, time.perf_counter()
        decoded = vae.decode(1 / scale * latents.permute(0, 2, 1, 3, 4)).sample
        synchronize(device)
        timings["decode"] = time.perf_counter() - clock
    frames = VideoProcessor(vae_scale_factor=8).postprocess_video(decoded, output_type="pil")[0]
    return [np.asarray(f) for f in frames]


def embedding(seed, shape):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed))


def conditioning(seed, frames, height, width):
    """A render-like clip: smooth colour ramps moving over the frames, a black hole region."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    clip = []
    for f in range(frames):
        phase = rng.uniform(0, 2 * np.pi, 3)
        rgb = [127.5 + 120 * np.sin(x / (7 + 3 * k) + y / (11 + k) + phase[k] + 0.3 * f) for k in range(3)]
        frame = np.stack(rgb, -1) + rng.normal(0, 6, (height, width, 3))
        frame[height // 3: height // 2, width // 4: width // 2 + f % 5] = 0  # a hole
        clip.append(np.clip(frame, 0, 255).round().astype(np.uint8))
    return np.stack(clip)


def write_case(out, name, device, dtype):
    config, vae_config, frames, height, width, steps, seed, guidance, with_negative, tiling = {**CASES, **FULL_SIZE}[name]
    folder = out / name
    torch.manual_seed(1000 + seed)
    # Tiny models are drawn on the CPU (the same weights on every device); full-size ones on the
    # device, in its dtype, as a GPU check can afford.
    build = torch.device(device) if name in FULL_SIZE else torch.device("cpu")
    with build:
        transformer = CogVideoXTransformer3DModel(**config).to(dtype if name in FULL_SIZE else torch.float32).eval()
        vae = AutoencoderKLCogVideoX(**vae_config).to(dtype if name in FULL_SIZE else torch.float32).eval()
    transformer.save_pretrained(folder / "transformer")
    vae.save_pretrained(folder / "vae")
    scheduler = CogVideoXDPMScheduler(**SCHEDULER_5B)
    scheduler.save_config(folder / "scheduler")
    shape = (config["max_text_seq_length"], config["text_embed_dim"])
    text = embedding(seed, shape)
    save_file({"encoder_hidden_states": text.contiguous()}, str(folder / "text.safetensors"))
    negative = embedding(seed + 1, shape) if with_negative else text
    if with_negative:
        save_file({"encoder_hidden_states": negative.contiguous()}, str(folder / "negative.safetensors"))
    clip = conditioning(seed, frames, height, width)
    (folder / "cond").mkdir(parents=True, exist_ok=True)
    for i, frame in enumerate(clip):
        Image.fromarray(frame).save(folder / "cond" / f"{i:05d}.png")
    if (transformer.dtype, transformer.device) != (dtype, torch.device(device)):
        transformer.to(device, dtype)
        vae.to(device, dtype)
    if tiling:
        vae.enable_tiling()
    if torch.device(device).type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    timings = {}
    result = sample(transformer, vae, scheduler, clip, text[None].to(device, dtype), negative[None].to(device, dtype),
                    steps, guidance, seed, device, dtype, timings)
    (folder / "expected").mkdir(exist_ok=True)
    for i, frame in enumerate(result):
        Image.fromarray(frame).save(folder / "expected" / f"{i:05d}.png")
    meta = dict(steps=steps, seed=seed, guidance=guidance, tiling=tiling, negative=with_negative,
                dtype=str(dtype).removeprefix("torch."), device=device, frames=frames, seconds=timings)
    if torch.device(device).type == "cuda":
        meta["peak_allocated_gib"] = torch.cuda.max_memory_allocated(device) / (1 << 30)
        meta["peak_reserved_gib"] = torch.cuda.max_memory_reserved(device) / (1 << 30)
    (folder / "case.json").write_text(json.dumps(meta, indent=1))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", choices=["fp32", "bf16"], default="fp32")
    parser.add_argument("--cases", default=",".join(CASES))
    args = parser.parse_args()
    dtype = torch.float32 if args.dtype == "fp32" else torch.bfloat16
    for name in args.cases.split(","):
        write_case(args.out, name, args.device, dtype)


if __name__ == "__main__":
    main()
