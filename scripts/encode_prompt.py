#!/usr/bin/env python3
"""Writes the text embedding file `trainer` reads (`--text-embedding`, `[model] text_embedding`).

Usage:
  encode_prompt.py --model COGVIDEOX_DIR --out FILE [--prompt TEXT] [--max-length 226]
                   [--dtype bf16|fp32] [--device cpu|cuda]
  encode_prompt.py --text-encoder DIR --tokenizer DIR --out FILE ...

COGVIDEOX_DIR is a CogVideoX pipeline folder (CogVideoX-5B-I2V's: `text_encoder/` holds T5-XXL's
encoder, `tokenizer/` its SentencePiece tokenizer). The prompt is encoded the way CogVideoX
pipelines (and the public CogNVS pipeline) encode it: T5Tokenizer with padding to `max_length`
(226), truncation and the end-of-sequence token, no attention mask, T5EncoderModel's last hidden
state. CogNVS was trained and is sampled with the empty prompt (the default): its embedding is not
zeros but the end-of-sequence token and padding run through T5.

The file holds `encoder_hidden_states` [max_length, d_model] in the dtype it was computed in
(default bf16, the public pipeline's `torch_dtype`), with the prompt and settings as metadata.
Needs torch, transformers and sentencepiece (the project venv, `scripts/setup.sh`). Encoding with
T5-XXL takes about 10 GB of memory in bf16; on a CPU, a few minutes.
"""

import argparse
import json
from pathlib import Path

import torch
from safetensors.torch import save_file
from transformers import T5EncoderModel, T5Tokenizer

# CogVideoX's text length (`max_text_seq_length` of its transformers).
MAX_LENGTH = 226


def encode(tokenizer, text_encoder, prompt, max_length, device):
    """The prompt's T5 encoding [max_length, d_model], as CogVideoX pipelines compute it."""
    tokens = tokenizer(prompt, padding="max_length", max_length=max_length, truncation=True,
                       add_special_tokens=True, return_tensors="pt")
    with torch.no_grad():
        hidden = text_encoder(tokens.input_ids.to(device))[0]
    return hidden[0]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--model", type=Path, help="CogVideoX pipeline folder (text_encoder/, tokenizer/)")
    parser.add_argument("--text-encoder", type=Path, help="T5 encoder folder [default: MODEL/text_encoder]")
    parser.add_argument("--tokenizer", type=Path, help="T5 tokenizer folder [default: MODEL/tokenizer]")
    parser.add_argument("--prompt", default="", help="the prompt [default: the empty prompt, as CogNVS]")
    parser.add_argument("--max-length", type=int, default=MAX_LENGTH)
    parser.add_argument("--dtype", choices=["bf16", "fp32"], default="bf16")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    encoder_dir = args.text_encoder or (args.model / "text_encoder" if args.model else None)
    tokenizer_dir = args.tokenizer or (args.model / "tokenizer" if args.model else None)
    if encoder_dir is None or tokenizer_dir is None:
        parser.error("give --model, or both --text-encoder and --tokenizer")
    for name, folder in (("text encoder", encoder_dir), ("tokenizer", tokenizer_dir)):
        if not folder.is_dir():
            parser.error(f"{name} folder {folder} does not exist")
    dtype = torch.bfloat16 if args.dtype == "bf16" else torch.float32
    tokenizer = T5Tokenizer.from_pretrained(tokenizer_dir)
    text_encoder = T5EncoderModel.from_pretrained(encoder_dir, torch_dtype=dtype).to(args.device).eval()
    hidden = encode(tokenizer, text_encoder, args.prompt, args.max_length, args.device)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    metadata = {"prompt": args.prompt, "max_length": str(args.max_length), "dtype": args.dtype,
                "text_encoder": str(encoder_dir), "tokenizer": str(tokenizer_dir)}
    save_file({"encoder_hidden_states": hidden.to(dtype).cpu().contiguous()}, str(args.out), metadata=metadata)
    print(json.dumps({"out": str(args.out), "shape": list(hidden.shape), **metadata}))


if __name__ == "__main__":
    main()
