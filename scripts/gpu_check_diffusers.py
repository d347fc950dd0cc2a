"""diffusers' side of scripts/gpu_check.sh: a few bf16 training steps of CogVideoXTransformer3DModel
(random weights, random text embedding) with gradient checkpointing, LoRA (peft, rank 128, alpha 64,
to_q/to_k/to_v/to_out.0) or full, printing the median step time and the peak device memory.

Usage: gpu_check_diffusers.py --mode lora|full [--steps 3] [--tiny] [--device cuda]
--tiny builds the trainer's `tiny` preset (2 blocks of 2 x 16) at 9 x 64 x 80 for a CPU check.
"""

import argparse
import json
import resource
import statistics
import time

import torch
from diffusers import CogVideoXTransformer3DModel

# The released CogNVS transformer (DESIGN.md §6): CogVideoX-5B-I2V with 32 input channels.
COGNVS_5B = dict(num_attention_heads=48, attention_head_dim=64, in_channels=32, out_channels=16, num_layers=42,
                 use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True)
# trainer's CogVideoXTransformer3DModelConfig::tiny().
TINY = dict(num_attention_heads=2, attention_head_dim=16, in_channels=32, out_channels=16, time_embed_dim=32,
            text_embed_dim=16, num_layers=2, sample_width=10, sample_height=8, sample_frames=9,
            max_text_seq_length=8, use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True)


def rotary(model, frames, height, width, device):
    from diffusers.models.embeddings import get_3d_rotary_pos_embed
    c = model.config
    grid = (height // c.patch_size, width // c.patch_size)
    # CogVideoXPipeline crops the grid to the model's base size (get_resize_crop_region_for_grid);
    # the check runs at the sample size itself, so the crop region is the whole grid.
    cos, sin = get_3d_rotary_pos_embed(c.attention_head_dim, ((0, 0), grid), grid, frames, device=device)
    return cos, sin


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--mode", choices=["lora", "full"], required=True)
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--tiny", action="store_true")
    p.add_argument("--device", default="cuda")
    a = p.parse_args()
    device = torch.device(a.device)
    dtype = torch.float32 if a.tiny else torch.bfloat16
    model = CogVideoXTransformer3DModel(**(TINY if a.tiny else COGNVS_5B)).to(device)
    c = model.config
    frames, height, width = c.sample_frames // 4 + 1, c.sample_height, c.sample_width
    if a.mode == "lora":
        from peft import LoraConfig
        model.requires_grad_(False)
        model.to(dtype)
        model.add_adapter(LoraConfig(r=128 if not a.tiny else 4, lora_alpha=64 if not a.tiny else 2,
                                     init_lora_weights=True, target_modules=["to_q", "to_k", "to_v", "to_out.0"]))
        params = [q for q in model.parameters() if q.requires_grad]
        for q in params:
            q.data = q.data.float()  # fp32 adapters + optimizer, as diffusers' scripts cast them
    else:
        params = list(model.parameters())  # fp32 master weights under bf16 autocast
    model.enable_gradient_checkpointing()
    model.train()
    optimizer = torch.optim.AdamW(params, lr=1e-4, betas=(0.9, 0.95), weight_decay=1e-4)
    text = torch.randn(1, c.max_text_seq_length, c.text_embed_dim, device=device, dtype=dtype)
    rope = rotary(model, frames, height, width, device)
    times = []
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    for _ in range(a.steps):
        start = time.perf_counter()
        x = torch.randn(1, frames, c.in_channels, height, width, device=device, dtype=dtype)
        t = torch.randint(0, 1000, (1,), device=device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=not a.tiny):
            out = model(hidden_states=x, encoder_hidden_states=text, timestep=t, image_rotary_emb=rope,
                        return_dict=False)[0]
        loss = out.float().square().mean()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    if device.type == "cuda":
        peak = torch.cuda.max_memory_reserved(device)
    else:  # peak RSS, as the trainer's CPU figure (ru_maxrss is in KiB on Linux)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps({"impl": "diffusers", "mode": a.mode, "median_step_s": statistics.median(times[1:] or times),
                      "peak_reserved_gb": None if peak is None else peak / 1e9,
                      "peak_allocated_gb": torch.cuda.max_memory_allocated(device) / 1e9 if device.type == "cuda" else None}))


if __name__ == "__main__":
    main()
