#!/usr/bin/env python3
"""A tiny CogVideoX text stack and its reference prompt embeddings, for `encode_prompt.py`'s test.

Usage: goldens_text_embedding.py OUT_DIR

Writes OUT_DIR/text_encoder/ (a random T5EncoderModel of a few small layers, save_pretrained) and
OUT_DIR/tokenizer/ (a SentencePiece unigram model trained here on a few sentences, in the file
layout of CogVideoX's tokenizer folder: spiece.model and tokenizer_config.json), then encodes the
prompts below with diffusers' own CogVideoX prompt encoder (`CogVideoXPipeline._get_t5_prompt_embeds`
on these two components) into OUT_DIR/reference.safetensors, one tensor per prompt
(`prompt_0`, `prompt_1`, ...: [226, d_model]) and OUT_DIR/prompts.json. Nothing is committed.
"""

import json
import sys
import types
from pathlib import Path

import sentencepiece
import torch
from diffusers import CogVideoXPipeline
from safetensors.torch import save_file
from transformers import T5Config, T5EncoderModel, T5Tokenizer

PROMPTS = ["", "a dog runs after a red ball in the park", " ".join(["the camera orbits the scene"] * 60)]

CORPUS = [
    "a camera orbits around a dog playing in the park",
    "the quick brown fox jumps over the lazy dog",
    "novel views of a dynamic scene with a red ball",
]


def main():
    out = Path(sys.argv[1])
    tokenizer_dir = out / "tokenizer"
    tokenizer_dir.mkdir(parents=True, exist_ok=True)
    corpus = out / "corpus.txt"
    corpus.write_text("\n".join(CORPUS * 50))
    # T5's special ids: pad 0, </s> 1, <unk> 2; no <s>.
    sentencepiece.SentencePieceTrainer.train(
        input=str(corpus), model_prefix=str(tokenizer_dir / "spiece"), vocab_size=40, model_type="unigram",
        pad_id=0, eos_id=1, unk_id=2, bos_id=-1, pad_piece="<pad>", eos_piece="</s>", unk_piece="<unk>",
        minloglevel=2)
    (tokenizer_dir / "spiece.vocab").unlink()
    (tokenizer_dir / "tokenizer_config.json").write_text(
        json.dumps({"tokenizer_class": "T5Tokenizer", "model_max_length": 226, "extra_ids": 0}))
    torch.manual_seed(20261204)
    config = T5Config(vocab_size=40, d_model=32, d_kv=8, d_ff=48, num_layers=2, num_heads=4,
                      relative_attention_num_buckets=8, feed_forward_proj="gated-gelu", is_encoder_decoder=False)
    T5EncoderModel(config).eval().save_pretrained(out / "text_encoder")

    components = types.SimpleNamespace(
        tokenizer=T5Tokenizer.from_pretrained(tokenizer_dir),
        text_encoder=T5EncoderModel.from_pretrained(out / "text_encoder").eval(),
    )
    reference = {}
    with torch.no_grad():
        for i, prompt in enumerate(PROMPTS):
            embeds = CogVideoXPipeline._get_t5_prompt_embeds(components, prompt=prompt, max_sequence_length=226,
                                                             device=torch.device("cpu"), dtype=torch.float32)
            reference[f"prompt_{i}"] = embeds[0].contiguous()
    save_file(reference, str(out / "reference.safetensors"))
    (out / "prompts.json").write_text(json.dumps(PROMPTS))


if __name__ == "__main__":
    main()
