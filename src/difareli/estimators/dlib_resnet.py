"""dlib's face-recognition ResNet (``dlib_face_recognition_resnet_model_v1.dat``) in PyTorch.

The network is ``anet_type`` of dlib's ``examples/dnn_face_recognition_ex.cpp``: a 7x7/2 convolution, max-pool,
14 residual blocks (affine = frozen batch-norm), global average pool and a 128-wide bias-free linear layer whose
output is the descriptor (dlib's ``loss_metric`` returns it as is: not normalised). dlib stays the reference;
this port runs batched and reads the weights from dlib's own file with a reader written from dlib's sources
(``dlib/serialize.h``, ``float_details.h``, ``dnn/core.h``, ``dnn/layers.h``, ``dnn/input.h``):

- integers: a control byte (low nibble = byte count, bit 7 = negative) then the magnitude, little endian;
  floats: two such integers, mantissa then exponent (value = mantissa * 2**exponent); strings: length + bytes;
  bools: ASCII '1' / '0'; tensors: version 2, four dimensions, then raw little-endian float32.
- ``add_layer`` writes its version, *then its subnetwork*, then its own layer: the file holds every layer's
  version from the loss down to the input, then the layers' details from the input back up to the top.

Parsing the 22 MB file takes ~0.04 s, ~0.07 s with building the module (the tensors are raw float32, read with
``np.frombuffer``; only ~100 layer headers are decoded in Python), so nothing is cached on disk.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from difareli.errors import UserError

CHIP = 150
DIM = 128
#: (width, downsamples) of the residual blocks, input to output (alevel4 ... alevel0).
BLOCKS = ([(32, False)] * 3 + [(64, True)] + [(64, False)] * 3 + [(128, True)] + [(128, False)] * 2
          + [(256, True)] + [(256, False)] * 2 + [(256, True)])


def _layer_kinds() -> list[str]:
    """The network's layers from the input up: dlib layer names, ``tag``/``skip`` for its tag and skip layers."""
    kinds = ["con", "affine", "relu", "max_pool"]
    for _, down in BLOCKS:
        kinds += ["tag", "con", "affine", "relu", "con", "affine"]
        kinds += (["tag", "skip", "avg_pool"] if down else []) + ["add_prev", "relu"]
    return kinds + ["avg_pool", "fc"]


class _Reader:
    """A cursor over dlib's serialized bytes; every failure is a UserError naming the file and the offset."""

    def __init__(self, data: bytes, path: str):
        self.data, self.path, self.pos = data, path, 0

    def fail(self, why: str) -> UserError:
        return UserError(f"{self.path}: not a readable dlib face-recognition ResNet file ({why} at byte {self.pos})")

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise self.fail("file ends early")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def int(self) -> int:
        ctrl = self.take(1)[0]
        size = ctrl & 0x0F
        if size == 0 or size > 8 or ctrl & 0x70:
            raise self.fail(f"bad integer control byte {ctrl:#x}")
        v = int.from_bytes(self.take(size), "little")
        return -v if ctrl & 0x80 else v

    def float(self) -> float:
        if self.data[self.pos:self.pos + 1] and self.data[self.pos] & 0x70:
            raise self.fail("old ASCII float encoding (unsupported)")
        mantissa, exponent = self.int(), self.int()
        special = {32000: math.inf, 32001: -math.inf, 32002: math.nan}  # float_details::is_inf, ...
        return special[exponent] if exponent in special else math.ldexp(mantissa, exponent)

    def string(self) -> str:
        n = self.int()
        if n > 256:
            raise self.fail(f"implausible string length {n}")
        return self.take(n).decode("latin-1")

    def bool(self) -> bool:
        c = self.take(1)
        if c not in (b"0", b"1"):
            raise self.fail(f"bad bool {c!r}")
        return c == b"1"

    def tensor(self) -> np.ndarray:
        if self.int() != 2:
            raise self.fail("unknown tensor version")
        shape = tuple(self.int() for _ in range(4))
        n = math.prod(shape)
        if min(shape) < 0 or 4 * n > len(self.data) - self.pos:
            raise self.fail(f"file ends early: a tensor of shape {shape} does not fit")
        return np.frombuffer(self.take(4 * n), "<f4").reshape(shape)

    def alias(self) -> tuple[int, ...]:
        if self.int() != 1:
            raise self.fail("unknown alias_tensor version")
        return tuple(self.int() for _ in range(4))


def _details(r: _Reader) -> tuple[str, dict]:
    """One layer's details (``serialize(layer_details)``): (kind, fields)."""
    version = r.string()
    if version in ("con_4", "con_5", "con_6"):
        params = r.tensor().ravel()
        d = {k: r.int() for k in ("num_filters", "nr", "nc", "stride_y", "stride_x", "pad_y", "pad_x")}
        filters, biases = r.alias(), r.alias()
        [r.float() for _ in range(4)]  # learning-rate / weight-decay multipliers
        use_bias = r.bool() if version != "con_4" else True
        if version == "con_6" and r.bool():
            raise r.fail("con_ with a fused relu (unsupported)")
        nw = math.prod(filters)
        d["weight"] = params[:nw].reshape(filters)
        d["bias"] = params[nw:nw + math.prod(biases)] if use_bias else np.zeros(filters[0], np.float32)
        return "con", d
    if version in ("affine_", "affine_2"):
        params = r.tensor().ravel()
        g, _ = r.alias(), r.alias()
        r.int()  # mode (CONV_MODE here)
        if version == "affine_2" and r.bool():
            raise r.fail("disabled affine_ layer (unsupported)")
        k = math.prod(g)
        return "affine", {"gamma": params[:k], "beta": params[k:2 * k]}
    if version in ("max_pool_2", "avg_pool_2"):
        return version[:-2], {k: r.int() for k in ("nr", "nc", "stride_y", "stride_x", "pad_y", "pad_x")}
    if version in ("fc_2", "fc_3"):
        n_out, n_in = r.int(), r.int()
        params = r.tensor().ravel()
        w, _ = r.alias(), r.alias()
        if r.int() != 1:  # fc_bias_mode: FC_NO_BIAS
            raise r.fail("fc_ layer with a bias (expected fc_no_bias)")
        [r.float() for _ in range(4)]
        if version == "fc_3":
            r.bool()
        return "fc", {"weight": params[:math.prod(w)].reshape(n_in, n_out)}
    if version in ("relu_", "relu_2"):
        if version == "relu_2" and r.bool():
            raise r.fail("disabled relu_ layer (unsupported)")
        return "relu", {}
    if version == "add_prev_":
        return "add_prev", {}
    raise r.fail(f"unexpected layer {version!r}")


def read_dlib_resnet(path: str | Path) -> dict:
    """Parse dlib's serialized ``anet_type`` into numpy arrays: ``mean_rgb`` (3,), ``layers`` (input to output,
    ``(kind, fields)``, tags and skips left out). Raises a UserError naming ``path`` on anything unexpected."""
    path = str(path)
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise UserError(f"{path}: cannot read the dlib face-recognition ResNet file ({e})") from e
    r = _Reader(data, path)
    if r.int() != 1 or (loss := r.string()) not in ("loss_metric_", "loss_metric_2"):
        raise r.fail("no loss_metric layer at the top")
    if loss == "loss_metric_2":
        r.float(), r.float()  # margin, distance threshold
    kinds = _layer_kinds()
    versions = [r.int() for _ in kinds]  # top-down: every add_layer / tag / skip writes its version first
    ok = {"tag": (1,), "skip": (1,)}
    for kind, v in zip(reversed(kinds[1:]), versions):
        if v not in ok.get(kind, (1, 2)):
            raise r.fail(f"version {v} for a {kind} layer")
    if versions[-1] not in (2, 3):  # the bottom add_layer, over the input layer
        raise r.fail(f"version {versions[-1]} for the input add_layer")
    if r.string() != "input_rgb_image_sized":
        raise r.fail("no input_rgb_image_sized layer")
    mean_rgb = np.array([r.float() for _ in range(3)], np.float32)
    if (r.int(), r.int()) != (CHIP, CHIP):
        raise r.fail(f"input size is not {CHIP}x{CHIP}")
    layers = []
    for i, (kind, v) in enumerate(zip(kinds, reversed(versions))):
        if kind in ("tag", "skip"):
            continue  # a tag/skip layer writes only its version and its subnetwork
        got, fields = _details(r)
        if got != kind:
            raise r.fail(f"layer {i} is {got!r}, expected {kind!r}")
        layers.append((kind, fields))
        [r.bool() for _ in range(3)]  # setup called, gradient stale, output disabled
        r.tensor(), r.tensor()  # x_grad, cached_output
        if i == 0:
            r.tensor()  # grad_final
            if v == 3:
                r.int()  # sample expansion factor
        elif v == 2:
            r.tensor()  # params_grad
    if r.pos != len(data):
        raise r.fail(f"{len(data) - r.pos} bytes left over")
    return {"mean_rgb": mean_rgb, "layers": layers}


def _add_padded(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """dlib's ``add_prev``: a sum over the larger of each dimension, the smaller tensor zero-filled at the end
    (a downsampling block adds more channels, and at 8 px its 3x3/2 convolution gives 3 px, its skip 4 px)."""
    if a.shape == b.shape:
        return a + b
    size = [max(p, q) for p, q in zip(a.shape, b.shape)]

    def pad(t: torch.Tensor) -> torch.Tensor:
        return F.pad(t, (0, size[3] - t.shape[3], 0, size[2] - t.shape[2], 0, size[1] - t.shape[1]))

    return pad(a) + pad(b)


def _conv(cin: int, cout: int, k: int, stride: int) -> nn.Conv2d:
    # dlib pads (by k // 2) only stride-1 convolutions; its strided ones are unpadded.
    return nn.Conv2d(cin, cout, k, stride, k // 2 if stride == 1 else 0)


class _Block(nn.Module):
    """``ares`` / ``ares_down``: relu(block(x) + skip), skip = x or avg_pool<2,2,2,2>(x); affines folded."""

    def __init__(self, cin: int, width: int, down: bool):
        super().__init__()
        self.down = down
        self.conv1, self.conv2 = _conv(cin, width, 3, 2 if down else 1), _conv(width, width, 3, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv2(F.relu(self.conv1(x)))
        return F.relu(_add_padded(y, F.avg_pool2d(x, 2) if self.down else x))


class DlibFaceResNet(nn.Module):
    """dlib's ``anet_type``: (N, 3, 150, 150) float RGB in 0..255 -> (N, 128) descriptors. Each ``affine``
    (frozen batch-norm) is folded into the convolution before it: one pass over the activations fewer, and
    descriptors still within 3e-7 of dlib's. fp32 only: bf16 autocast errs by 2.3e-3."""

    def __init__(self):
        super().__init__()
        self.register_buffer("mean_rgb", torch.zeros(1, 3, 1, 1))
        self.stem = _conv(3, 32, 7, 2)
        widths = [32] + [w for w, _ in BLOCKS]
        self.blocks = nn.Sequential(*(_Block(c, w, d) for c, (w, d) in zip(widths, BLOCKS)))
        self.fc = nn.Linear(256, DIM, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = (x - self.mean_rgb) / 256.0  # input_rgb_image_sized::to_tensor
        x = F.max_pool2d(F.relu(self.stem(x)), 3, 2)
        return self.fc(self.blocks(x).mean((2, 3)))  # avg_pool_everything, fc_no_bias

    @classmethod
    def from_dlib(cls, path: str | Path | None = None) -> DlibFaceResNet:
        """The network with the weights of dlib's file (default: ``face_recognition_models``' copy)."""
        if path is None:
            import face_recognition_models

            path = face_recognition_models.face_recognition_model_location()
        parsed = read_dlib_resnet(path)
        net = cls()
        convs = [net.stem] + [c for b in net.blocks for c in (b.conv1, b.conv2)]
        cons = [f for k, f in parsed["layers"] if k == "con"]
        affines = [f for k, f in parsed["layers"] if k == "affine"]
        pools = [tuple(f.values()) for k, f in parsed["layers"] if k.endswith("pool")]
        down = sum(d for _, d in BLOCKS)  # (nr, nc, stride_y, stride_x, pad_y, pad_x): 3x3/2, 2x2/2s, global
        if pools != [(3, 3, 2, 2, 0, 0)] + [(2, 2, 2, 2, 0, 0)] * down + [(0, 0, 1, 1, 0, 0)]:
            raise UserError(f"{path}: pooling layers {pools} do not match dlib's face ResNet")
        with torch.no_grad():
            for conv, con, aff in zip(convs, cons, affines, strict=True):
                got = (con["weight"].shape, con["stride_y"], con["pad_y"])
                if got != (conv.weight.shape, conv.stride[0], conv.padding[0]):
                    raise UserError(f"{path}: convolution {got} does not match dlib's face ResNet")
                g = torch.from_numpy(aff["gamma"].copy())
                conv.weight.copy_(torch.from_numpy(con["weight"].copy()) * g[:, None, None, None])
                conv.bias.copy_(torch.from_numpy(con["bias"].copy()) * g + torch.from_numpy(aff["beta"].copy()))
            fc = parsed["layers"][-1][1]["weight"]
            if fc.shape != (256, DIM):
                raise UserError(f"{path}: fc layer of shape {fc.shape}, expected (256, {DIM})")
            net.fc.weight.copy_(torch.from_numpy(fc.T.copy()))
            net.mean_rgb.copy_(torch.from_numpy(parsed["mean_rgb"]).view(1, 3, 1, 1))
        # channels_last: measured 1.7x faster than NCHW at batch 1 on one CPU thread (oneDNN's native layout)
        return net.eval().requires_grad_(False).to(memory_format=torch.channels_last)


@functools.lru_cache(maxsize=2)
def load(path: str | None = None) -> DlibFaceResNet:
    """:meth:`DlibFaceResNet.from_dlib`, once per process and path (~0.07 s)."""
    return DlibFaceResNet.from_dlib(path)


def face_descriptors(chips: np.ndarray, net: DlibFaceResNet | None = None, batch_size: int = 16) -> np.ndarray:
    """128-d descriptors (N, 128) float32 of face chips (N, 150, 150, 3) uint8 RGB as ``dlib.get_face_chip(image,
    shape, 150, 0.25)`` cuts them; equal to dlib's ``compute_face_descriptor(chip)`` up to float rounding."""
    chips = np.asarray(chips)
    if chips.ndim == 3:
        chips = chips[None]
    if chips.ndim != 4 or chips.shape[1:] != (CHIP, CHIP, 3):
        raise UserError(f"face chips must be (N, {CHIP}, {CHIP}, 3) RGB, got shape {chips.shape}")
    net = load() if net is None else net
    out = []
    with torch.inference_mode():
        for i in range(0, len(chips), batch_size):
            x = torch.from_numpy(np.ascontiguousarray(chips[i:i + batch_size])).permute(0, 3, 1, 2)
            out.append(net(x.float().contiguous(memory_format=torch.channels_last)).numpy())
    return np.concatenate(out) if out else np.zeros((0, DIM), np.float32)
