#!/usr/bin/env python3
"""Reference outputs of diffusers' Wan components, for the trainer's Wan parity tests.

Usage: goldens_wan.py OUT_DIR

Builds tiny random `WanTransformer3DModel`s (fixed seed) with the structures of Wan2.1 T2V,
Wan2.1 I2V (CLIP image tokens through `image_dim` / `added_kv_proj_dim`), Wan2.1 FLF2V (the image
embedder's positional table, `pos_embed_seq_len`) and Wan2.2 TI2V (per-token timesteps), the
flow-matching schedulers Wan samples with (`UniPCMultistepScheduler`,
`FlowMatchEulerDiscreteScheduler`) and tiny `AutoencoderKLWan`s (Wan2.1's, Wan2.2's), runs
diffusers on fixed random inputs and writes what the Rust tests (`trainer/tests/integration/wan.rs`)
compare against:

  OUT_DIR/transformer_t2v/              diffusers' own save_pretrained output
  OUT_DIR/transformer_i2v/              the same, with image cross-attention
  OUT_DIR/transformer_flf2v/            the same, with the image embedder's positional table
  OUT_DIR/transformer_variant/          T2V without cross-attention norm, patches of 2 x 2 x 2
  OUT_DIR/transformer_io.safetensors    inputs and diffusers' outputs (fp32; bf16 upcast)
  OUT_DIR/transformer_shapes.json       {preset: {state-dict key: shape}} of the real models
  OUT_DIR/scheduler_<case>/             each scheduler case's save_config output
  OUT_DIR/scheduler_io.safetensors      schedules, scale_noise/add_noise and whole sampling loops
  OUT_DIR/vae_wan21/, vae_wan22/,       tiny random AutoencoderKLWan folders (Wan2.1's structure;
  OUT_DIR/vae_wan21_2d/                 Wan2.2's residual, patchified one; a spatial-only first
                                        level)
  OUT_DIR/vae_io.safetensors            their encode (posterior mean and log-variance), decode and
                                        the pipelines' latent normalisation
  OUT_DIR/vae_shapes.json               {name: {state-dict key: shape}} of the real VAEs
  OUT_DIR/pipeline_transformer_2/       a second tiny T2V transformer (Wan2.2's low-noise expert)
  OUT_DIR/pipeline_scheduler/           the UniPC config the pipeline cases sample with
  OUT_DIR/pipeline_io.safetensors       `WanPipeline` videos (output_type="np") for a seed: with
                                        classifier-free guidance, two experts, per-token timesteps;
                                        and `WanImageToVideoPipeline`'s for an image and CLIP tokens
  OUT_DIR/objective_transformer/        a tiny T2V transformer taking the CogNVS channels (noisy +
                                        mask + condition latents: `tiny_cognvs()`)
  OUT_DIR/objective_io.safetensors      the rectified-flow training objective on fixed tensors:
                                        drawn sigmas and timesteps, noisy latents, target, loss

Nothing here is committed; the tests run it into a temporary folder (a few seconds on a CPU).
Requires torch and diffusers (the project venv, `scripts/setup.sh`).
"""

import json
import sys
from pathlib import Path

import torch
from safetensors.torch import save_file
from diffusers.training_utils import compute_loss_weighting_for_sd3
from diffusers import (
    AutoencoderKLWan,
    FlowMatchEulerDiscreteScheduler,
    UniPCMultistepScheduler,
    WanImageToVideoPipeline,
    WanPipeline,
    WanTransformer3DModel,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from goldens_vae_scheduler import randomize_  # noqa: E402

SEED = 20261207

# diffusers' WanAttnProcessor splits the image tokens off the front of the cross-attention context
# by assuming 512 text tokens (umT5's padded length); image-conditioned goldens use that length.
TEXT_CONTEXT_LENGTH = 512

# Must equal the Rust `WanTransformer3DModelConfig::tiny_t2v()` preset: the Wan2.1 T2V structure
# at small widths (head_dim 16 splits into 8 temporal and 4 + 4 spatial rotary channels).
TINY_T2V = dict(
    patch_size=[1, 2, 2],
    num_attention_heads=2,
    attention_head_dim=16,
    in_channels=4,
    out_channels=4,
    text_dim=16,
    freq_dim=32,
    ffn_dim=48,
    num_layers=2,
    cross_attn_norm=True,
    qk_norm="rms_norm_across_heads",
    eps=1e-6,
    image_dim=None,
    added_kv_proj_dim=None,
    rope_max_seq_len=32,
    pos_embed_seq_len=None,
)

# Must equal `WanTransformer3DModelConfig::tiny_i2v()`: Wan2.1 I2V's structure (noisy latents +
# mask + condition latents in, CLIP tokens through the added key/value projections).
TINY_I2V = dict(TINY_T2V, in_channels=12, image_dim=24, added_kv_proj_dim=32)

# Wan2.1 FLF2V: the image embedder adds a positional table over both frames' CLIP tokens.
TINY_FLF2V = dict(TINY_I2V, pos_embed_seq_len=2 * 5)

# Real configs (their transformer/config.json on the Hugging Face hub, Wan-AI/*-Diffusers).
WAN21_T2V_1_3B = dict(
    patch_size=[1, 2, 2], num_attention_heads=12, attention_head_dim=128, in_channels=16, out_channels=16,
    text_dim=4096, freq_dim=256, ffn_dim=8960, num_layers=30, cross_attn_norm=True, eps=1e-6,
)
WAN21_I2V_14B = dict(
    patch_size=[1, 2, 2], num_attention_heads=40, attention_head_dim=128, in_channels=36, out_channels=16,
    text_dim=4096, freq_dim=256, ffn_dim=13824, num_layers=40, cross_attn_norm=True, eps=1e-6,
    image_dim=1280, added_kv_proj_dim=5120,
)
WAN22_TI2V_5B = dict(
    patch_size=[1, 2, 2], num_attention_heads=24, attention_head_dim=128, in_channels=48, out_channels=48,
    text_dim=4096, freq_dim=256, ffn_dim=14336, num_layers=30, cross_attn_norm=True, eps=1e-6,
)


def randomized(config: dict, g: torch.Generator) -> WanTransformer3DModel:
    model = WanTransformer3DModel(**config).eval()
    randomize_(model, g)
    with torch.no_grad():
        for name, p in model.named_parameters():
            # The image embedder's positional table starts at zero; make it matter.
            if name.endswith("pos_embed"):
                p.copy_(0.1 * torch.randn(p.shape, generator=g))
    return model


def run(model, **inputs):
    with torch.no_grad():
        return model(**inputs, return_dict=False)[0]


def transformer_goldens(out: Path) -> None:
    g = torch.Generator().manual_seed(SEED)
    tensors = {}

    def case(name: str, model, **inputs):
        for key, value in inputs.items():
            tensors[f"{name}.{key}"] = value.clone()
        tensors[f"{name}.sample"] = run(model, **inputs)

    t2v = randomized(TINY_T2V, g)
    t2v.save_pretrained(out / "transformer_t2v", safe_serialization=True)
    c = TINY_T2V
    # Batch 2, 3 latent frames of 6x8 (3x4 patches), fractional and integer timesteps.
    x = torch.randn((2, c["in_channels"], 3, 6, 8), generator=g)
    text = torch.randn((2, 7, c["text_dim"]), generator=g)
    case("t2v", t2v, hidden_states=x, timestep=torch.tensor([999.0, 17.5]), encoder_hidden_states=text)
    # Wan2.2 TI2V's per-token timesteps (`expand_timesteps`): [B, tokens], the first latent frame's
    # tokens at 0 (the clean image), the rest at the step's timestep.
    tokens = 3 * (6 // 2) * (8 // 2)
    per_token = torch.full((2, tokens), 640.0)
    per_token[:, : tokens // 3] = 0.0
    per_token[1] = 250.0 * (per_token[1] > 0)
    case("ti2v", t2v, hidden_states=x, timestep=per_token, encoder_hidden_states=text)

    # No cross-attention norm and temporal patches of 2 (config branches no released model takes).
    variant = randomized(dict(TINY_T2V, cross_attn_norm=False, patch_size=[2, 2, 2]), g)
    variant.save_pretrained(out / "transformer_variant", safe_serialization=True)
    x = torch.randn((1, TINY_T2V["in_channels"], 4, 4, 6), generator=g)
    case("variant", variant, hidden_states=x, timestep=torch.tensor([500]), encoder_hidden_states=text[:1].clone())

    i2v = randomized(TINY_I2V, g)
    i2v.save_pretrained(out / "transformer_i2v", safe_serialization=True)
    c = TINY_I2V
    x = torch.randn((1, c["in_channels"], 2, 4, 6), generator=g)
    text = torch.randn((1, TEXT_CONTEXT_LENGTH, c["text_dim"]), generator=g)
    image = torch.randn((1, 5, c["image_dim"]), generator=g)
    case(
        "i2v", i2v, hidden_states=x, timestep=torch.tensor([333]), encoder_hidden_states=text,
        encoder_hidden_states_image=image,
    )

    # bf16 as diffusers loads it: `_keep_in_fp32_modules` (time embedder, modulation tables, norms)
    # stay fp32, the rest is bf16; inputs bf16, the output stored upcast.
    i2v_bf16 = WanTransformer3DModel.from_pretrained(out / "transformer_i2v", torch_dtype=torch.bfloat16).eval()
    tensors["i2v_bf16.sample"] = run(
        i2v_bf16, hidden_states=x.bfloat16(), timestep=torch.tensor([333]), encoder_hidden_states=text.bfloat16(),
        encoder_hidden_states_image=image.bfloat16(),
    ).float()

    flf2v = randomized(TINY_FLF2V, g)
    flf2v.save_pretrained(out / "transformer_flf2v", safe_serialization=True)
    # The first and last frames' CLIP tokens come as a batch of two per sample.
    image = torch.randn((2, 5, c["image_dim"]), generator=g)
    case(
        "flf2v", flf2v, hidden_states=x, timestep=torch.tensor([71]), encoder_hidden_states=text,
        encoder_hidden_states_image=image,
    )

    save_file({k: v.contiguous() for k, v in tensors.items()}, str(out / "transformer_io.safetensors"))

    shapes = {}
    for preset, config in [
        ("wan2.1-t2v-1.3b", WAN21_T2V_1_3B),
        ("wan2.1-i2v-14b", WAN21_I2V_14B),
        ("wan2.2-ti2v-5b", WAN22_TI2V_5B),
    ]:
        with torch.device("meta"):
            real = WanTransformer3DModel(**config)
        shapes[preset] = {k: list(v.shape) for k, v in real.state_dict().items()}
    (out / "transformer_shapes.json").write_text(json.dumps(shapes, indent=1, sort_keys=True))


# The scheduler_config.json of Wan-AI/Wan2.1-T2V-1.3B-Diffusers (flow_shift 3: 480p).
UNIPC_WAN = dict(
    beta_end=0.02, beta_schedule="linear", beta_start=0.0001, disable_corrector=[], dynamic_thresholding_ratio=0.995,
    final_sigmas_type="zero", flow_shift=3.0, lower_order_final=True, num_train_timesteps=1000, predict_x0=True,
    prediction_type="flow_prediction", rescale_betas_zero_snr=False, sample_max_value=1.0, solver_order=2,
    solver_p=None, solver_type="bh2", steps_offset=0, thresholding=False, timestep_spacing="linspace",
    trained_betas=None, use_beta_sigmas=False, use_exponential_sigmas=False, use_flow_sigmas=True,
    use_karras_sigmas=False,
)

# (case, class, config, steps, mu): Wan's UniPC; a third-order bh1 variant ending at sigma_min
# with a disabled corrector; data-free epsilon solving with a dynamic linear shift stretched to a
# terminal sigma; the Euler sampler with Wan's training shift, with a dynamic exponential shift and
# Karras respacing, inverted, and stochastic.
SCHEDULER_CASES = [
    ("unipc_wan", UniPCMultistepScheduler, UNIPC_WAN, 12, None),
    (
        "unipc_order3",
        UniPCMultistepScheduler,
        dict(UNIPC_WAN, solver_order=3, solver_type="bh1", final_sigmas_type="sigma_min",
             disable_corrector=[2], flow_shift=5.0),
        9,
        None,
    ),
    (
        "unipc_epsilon",
        UniPCMultistepScheduler,
        dict(UNIPC_WAN, prediction_type="epsilon", predict_x0=False, final_sigmas_type="sigma_min",
             use_dynamic_shifting=True, time_shift_type="linear", shift_terminal=0.1),
        7,
        0.8,
    ),
    ("euler_shift", FlowMatchEulerDiscreteScheduler, dict(shift=5.0), 10, None),
    (
        "euler_dynamic",
        FlowMatchEulerDiscreteScheduler,
        dict(use_dynamic_shifting=True, shift_terminal=0.02, use_karras_sigmas=True),
        8,
        1.3,
    ),
    ("euler_inverted", FlowMatchEulerDiscreteScheduler, dict(shift=3.0, invert_sigmas=True, use_exponential_sigmas=True), 6, None),
    ("euler_stochastic", FlowMatchEulerDiscreteScheduler, dict(shift=3.0, stochastic_sampling=True), 5, None),
]


def scheduler_goldens(out: Path) -> None:
    g = torch.Generator().manual_seed(SEED + 1)
    t = {}
    shape = (1, 4, 3, 2, 3)
    for name, cls, config, steps, mu in SCHEDULER_CASES:
        scheduler = cls(**config)
        scheduler.save_config(out / f"scheduler_{name}")
        scheduler.set_timesteps(steps, mu=mu)
        t[f"{name}.timesteps"] = scheduler.timesteps.clone()
        t[f"{name}.sigmas"] = scheduler.sigmas.clone()
        t[f"{name}.steps"] = torch.tensor([steps])
        if mu is not None:
            t[f"{name}.mu"] = torch.tensor([mu], dtype=torch.float64)

        # The forward process at two of the schedule's timesteps, before stepping.
        x0 = torch.randn((2,) + shape[1:], generator=g)
        noise = torch.randn(x0.shape, generator=g)
        at = scheduler.timesteps[[1, steps - 1]]
        t[f"{name}.noise_timesteps"] = at.clone()
        t[f"{name}.original_samples"] = x0
        t[f"{name}.noise"] = noise
        if cls is UniPCMultistepScheduler:
            t[f"{name}.noisy_samples"] = scheduler.add_noise(x0, noise, at)
        else:
            t[f"{name}.noisy_samples"] = scheduler.scale_noise(x0, at, noise)

        # A whole sampling loop with random "model outputs" (the update rule needs no model). The
        # stochastic Euler step draws its noise from the generator passed in: replayed by a twin.
        sample = torch.randn(shape, generator=g)
        t[f"{name}.initial_sample"] = sample
        step_gen = torch.Generator().manual_seed(SEED + 2)
        twin_gen = torch.Generator().manual_seed(SEED + 2)
        for i, ts in enumerate(scheduler.timesteps):
            model_output = torch.randn(shape, generator=g)
            t[f"{name}.{i}.model_output"] = model_output
            if config.get("stochastic_sampling"):
                t[f"{name}.{i}.step_noise"] = torch.randn(shape, generator=twin_gen)
                sample = scheduler.step(model_output, ts, sample, generator=step_gen, return_dict=False)[0]
            else:
                sample = scheduler.step(model_output, ts, sample, return_dict=False)[0]
            t[f"{name}.{i}.prev_sample"] = sample
    save_file({k: v.contiguous() for k, v in t.items()}, str(out / "scheduler_io.safetensors"))


# Must equal `AutoencoderKLWanConfig::tiny()`: Wan2.1's VAE structure at small widths (3 levels,
# 4x spatial and 4x temporal compression).
TINY_VAE21 = dict(
    base_dim=8, z_dim=4, dim_mult=[1, 2, 2], num_res_blocks=1, temperal_downsample=[True, True],
    latents_mean=[0.1, -0.2, 0.3, 0.0], latents_std=[1.5, 0.8, 1.1, 2.0], scale_factor_spatial=4,
)
# Must equal `AutoencoderKLWanConfig::tiny_residual()`: Wan2.2's residual blocks and 2x2 patches.
TINY_VAE22 = dict(
    TINY_VAE21, decoder_base_dim=16, z_dim=6, latents_mean=[0.0] * 6, latents_std=[1.0] * 6, is_residual=True,
    in_channels=12, out_channels=12, patch_size=2, scale_factor_spatial=8,
)
# Wan-AI/Wan2.2-TI2V-5B-Diffusers vae/config.json's structure (the latent statistics do not change
# any parameter's shape).
WAN22_VAE = dict(
    base_dim=160, decoder_base_dim=256, z_dim=48, is_residual=True, in_channels=12, out_channels=12, patch_size=2,
    scale_factor_spatial=16, latents_mean=[0.0] * 48, latents_std=[1.0] * 48,
)


def vae_goldens(out: Path) -> None:
    g = torch.Generator().manual_seed(SEED + 3)
    t = {}
    # wan21_2d: Wan2.1's first level compresses space only, as the released VAE's does.
    cases = [
        ("wan21", TINY_VAE21, 16, 24),
        ("wan22", TINY_VAE22, 16, 32),
        ("wan21_2d", dict(TINY_VAE21, temperal_downsample=[False, True]), 16, 24),
    ]
    for name, config, height, width in cases:
        vae = AutoencoderKLWan(**config).eval()
        randomize_(vae, g)
        vae.save_pretrained(out / f"vae_{name}", safe_serialization=True)
        with torch.no_grad():
            # 9 frames: the encoder runs chunks of 1, 4, 4 frames with the causal caches carried.
            sample = torch.rand((2, 3, 9, height, width), generator=g) * 2 - 1
            posterior = vae.encode(sample).latent_dist
            t[f"{name}.encode.sample"] = sample
            t[f"{name}.encode.mean"] = posterior.mean
            t[f"{name}.encode.logvar"] = posterior.logvar
            # 3 latent frames, decoded one at a time: 1 + 4 + 4 frames.
            latent = torch.randn((1,) + tuple(posterior.mean.shape[1:]), generator=g)
            t[f"{name}.decode.latent"] = latent
            t[f"{name}.decode.sample"] = vae.decode(latent).sample
            # The pipelines' normalisation of the encoded latent and its inverse before decoding.
            c = vae.config
            mean = torch.tensor(c.latents_mean).view(1, c.z_dim, 1, 1, 1)
            inv_std = 1.0 / torch.tensor(c.latents_std).view(1, c.z_dim, 1, 1, 1)
            t[f"{name}.normalized"] = (posterior.mean - mean) * inv_std
            t[f"{name}.denormalized"] = latent / inv_std + mean
    save_file({k: v.contiguous() for k, v in t.items()}, str(out / "vae_io.safetensors"))

    shapes = {}
    for name, config in [("wan2.1", {}), ("wan2.2", WAN22_VAE)]:
        with torch.device("meta"):
            real = AutoencoderKLWan(**config)
        shapes[name] = {k: list(v.shape) for k, v in real.state_dict().items()}
    (out / "vae_shapes.json").write_text(json.dumps(shapes, indent=1, sort_keys=True))


# Pipeline cases: 9 frames of 16 x 32 (divisible by 16, as `WanPipeline.check_inputs` asks), so
# 3 latent frames of 4 x 8 with the tiny Wan2.1 VAE; 4 UniPC steps; seed of the pipeline's
# generator (a CPU `torch.Generator`, which the Rust side replays with `tch::manual_seed`).
PIPELINE_FRAMES, PIPELINE_HEIGHT, PIPELINE_WIDTH, PIPELINE_STEPS, PIPELINE_SEED = 9, 16, 32, 4, 42
# (name, guidance_scale, guidance_scale_2, boundary_ratio, expand_timesteps): CFG on one expert;
# Wan2.2's two experts switching at 0.8 of the training timesteps (between the 2nd and 3rd of the
# 4 steps: 999, 900 | 750, 500) with their own guidance; TI2V's
# per-token timesteps; no guidance (one forward per step).
PIPELINE_CASES = [
    ("cfg", 3.0, None, None, False),
    ("two_experts", 3.0, 1.5, 0.8, False),
    ("expand_timesteps", 2.0, None, None, True),
    ("no_guidance", 1.0, None, None, False),
]


def pipeline_goldens(out: Path) -> None:
    g = torch.Generator().manual_seed(SEED + 4)
    transformer = WanTransformer3DModel.from_pretrained(out / "transformer_t2v").eval()
    transformer_2 = randomized(TINY_T2V, g)
    transformer_2.save_pretrained(out / "pipeline_transformer_2", safe_serialization=True)
    vae = AutoencoderKLWan.from_pretrained(out / "vae_wan21").eval()
    # Wan2.1's released scheduler (flow prediction, flow sigmas, shift 3) at a small step count.
    scheduler = UniPCMultistepScheduler(prediction_type="flow_prediction", use_flow_sigmas=True, flow_shift=3.0)
    scheduler.save_config(out / "pipeline_scheduler")
    t = {
        "prompt_embeds": torch.randn((1, 7, TINY_T2V["text_dim"]), generator=g),
        "negative_prompt_embeds": torch.randn((1, 7, TINY_T2V["text_dim"]), generator=g),
        "shape": torch.tensor([PIPELINE_FRAMES, PIPELINE_HEIGHT, PIPELINE_WIDTH, PIPELINE_STEPS, PIPELINE_SEED]),
    }
    for name, guidance, guidance_2, boundary, expand in PIPELINE_CASES:
        pipe = WanPipeline(
            tokenizer=None, text_encoder=None, vae=vae, scheduler=scheduler, transformer=transformer,
            transformer_2=transformer_2 if boundary is not None else None, boundary_ratio=boundary,
            expand_timesteps=expand,
        )
        pipe.set_progress_bar_config(disable=True)
        extra = {} if guidance_2 is None else {"guidance_scale_2": guidance_2}
        video = pipe(
            prompt_embeds=t["prompt_embeds"], negative_prompt_embeds=t["negative_prompt_embeds"],
            height=PIPELINE_HEIGHT, width=PIPELINE_WIDTH, num_frames=PIPELINE_FRAMES,
            num_inference_steps=PIPELINE_STEPS, guidance_scale=guidance,
            generator=torch.Generator().manual_seed(PIPELINE_SEED), output_type="np", **extra,
        ).frames
        # [1, F, H, W, 3] in [0, 1].
        t[f"{name}.video"] = torch.from_numpy(video).float()

    # Image to video with the tiny Wan2.1 I2V transformer: the image's latent and the first-frame
    # mask enter beside the noisy latents, CLIP tokens through the image cross-attention. The
    # CLIP embedding is given (the toolkit precomputes it by script): diffusers refuses `image`
    # beside `image_embeds`, so its `encode_image` is replaced by one returning them.
    i2v = WanTransformer3DModel.from_pretrained(out / "transformer_i2v").eval()
    image = torch.rand((1, 3, PIPELINE_HEIGHT, PIPELINE_WIDTH), generator=g) * 2 - 1
    image_embeds = torch.randn((1, 5, TINY_I2V["image_dim"]), generator=g)
    text = torch.randn((1, TEXT_CONTEXT_LENGTH, TINY_I2V["text_dim"]), generator=g)
    negative = torch.randn((1, TEXT_CONTEXT_LENGTH, TINY_I2V["text_dim"]), generator=g)
    pipe = WanImageToVideoPipeline(
        tokenizer=None, text_encoder=None, vae=vae, scheduler=scheduler, transformer=i2v
    )
    pipe.set_progress_bar_config(disable=True)
    pipe.encode_image = lambda image, device: image_embeds
    # A tensor in [-1, 1] at the output size reaches the VAE unchanged (no resize, no rescale).
    assert torch.equal(pipe.video_processor.preprocess(image, height=PIPELINE_HEIGHT, width=PIPELINE_WIDTH), image)
    video = pipe(
        image=image, prompt_embeds=text, negative_prompt_embeds=negative, height=PIPELINE_HEIGHT,
        width=PIPELINE_WIDTH, num_frames=PIPELINE_FRAMES, num_inference_steps=PIPELINE_STEPS, guidance_scale=3.0,
        generator=torch.Generator().manual_seed(PIPELINE_SEED), output_type="np",
    ).frames
    t.update({
        "i2v.image": image, "i2v.image_embeds": image_embeds, "i2v.prompt_embeds": text,
        "i2v.negative_prompt_embeds": negative, "i2v.video": torch.from_numpy(video).float(),
    })
    save_file({k: v.contiguous() for k, v in t.items()}, str(out / "pipeline_io.safetensors"))


# Must equal `WanTransformer3DModelConfig::tiny_cognvs()`: the T2V structure taking the CogNVS
# conditioning (4 noisy + 4 mask + 4 condition latent channels), no image tokens.
TINY_COGNVS = dict(TINY_T2V, in_channels=12)
# The static flow shift a Wan run trains with by default (the Rust `WAN_FLOW_SHIFT`).
OBJECTIVE_SHIFT = 3.0


def objective_goldens(out: Path) -> None:
    """The rectified-flow objective as diffusers-based trainers compute it for Wan (finetrainers'
    `prepare_sigmas` with uniform weighting, `flow_match_xt`, `prepare_target`, and
    `compute_loss_weighting_for_sd3`), written out from their formulas on fixed draws `u`."""
    g = torch.Generator().manual_seed(SEED + 5)
    model = randomized(TINY_COGNVS, g)
    model.save_pretrained(str(out / "objective_transformer"))
    b, f, h, w = 3, 2, 4, 6
    x0 = torch.randn(b, 4, f, h, w, generator=g)
    condition = torch.randn(b, 8, f, h, w, generator=g)
    text = torch.randn(b, 7, TINY_T2V["text_dim"], generator=g)
    noise = torch.randn(b, 4, f, h, w, generator=g)
    # The ends of [0, 1) and an interior draw.
    u = torch.tensor([0.0, 0.4567, 0.99995])
    scheduler = FlowMatchEulerDiscreteScheduler(shift=OBJECTIVE_SHIFT)
    n = scheduler.config.num_train_timesteps
    indices = (u * n).long()
    sigmas = scheduler.sigmas[indices]
    timesteps = (sigmas * 1000.0).long()
    sigma = sigmas.view(-1, 1, 1, 1, 1)
    noisy = (1.0 - sigma) * x0 + sigma * noise
    target = noise - x0
    pred = run(model, hidden_states=torch.cat([noisy, condition], dim=1), timestep=timesteps, encoder_hidden_states=text)
    weights = compute_loss_weighting_for_sd3(weighting_scheme="none", sigmas=sigma)
    loss = (weights.float() * (pred.float() - target.float()) ** 2).mean(dim=list(range(1, pred.ndim))).mean()
    save_file({k: v.contiguous() for k, v in {
        "x0": x0, "condition": condition, "text": text, "noise": noise, "u": u, "sigmas": sigmas,
        "timesteps": timesteps, "noisy": noisy, "target": target, "pred": pred, "loss": loss.reshape(1),
    }.items()}, str(out / "objective_io.safetensors"))


def main() -> None:
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(SEED)
    transformer_goldens(out)
    scheduler_goldens(out)
    vae_goldens(out)
    pipeline_goldens(out)
    objective_goldens(out)


if __name__ == "__main__":
    main()
