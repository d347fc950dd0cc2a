#!/usr/bin/env python3
"""Converts evaluation network weights that users already have on disk into the safetensors files
`trainer eval --lpips-weights / --inception-weights` reads. Nothing is downloaded.

Usage:
  convert_eval_weights.py lpips --net alex|vgg --backbone BACKBONE.pth --heads HEADS.pth --out FILE
      BACKBONE: torchvision's ImageNet checkpoint (~/.cache/torch/hub/checkpoints/
      alexnet-owt-7be5be79.pth or vgg16-397923af.pth); HEADS: the `lpips` package's linear heads
      (site-packages/lpips/weights/v0.1/alex.pth or vgg.pth). Writes `features.{i}.weight|bias`
      (torchvision names) and `lin{k}.model.1.weight`.
  convert_eval_weights.py inception --source FILE --out FILE
      FILE: pytorch-fid's `pt_inception-2015-12-05-6726825d.pth` (torchvision Inception3 names,
      used as they are) or clean-fid's TorchScript `inception-2015-12-05.pt` (its parameters and
      batch-norm buffers are matched to ours in module order, every shape checked). Writes
      torchvision Inception3 names without `fc.` and `num_batches_tracked`.

Requires torch and safetensors (the project venv).
"""

import argparse
import sys

import torch
from safetensors.torch import save_file

# Module order of the FID Inception (the TF 2015-12-05 graph): every BasicConv2d in forward order.
INCEPTION_CONVS = (
    ["Conv2d_1a_3x3", "Conv2d_2a_3x3", "Conv2d_2b_3x3", "Conv2d_3b_1x1", "Conv2d_4a_3x3"]
    + [f"Mixed_5{b}.{c}" for b in "bcd" for c in ["branch1x1", "branch5x5_1", "branch5x5_2", "branch3x3dbl_1",
                                                 "branch3x3dbl_2", "branch3x3dbl_3", "branch_pool"]]
    + [f"Mixed_6a.{c}" for c in ["branch3x3", "branch3x3dbl_1", "branch3x3dbl_2", "branch3x3dbl_3"]]
    + [f"Mixed_6{b}.{c}" for b in "bcde" for c in ["branch1x1", "branch7x7_1", "branch7x7_2", "branch7x7_3",
                                                  "branch7x7dbl_1", "branch7x7dbl_2", "branch7x7dbl_3",
                                                  "branch7x7dbl_4", "branch7x7dbl_5", "branch_pool"]]
    + [f"Mixed_7a.{c}" for c in ["branch3x3_1", "branch3x3_2", "branch7x7x3_1", "branch7x7x3_2", "branch7x7x3_3",
                                 "branch7x7x3_4"]]
    + [f"Mixed_7{b}.{c}" for b in "bc" for c in ["branch1x1", "branch3x3_1", "branch3x3_2a", "branch3x3_2b",
                                                "branch3x3dbl_1", "branch3x3dbl_2", "branch3x3dbl_3a",
                                                "branch3x3dbl_3b", "branch_pool"]]
)
BN_PARTS = ["weight", "bias", "running_mean", "running_var"]


def fail(msg: str) -> None:
    sys.exit(f"convert_eval_weights: {msg}")


def load_state(path: str) -> dict:
    obj = torch.load(path, map_location="cpu", weights_only=True)
    return obj.get("state_dict", obj) if isinstance(obj, dict) else obj


def lpips(args) -> None:
    backbone, heads = load_state(args.backbone), load_state(args.heads)
    out = {k: v for k, v in backbone.items() if k.startswith("features.")}
    if not out:
        fail(f"{args.backbone}: no `features.*` tensors (expected torchvision's {args.net} checkpoint)")
    first = out.get("features.0.weight")
    want = (64, 3, 11, 11) if args.net == "alex" else (64, 3, 3, 3)
    if first is None or tuple(first.shape) != want:
        fail(f"{args.backbone}: tensor `features.0.weight` is {None if first is None else tuple(first.shape)}, "
             f"expected {want} for --net {args.net}")
    for k in range(5):
        name = f"lin{k}.model.1.weight"
        if name not in heads:
            fail(f"{args.heads}: missing tensor `{name}` (expected the lpips package's v0.1 {args.net}.pth)")
        out[name] = heads[name]
    save_file({k: v.float().contiguous() for k, v in out.items()}, args.out)
    print(f"wrote {len(out)} tensors to {args.out}")


def expected_inception_names() -> list:
    names = []
    for conv in INCEPTION_CONVS:
        names.append(f"{conv}.conv.weight")
        names += [f"{conv}.bn.{p}" for p in BN_PARTS]
    return names


def inception(args) -> None:
    names = expected_inception_names()
    state, ordered = None, None
    try:
        module = torch.jit.load(args.source, map_location="cpu")
        # A TorchScript archive: parameters and buffers in module order, without counters.
        ordered = [(k, v) for k, v in module.state_dict().items()
                   if not k.endswith("num_batches_tracked") and v.dim() > 0]
    except RuntimeError:  # a pickled state dict, not TorchScript
        state = load_state(args.source)
    if state is not None:
        missing = [n for n in names if n not in state]
        if missing:
            fail(f"{args.source}: missing tensor `{missing[0]}` ({len(missing)} missing; expected torchvision "
                 "Inception3 names as in pytorch-fid's pt_inception-2015-12-05 file)")
        out = {n: state[n] for n in names}
    else:
        # The TorchScript file holds, per conv in forward order, its weight then the four BN
        # tensors; the module order is matched position by position and every shape checked below.
        ordered = [(k, v) for k, v in ordered if not k.startswith(("output", "fc"))]
        if len(ordered) < len(names):
            fail(f"{args.source}: {len(ordered)} tensors, expected at least {len(names)} "
                 "(is this clean-fid's inception-2015-12-05.pt?)")
        out = {}
        for ours, (theirs, value) in zip(names, ordered):
            if ours.endswith(".conv.weight") and value.dim() != 4:
                fail(f"{args.source}: tensor `{theirs}` has shape {tuple(value.shape)}, expected a conv weight "
                     f"for `{ours}`")
            out[ours] = value
    # Shape chain check: each BN vector matches its conv's output channels.
    for conv in INCEPTION_CONVS:
        w = out[f"{conv}.conv.weight"]
        for p in BN_PARTS:
            v = out[f"{conv}.bn.{p}"]
            if tuple(v.shape) != (w.shape[0],):
                fail(f"tensor `{conv}.bn.{p}` has shape {tuple(v.shape)}, expected ({w.shape[0]},)")
    save_file({k: v.float().contiguous() for k, v in out.items()}, args.out)
    print(f"wrote {len(out)} tensors to {args.out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("lpips")
    p.add_argument("--net", choices=["alex", "vgg"], default="alex")
    p.add_argument("--backbone", required=True)
    p.add_argument("--heads", required=True)
    p.add_argument("--out", required=True)
    p = sub.add_parser("inception")
    p.add_argument("--source", required=True)
    p.add_argument("--out", required=True)
    args = parser.parse_args()
    {"lpips": lpips, "inception": inception}[args.what](args)


if __name__ == "__main__":
    main()
