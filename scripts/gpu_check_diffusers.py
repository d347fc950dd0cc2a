"""diffusers' side of scripts/gpu_check.sh: training steps of CogVideoXTransformer3DModel (random
weights, random text embedding) with gradient checkpointing, LoRA or full, and the VAE encodes a
training step makes, timed apart; prints one JSON line.

Usage: gpu_check_diffusers.py --mode lora|full [--steps 6] [--tiny] [--device cuda]

The transformer is built on the device. A step is the transformer's forward and backward on
random latents of the training shape (49x480x720: 13 x 60 x 90 latents, 226 text tokens), the
gradient clipping and AdamW; the first step is the warm-up, the median of the others is reported.
The VAE encode is timed on its own: two encodes of a 49x480x720 clip (target and condition, as a
training step makes them) with the CogVideoX-5B VAE in bf16, median of 3 after a warm-up. Peaks
are the caching allocator's, in GiB, over the whole run. --tiny builds the trainer's `tiny`
preset (2 blocks of 2 x 16) at 9 x 64 x 80 in fp32 for a CPU rehearsal.
"""

import argparse
import json
import resource
import statistics
import time

import torch
from diffusers import AutoencoderKLCogVideoX, CogVideoXTransformer3DModel

# The released CogNVS transformer: CogVideoX-5B-I2V with 32 input channels.
COGNVS_5B = dict(num_attention_heads=48, attention_head_dim=64, in_channels=32, out_channels=16, num_layers=42,
                 use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True)
# trainer's CogVideoXTransformer3DModelConfig::tiny().
TINY = dict(num_attention_heads=2, attention_head_dim=16, in_channels=32, out_channels=16, time_embed_dim=32,
            text_embed_dim=16, num_layers=2, sample_width=10, sample_height=8, sample_frames=9,
            max_text_seq_length=8, use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True)
# The CogVideoX-5B VAE (diffusers' defaults with scaling factor 0.7) and trainer's `tiny` VAE.
VAE_5B = dict(scaling_factor=0.7)
VAE_TINY = dict(block_out_channels=[16, 32, 32, 64], layers_per_block=1, norm_num_groups=8, sample_height=64,
                sample_width=80, scaling_factor=0.7)
GIB = 1 << 30


def synchronize(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def rotary(model, frames, height, width, device):
    from diffusers.models.embeddings import get_3d_rotary_pos_embed
    c = model.config
    grid = (height // c.patch_size, width // c.patch_size)
    # At the transformer's own size the pipelines' crop region is the whole grid.
    return get_3d_rotary_pos_embed(c.attention_head_dim, ((0, 0), grid), grid, frames, device=device)


def train_steps(mode, steps, tiny, device, dtype):
    with torch.device(device):
        model = CogVideoXTransformer3DModel(**(TINY if tiny else COGNVS_5B))
    c = model.config
    frames, height, width = (c.sample_frames - 1) // 4 + 1, c.sample_height, c.sample_width
    if mode == "lora":
        from peft import LoraConfig
        model.requires_grad_(False)
        model.to(dtype)
        model.add_adapter(LoraConfig(r=4 if tiny else 128, lora_alpha=2 if tiny else 64, init_lora_weights=True,
                                     target_modules=["to_q", "to_k", "to_v", "to_out.0"]))
        params = [p for p in model.parameters() if p.requires_grad]
        for p in params:
            p.data = p.data.float()  # fp32 adapters and optimizer, as diffusers' scripts cast them
    else:
        params = list(model.parameters())  # fp32 weights under bf16 autocast
    model.enable_gradient_checkpointing()
    model.train()
    optimizer = torch.optim.AdamW(params, lr=2e-5, betas=(0.9, 0.95), weight_decay=1e-4)
    text = torch.randn(1, c.max_text_seq_length, c.text_embed_dim, device=device, dtype=dtype)
    rope = rotary(model, frames, height, width, device)
    times = []
    for _ in range(steps):
        synchronize(device)
        start = time.perf_counter()
        x = torch.randn(1, frames, c.in_channels, height, width, device=device, dtype=dtype)
        t = torch.randint(0, 1000, (1,), device=device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=dtype == torch.bfloat16):
            out = model(hidden_states=x, encoder_hidden_states=text, timestep=t, image_rotary_emb=rope,
                        return_dict=False)[0]
        loss = out.float().square().mean()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        synchronize(device)
        times.append(time.perf_counter() - start)
    del model, optimizer, params
    return times


def encode_times(tiny, device, dtype, repeats=4):
    with torch.device(device):
        vae = AutoencoderKLCogVideoX(**(VAE_TINY if tiny else VAE_5B)).to(dtype).eval()
    frames, height, width = (9, 64, 80) if tiny else (49, 480, 720)
    video = torch.rand(1, 3, frames, height, width, device=device, dtype=dtype) * 2 - 1
    times = []
    with torch.no_grad():
        for _ in range(repeats):
            synchronize(device)
            start = time.perf_counter()
            for _ in range(2):  # target and condition
                vae.encode(video).latent_dist.sample()
            synchronize(device)
            times.append(time.perf_counter() - start)
    return times


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--mode", choices=["lora", "full"], required=True)
    p.add_argument("--steps", type=int, default=6)
    p.add_argument("--tiny", action="store_true")
    p.add_argument("--device", default="cuda")
    a = p.parse_args()
    device = torch.device(a.device)
    dtype = torch.float32 if a.tiny else torch.bfloat16
    step_times = train_steps(a.mode, a.steps, a.tiny, device, dtype)
    encodes = encode_times(a.tiny, device, dtype)
    result = {"impl": "diffusers", "mode": a.mode, "steps": len(step_times),
              "median_transformer_step_s": statistics.median(step_times[1:] or step_times),
              "warmup_step_s": step_times[0], "median_encode_s": statistics.median(encodes[1:] or encodes)}
    if device.type == "cuda":
        result["peak_allocated_gib"] = torch.cuda.max_memory_allocated(device) / GIB
        result["peak_reserved_gib"] = torch.cuda.max_memory_reserved(device) / GIB
    else:  # peak RSS, as the trainer's CPU figure (ru_maxrss is in KiB on Linux)
        result["peak_rss_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GIB
    print(json.dumps(result))


if __name__ == "__main__":
    main()
