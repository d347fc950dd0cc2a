#!/usr/bin/env python3
"""LoRA files on Wan through diffusers + peft, for the trainer's Wan LoRA tests.

Usage: goldens_wan_lora.py WORK_DIR CASE...

For each CASE (a folder name under WORK_DIR, which the Rust test `trainer/tests/integration/
wan_lora.rs` filled), reads

  WORK_DIR/CASE/base/                   a tiny random WanTransformer3DModel folder (ours)
  WORK_DIR/CASE/pytorch_lora_weights.safetensors   our LoRA file for it
  WORK_DIR/CASE/inputs.safetensors      hidden_states, timestep, encoder_hidden_states
                                        (and encoder_hidden_states_image for I2V)
  WORK_DIR/CASE/lora.json               {"r", "lora_alpha", "target_modules", "use_rslora"} of the
                                        adapter diffusers trains here

and writes

  WORK_DIR/CASE/diffusers_lora/pytorch_lora_weights.safetensors
      a LoRA that peft adds to the same base (`add_adapter`, random weights from a fixed seed)
      saved by `WanPipeline.save_lora_weights` with peft's adapter metadata (alpha, rank), as a
      diffusers Wan LoRA trainer writes it;
  WORK_DIR/CASE/outputs.safetensors
      base:            the base transformer's output
      ours:            the output after `WanPipeline.load_lora_weights(our file)`
      diffusers_lora:  the output with diffusers' own adapter.

Runs on the CPU in fp32 (a few seconds). Requires torch, diffusers and peft (the project venv).
"""

import json
import sys
from pathlib import Path

import torch
from diffusers import WanPipeline, WanTransformer3DModel
from peft import LoraConfig
from peft.utils import get_peft_model_state_dict
from safetensors.torch import load_file, save_file

SEED = 20261207
# Standard deviation of diffusers' adapter weights: far from peft's zero `lora_B`, so that a
# lost scale or a dropped layer changes the output visibly.
ADAPTER_STD = 0.2


def pipeline(base: Path) -> WanPipeline:
    """A WanPipeline holding only the transformer: `load_lora_weights` needs nothing else."""
    transformer = WanTransformer3DModel.from_pretrained(base).eval()
    return WanPipeline(tokenizer=None, text_encoder=None, transformer=transformer, vae=None, scheduler=None)


def forward(transformer: WanTransformer3DModel, inputs: dict) -> torch.Tensor:
    with torch.no_grad():
        return transformer(**inputs, return_dict=False)[0].contiguous()


def case(work: Path) -> None:
    inputs = load_file(work / "inputs.safetensors")
    outputs = {}

    pipe = pipeline(work / "base")
    outputs["base"] = forward(pipe.transformer, inputs)
    pipe.load_lora_weights(work / "pytorch_lora_weights.safetensors")
    outputs["ours"] = forward(pipe.transformer, inputs)

    settings = json.loads((work / "lora.json").read_text())
    config = LoraConfig(
        r=settings["r"],
        lora_alpha=settings["lora_alpha"],
        target_modules=settings["target_modules"],
        use_rslora=settings["use_rslora"],
        init_lora_weights=False,
    )
    transformer = pipeline(work / "base").transformer
    transformer.add_adapter(config)
    g = torch.Generator().manual_seed(SEED)
    with torch.no_grad():
        for name, p in transformer.named_parameters():
            if ".lora_" in name:
                p.copy_(ADAPTER_STD * torch.randn(p.shape, generator=g))
    outputs["diffusers_lora"] = forward(transformer, inputs)
    WanPipeline.save_lora_weights(
        work / "diffusers_lora",
        transformer_lora_layers=get_peft_model_state_dict(transformer),
        transformer_lora_adapter_metadata=config.to_dict(),
    )
    save_file(outputs, work / "outputs.safetensors")


def main() -> None:
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    work = Path(sys.argv[1])
    for name in sys.argv[2:]:
        case(work / name)


if __name__ == "__main__":
    main()
