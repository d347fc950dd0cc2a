#!/usr/bin/env python3
"""Reference outputs of diffusers' CogVideoXTransformer3DModel, for the trainer's parity tests.

Usage:
  goldens_transformer.py OUT_DIR
  goldens_transformer.py --reload MODEL_DIR INPUTS.safetensors OUT.safetensors [LORA.safetensors]
  goldens_transformer.py --reload-each INPUTS.safetensors MODEL_DIR OUT.safetensors [MODEL_DIR OUT ...]

The first form builds tiny random transformers (fixed seed) with the structure of CogNVS (learned
+ 3D rotary positions) and of CogVideoX-2B (sin-cos positions), runs diffusers on fixed random
inputs the way the CogNVS trainer calls it (rotary table from `get_3d_rotary_pos_embed` with
grid_type="slice" over the latent patch grid) and writes what the Rust tests
(`trainer/tests/integration/transformer.rs`) compare against:

  OUT_DIR/cognvs_tiny/                  diffusers' own save_pretrained output (single file)
  OUT_DIR/cognvs_tiny_sharded/          the same weights saved in shards with an index
  OUT_DIR/cogvideox2b_tiny/             a tiny sin-cos-position model
  OUT_DIR/transformer_io.safetensors    inputs and diffusers' outputs (fp32, and bf16 upcast)
  OUT_DIR/cognvs_5b_shapes.json         {state-dict key: shape} of the real CogNVS transformer

The second form loads a model folder written by the Rust trainer with diffusers' from_pretrained,
runs it on the inputs (`hidden_states`, `encoder_hidden_states`, `timestep`) and writes `sample`,
so a test can prove our checkpoints load in diffusers and compute the same thing. With a LoRA
file (our `pytorch_lora_weights.safetensors`), diffusers' own `load_lora_adapter` (through peft)
attaches it to the loaded model first, as `CogVideoXPipeline.load_lora_weights` does. The third
form does the second for several model folders on the same inputs in one process (one import of
torch and diffusers instead of one per folder).

Nothing here is committed; the tests run it into a temporary folder (a few seconds on a CPU).
Requires torch and diffusers (the project venv, `scripts/setup.sh`).
"""

import json
import sys
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file
from diffusers import CogVideoXTransformer3DModel
from diffusers.models.embeddings import get_3d_rotary_pos_embed

sys.path.insert(0, str(Path(__file__).resolve().parent))
from goldens_vae_scheduler import randomize_  # noqa: E402

SEED = 20261124

# Must equal the Rust `CogVideoXTransformer3DModelConfig::tiny()` preset: the CogNVS structure
# (32 -> 16 latent channels, learned + rotary positions) at small widths.
TINY_COGNVS = dict(
    num_attention_heads=2,
    attention_head_dim=16,
    in_channels=32,
    out_channels=16,
    time_embed_dim=32,
    text_embed_dim=16,
    num_layers=2,
    sample_width=10,
    sample_height=8,
    sample_frames=9,
    max_text_seq_length=8,
    use_rotary_positional_embeddings=True,
    use_learned_positional_embeddings=True,
)

# The CogVideoX-2B structure (sin-cos positions, no rotary) at small widths.
TINY_2B = dict(TINY_COGNVS, in_channels=16, use_rotary_positional_embeddings=False, use_learned_positional_embeddings=False)

# The released CogNVS transformer config (the checkpoint's config.json).
COGNVS_5B = dict(
    num_attention_heads=48,
    in_channels=32,
    num_layers=42,
    use_rotary_positional_embeddings=True,
    use_learned_positional_embeddings=True,
)


def rotary(model: CogVideoXTransformer3DModel, frames: int, height: int, width: int):
    """The CogNVS trainer's rotary table: slice grid, positions 0..n-1 over the latent patch grid."""
    p = model.config.patch_size
    grid = (height // p, width // p)
    return get_3d_rotary_pos_embed(
        embed_dim=model.config.attention_head_dim,
        crops_coords=None,
        grid_size=grid,
        temporal_size=frames,
        grid_type="slice",
        max_size=grid,
    )


def run(model, hidden_states, encoder_hidden_states, timestep):
    _, frames, _, height, width = hidden_states.shape
    rope = rotary(model, frames, height, width) if model.config.use_rotary_positional_embeddings else None
    with torch.no_grad():
        return model(
            hidden_states=hidden_states,
            encoder_hidden_states=encoder_hidden_states,
            timestep=timestep,
            image_rotary_emb=rope,
            return_dict=False,
        )[0]


def randomized(config: dict, g: torch.Generator) -> CogVideoXTransformer3DModel:
    model = CogVideoXTransformer3DModel(**config).eval()
    randomize_(model, g)
    with torch.no_grad():
        for name, buf in model.named_buffers():
            # The learned positional table: its text rows start at zero; make them matter.
            buf.add_(0.1 * torch.randn(buf.shape, generator=g))
    return model


def goldens(out: Path) -> None:
    g = torch.Generator().manual_seed(SEED)
    tensors = {}

    cognvs = randomized(TINY_COGNVS, g)
    cognvs.save_pretrained(out / "cognvs_tiny", safe_serialization=True)
    cognvs.save_pretrained(out / "cognvs_tiny_sharded", safe_serialization=True, max_shard_size="40KB")
    c = TINY_COGNVS
    latent_frames = (c["sample_frames"] - 1) // 4 + 1
    # Batch of 2, the stored table's frame count (learned positions are used).
    x = torch.randn((2, latent_frames, c["in_channels"], c["sample_height"], c["sample_width"]), generator=g)
    text = torch.randn((2, c["max_text_seq_length"], c["text_embed_dim"]), generator=g)
    t = torch.tensor([999, 17], dtype=torch.int64)
    tensors.update({"cognvs.hidden_states": x, "cognvs.encoder_hidden_states": text, "cognvs.timestep": t})
    tensors["cognvs.sample"] = run(cognvs, x, text, t)
    # Two latent frames: diffusers replaces the learned table by a computed sin-cos one.
    x2 = torch.randn((1, 2, c["in_channels"], c["sample_height"], c["sample_width"]), generator=g)
    t2 = torch.tensor([250.5])
    tensors.update({"cognvs_f2.hidden_states": x2, "cognvs_f2.encoder_hidden_states": text[:1].clone(), "cognvs_f2.timestep": t2})
    tensors["cognvs_f2.sample"] = run(cognvs, x2, text[:1], t2)
    # bf16 weights and inputs (outputs stored upcast to fp32).
    bf16 = randomized(TINY_COGNVS, torch.Generator().manual_seed(SEED))
    bf16.load_state_dict(cognvs.state_dict())
    bf16 = bf16.to(torch.bfloat16)  # all of it: the Rust side has no fp32-kept modules either
    tensors["cognvs_bf16.sample"] = run(bf16, x.bfloat16(), text.bfloat16(), t).float()

    small = randomized(TINY_2B, g)
    small.save_pretrained(out / "cogvideox2b_tiny", safe_serialization=True)
    c = TINY_2B
    x = torch.randn((1, 3, c["in_channels"], 6, 8), generator=g)
    text = torch.randn((1, c["max_text_seq_length"], c["text_embed_dim"]), generator=g)
    t = torch.tensor([421])
    tensors.update({"cogvideox2b.hidden_states": x, "cogvideox2b.encoder_hidden_states": text, "cogvideox2b.timestep": t})
    tensors["cogvideox2b.sample"] = run(small, x, text, t)

    save_file({k: v.contiguous() for k, v in tensors.items()}, str(out / "transformer_io.safetensors"))

    with torch.device("meta"):
        real = CogVideoXTransformer3DModel(**COGNVS_5B)
    shapes = {k: list(v.shape) for k, v in real.state_dict().items()}
    (out / "cognvs_5b_shapes.json").write_text(json.dumps(shapes, indent=1, sort_keys=True))


def reload(model_dir: Path, inputs: Path, out: Path, lora: Path | None = None) -> None:
    model = CogVideoXTransformer3DModel.from_pretrained(model_dir).eval().float()
    if lora is not None:
        model.load_lora_adapter(str(lora), prefix="transformer")
    x = load_file(str(inputs))
    sample = run(model, x["hidden_states"].float(), x["encoder_hidden_states"].float(), x["timestep"])
    save_file({"sample": sample.contiguous()}, str(out))


def main() -> None:
    torch.set_num_threads(max(1, torch.get_num_threads()))
    if len(sys.argv) in (5, 6) and sys.argv[1] == "--reload":
        lora = Path(sys.argv[5]) if len(sys.argv) == 6 else None
        reload(Path(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]), lora)
    elif len(sys.argv) >= 5 and len(sys.argv) % 2 == 1 and sys.argv[1] == "--reload-each":
        inputs = Path(sys.argv[2])
        for model_dir, out in zip(sys.argv[3::2], sys.argv[4::2]):
            reload(Path(model_dir), inputs, Path(out))
    elif len(sys.argv) == 2:
        out = Path(sys.argv[1])
        out.mkdir(parents=True, exist_ok=True)
        goldens(out)
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
