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

Both folders are checked before anything is encoded: the tokenizer must have its vocabulary file,
the encoder its config.json (model_type t5) and every weight, and the two must be one model's (the
encoder's vocab_size is the tokenizer's size rounded up to T5's padding); anything else exits
non-zero naming the folder and what is missing, never writing an embedding.
"""

import argparse
import json
import sys
from pathlib import Path

# CogVideoX's text length (`max_text_seq_length` of its transformers).
MAX_LENGTH = 226
# The vocabulary files T5Tokenizer reads (SentencePiece's model, or the fast tokenizer's JSON): a
# tokenizer folder without one loads as a tokenizer that knows no word.
TOKENIZER_FILES = ("spiece.model", "tokenizer.json")
# The weight files `from_pretrained` reads from an encoder folder.
ENCODER_WEIGHTS = ("model.safetensors", "model.safetensors.index.json", "pytorch_model.bin",
                   "pytorch_model.bin.index.json")
# T5 checkpoints round their embedding table up to a multiple of 128 rows (T5-XXL: 32 128 rows for
# its tokenizer's 32 100 tokens): the encoder of a tokenizer has at least as many rows and fewer
# than this many more.
VOCAB_PADDING = 128
# The model type of CogVideoX's text encoder (`config.json` `model_type`).
MODEL_TYPE = "t5"


def missing_files(encoder_dir, tokenizer_dir):
    """What the two folders lack before anything is loaded, as messages naming the folder."""
    problems = []
    if not any((tokenizer_dir / name).is_file() for name in TOKENIZER_FILES):
        problems.append(f"tokenizer folder {tokenizer_dir} has no vocabulary ({' or '.join(TOKENIZER_FILES)})")
    config = encoder_dir / "config.json"
    if not config.is_file():
        problems.append(f"text encoder folder {encoder_dir} has no config.json")
    else:
        try:
            model_type = json.loads(config.read_text()).get("model_type")
        except (ValueError, AttributeError) as e:
            model_type = f"unreadable ({e})"
        if model_type != MODEL_TYPE:
            problems.append(f"{config}: model_type is {model_type!r}, expected {MODEL_TYPE!r} (T5's encoder)")
    if not any((encoder_dir / name).is_file() for name in ENCODER_WEIGHTS):
        problems.append(f"text encoder folder {encoder_dir} has no weights ({', '.join(ENCODER_WEIGHTS)})")
    return problems


def mismatches(tokenizer, text_encoder, loading_info, encoder_dir, tokenizer_dir):
    """What makes the loaded pair unusable together, as messages naming the folders."""
    problems = []
    missing = loading_info.get("missing_keys") or []
    if missing:
        problems.append(f"text encoder folder {encoder_dir}: {len(missing)} weights missing (e.g. {sorted(missing)[0]}); "
                        f"they would be random")
    mismatched = loading_info.get("mismatched_keys") or []
    if mismatched:
        problems.append(f"text encoder folder {encoder_dir}: {len(mismatched)} weights of another shape "
                        f"(e.g. {sorted(mismatched)[0]})")
    tokens, rows = len(tokenizer), text_encoder.config.vocab_size
    if not rows - VOCAB_PADDING < tokens <= rows:
        problems.append(f"tokenizer {tokenizer_dir} has {tokens} tokens but text encoder {encoder_dir}/config.json "
                        f"has vocab_size {rows}: they are not one model's")
    return problems


def refuse(problems):
    """Exits with every problem on stderr, naming what is missing."""
    sys.exit("encode_prompt.py: " + "; ".join(problems))


def encode(tokenizer, text_encoder, prompt, max_length, device):
    """The prompt's T5 encoding [max_length, d_model], as CogVideoX pipelines compute it."""
    import torch

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
    parser.add_argument("--device", help="cpu, cuda or cuda:N [default: cuda when available]")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    encoder_dir = args.text_encoder or (args.model / "text_encoder" if args.model else None)
    tokenizer_dir = args.tokenizer or (args.model / "tokenizer" if args.model else None)
    if encoder_dir is None or tokenizer_dir is None:
        parser.error("give --model, or both --text-encoder and --tokenizer")
    for name, folder in (("text encoder", encoder_dir), ("tokenizer", tokenizer_dir)):
        if not folder.is_dir():
            parser.error(f"{name} folder {folder} does not exist")
    if args.max_length <= 0:
        parser.error(f"--max-length must be positive, got {args.max_length}")
    problems = missing_files(encoder_dir, tokenizer_dir)
    if problems:
        refuse(problems)
    # Loaded only now, so that missing files are named within a second, not after torch's import.
    import torch
    from safetensors.torch import save_file
    from transformers import T5EncoderModel, T5Tokenizer

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    dtype = torch.bfloat16 if args.dtype == "bf16" else torch.float32
    tokenizer = T5Tokenizer.from_pretrained(tokenizer_dir)
    text_encoder, loading_info = T5EncoderModel.from_pretrained(encoder_dir, torch_dtype=dtype,
                                                                output_loading_info=True)
    problems = mismatches(tokenizer, text_encoder, loading_info, encoder_dir, tokenizer_dir)
    if problems:
        refuse(problems)
    text_encoder = text_encoder.to(device).eval()
    hidden = encode(tokenizer, text_encoder, args.prompt, args.max_length, device)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    metadata = {"prompt": args.prompt, "max_length": str(args.max_length), "dtype": args.dtype,
                "text_encoder": str(encoder_dir), "tokenizer": str(tokenizer_dir)}
    save_file({"encoder_hidden_states": hidden.to(dtype).cpu().contiguous()}, str(args.out), metadata=metadata)
    print(json.dumps({"out": str(args.out), "shape": list(hidden.shape), **metadata}))


if __name__ == "__main__":
    main()
