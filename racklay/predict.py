"""Run a trained RackLay model on photos: per-shelf top- and front-view layouts.

`Predictor(weights, backend="torch"|"onnx")` loads a checkpoint (safetensors, see
`racklay.checkpoint`) or an exported ONNX file (`racklay export`, which stores the model
config in the file's metadata) and turns an RGB uint8 photo of any size into

    {"top": (R, S, S) uint8 class ids, "front": ..., "probs": {view: (R, 3, S, S) float32},
     "grid": racklay.layout.Grid(S, extent)}

for the views the model has. The photo is resized to the model's input size with
`racklay.torchdata.prepare_image` and ImageNet-normalised with `image_to_tensor`, exactly as in
training. `predict_folder` is the engine behind `racklay predict`.
"""
from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from . import layout as L
from .onnx import export_onnx_bytes, onnx_session
from .precision import PRECISIONS, cast_for_autocast, resolve_precision  # noqa: F401  (the one home of precision)

BACKENDS = ("torch", "onnx")
#: photos with a shorter side than this are predicted with a warning (upscaled, they hold no rack)
MIN_PHOTO_SIDE = 32


def add_precision_args(p) -> None:
    """--precision auto|fp32|bf16 (with --bf16 / --fp32 shorthands) for commands that run a model."""
    p.add_argument("--precision", choices=PRECISIONS, default="auto",
                   help="torch backend: auto (default) = bf16 autocast + channels_last on CPUs with "
                        "native bf16 (about 2x faster; argmax agrees with fp32 on >99%% of pixels, "
                        "docs/benchmarks.md), fp32 elsewhere; the onnx backend always runs fp32")
    p.add_argument("--bf16", dest="precision", action="store_const", const="bf16",
                   help="same as --precision bf16")
    p.add_argument("--fp32", dest="precision", action="store_const", const="fp32",
                   help="same as --precision fp32")


def add_shelf_length_arg(p) -> None:
    """--shelf-length M for commands that run a model on photos."""
    from .config import positive_float

    p.add_argument("--shelf-length", type=positive_float, default=None, metavar="M",
                   help="the shelves' known length in metres (beam length, bay width; where the photo "
                        "cuts the bay, the length of the part it shows, which is what the layouts draw): "
                        "fixes the metric scale, which one photo cannot; every predicted shelf is scaled "
                        "about its origin to this length in all its dimensions, its shape unchanged "
                        "(default: the model's own estimate)")


#: `--rack-box`: the rack's box is grown by this share of its width and height on every side
#: before it is grown to the model's input aspect (RULE18, docs/eval-predict.md)
RACK_BOX_MARGIN = 0.1


def rack_box_arg(text: str) -> tuple[float, float, float, float]:
    """argparse type: 'X0,Y0,X1,Y1', the rack's box in image pixels (x0 < x1, y0 < y1)."""
    import argparse

    parts = text.replace(" ", "").split(",")
    try:
        box = tuple(float(v) for v in parts)
    except ValueError:
        box = ()
    if len(box) != 4 or not all(np.isfinite(box)):
        raise argparse.ArgumentTypeError(f"expected four numbers X0,Y0,X1,Y1 (pixels), got {text!r}")
    if not (box[0] < box[2] and box[1] < box[3]):
        raise argparse.ArgumentTypeError(f"expected X0 < X1 and Y0 < Y1 (the box's left, top, right, bottom "
                                         f"in pixels), got {text!r}")
    return box


def add_rack_box_arg(p) -> None:
    """--rack-box X0,Y0,X1,Y1 for commands that run a model on photos."""
    p.add_argument("--rack-box", type=rack_box_arg, default=None, metavar="X0,Y0,X1,Y1",
                   help="the rack to read, as a box in the photo's pixels (left, top, right, bottom; the "
                        "bays you want the layouts of, as a labeller would outline them): the model reads "
                        "the photo cropped to it, grown by 10%% on every side and to the model's input "
                        "aspect, instead of the whole frame. For wide frames with several bays or racks: on "
                        "photos of sites no model saw it read 3-5 box-IoU points more (docs/eval-predict.md)"
                        "; the same box applies to every input photo (default: the whole photo)")


def rack_crop(box, width: int, height: int, aspect: float, margin: float = RACK_BOX_MARGIN,
              source: str = "image") -> tuple[int, int, int, int]:
    """The crop (x0, y0, x1, y1, integer pixels) that a model reads for a rack box (x0, y0, x1,
    y1) in a width x height photo: the box grown by `margin` of its size on every side, then its
    shorter side grown to `aspect` (width / height, the model's input) about its centre, then
    shifted to lie inside the photo and clipped where it is larger. A box that misses the photo
    is a ValueError naming `source`."""
    x0, y0, x1, y1 = map(float, box)
    if not (x0 < x1 and y0 < y1):
        raise ValueError(f"{source}: rack box {tuple(box)} is empty (need x0 < x1, y0 < y1)")
    if x1 <= 0 or y1 <= 0 or x0 >= width or y0 >= height:
        raise ValueError(f"{source}: rack box {tuple(box)} lies outside the {width}x{height} photo")
    w, h = x1 - x0, y1 - y0
    w, h = w * (1 + 2 * margin), h * (1 + 2 * margin)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    if w / h < aspect:
        w = h * aspect
    else:
        h = w / aspect
    w, h = min(w, width), min(h, height)
    left = min(max(cx - w / 2, 0.0), width - w)
    top = min(max(cy - h / 2, 0.0), height - h)
    c = (int(round(left)), int(round(top)), int(round(left + w)), int(round(top + h)))
    return c[0], c[1], max(c[2], c[0] + 1), max(c[3], c[1] + 1)


def add_flip_average_arg(p) -> None:
    """--flip-average for commands that run a model (torch backend)."""
    p.add_argument("--flip-average", action="store_true",
                   help="torch backend: predict each image together with its left-right mirror image and "
                        "average the two (a struct model averages its shelves and boxes, so rectangles stay "
                        "rectangles): 1-2 box-IoU points better for about 1.3x the model's time "
                        "(docs/eval-predict.md)")


def softmax_classes(logits: np.ndarray, axis: int = -3) -> np.ndarray:
    """Numerically stable softmax over the class axis of (..., 3, S, S) logits (float32)."""
    z = np.asarray(logits, dtype=np.float32)
    z = z - z.max(axis=axis, keepdims=True)
    np.exp(z, out=z)
    z /= z.sum(axis=axis, keepdims=True)
    return z


def decide(logits: np.ndarray, bias=None, axis: int = 2) -> np.ndarray:
    """Classes (uint8) from (..., 3, S, S) logits: the argmax over the class axis, after adding
    the per-class `bias` (background, shelf, box) when the model carries one (`racklay calibrate`)."""
    z = np.asarray(logits, dtype=np.float32)
    if bias is not None:
        shape = [1] * z.ndim
        shape[axis] = len(bias)
        z = z + np.asarray(bias, dtype=np.float32).reshape(shape)
    return z.argmax(axis=axis).astype(np.uint8)


def as_rgb_uint8(image: np.ndarray, source: str = "image") -> np.ndarray:
    """Accept (H, W) grey, (H, W, 3) RGB or (H, W, 4) RGBA uint8; return (H, W, 3) RGB uint8."""
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"{source}: expected a uint8 image, got dtype {a.dtype}")
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or min(a.shape[:2]) < 1:
        raise ValueError(f"{source}: expected an (H, W, 3) RGB image, got shape {a.shape}")
    return np.ascontiguousarray(a[:, :, :3])


class Predictor:
    """A loaded model, ready to turn photos into layouts.

    weights: a checkpoint (`.safetensors`, from `racklay train`) or an ONNX file from
    `racklay export` (backend "onnx" is implied by the suffix). With backend="onnx" and a
    checkpoint, the model is exported in memory and run by onnxruntime.
    threads: torch / onnxruntime intra-op threads (default: library default).
    precision: "fp32" (default), "bf16" (torch backend: bfloat16 autocast; about 2x faster on
    CPUs with native bf16, see docs/benchmarks.md; logits differ slightly from fp32, argmax
    agreement in docs/benchmarks.md) or "auto" (bf16 where the CPU has native bf16 and the
    backend is torch, else fp32; the command-line default).
    The torch backend runs the model it loads in channels_last memory format (oneDNN's native
    layout on CPU: 1.2-1.5x faster than the default layout, same logits to ~1e-5,
    docs/benchmarks.md), with its batch norms folded into the convolutions before them
    (`racklay.model.fold_batchnorm`: the same argmax, ~1.1x faster) and, in bf16, its convolution
    and linear weights stored in bf16 (`racklay.precision.cast_for_autocast`: the same logits bit
    for bit, not cast again on every call).
    cut_gaps: False draws a struct model's boxes from its box output alone, without the gap
    output's cuts (torch backend; `RackLayNet.set_gap_cut`).
    flip_average: predict each photo together with its mirror image and average the two (torch
    backend; `RackLayNet.set_flip_average`).
    """

    def __init__(self, weights, backend: str = "torch", threads: int | None = None, precision: str = "fp32",
                 cut_gaps: bool = True, flip_average: bool = False):
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.weights = Path(weights)
        if self.weights.suffix.lower() == ".onnx":
            backend = "onnx"
        precision = resolve_precision(precision, backend=backend)
        self.precision = precision
        if backend == "onnx" and precision != "fp32":
            raise ValueError("precision bf16 is for the torch backend; onnxruntime runs fp32")
        if backend == "onnx" and not cut_gaps:
            raise ValueError("drawing without the gap cut is for the torch backend; an ONNX graph has the cut built in")
        if backend == "onnx" and flip_average:
            raise ValueError("flip averaging is for the torch backend; an ONNX graph predicts the photo alone")
        self.backend = backend
        self.threads = threads
        self.model = None
        self.session = None
        if backend == "onnx" and self.weights.suffix.lower() == ".onnx":
            self.session, self.cfg = onnx_session(self.weights, threads=threads)
            self.meta = {}
        else:
            from .checkpoint import load_model

            model, self.cfg, self.meta = load_model(self.weights, map_location="cpu")
            if not cut_gaps:
                try:
                    model.set_gap_cut(False)
                except ValueError as e:
                    raise ValueError(f"{self.weights}: {e}") from None
            model.set_flip_average(flip_average)
            if backend == "onnx":
                data = export_onnx_bytes(model.eval(), self.cfg)
                self.session, _ = onnx_session(data, threads=threads, source=str(self.weights))
            self._set_model(model, channels_last=True, fold=True)
        if threads and backend == "torch":
            import torch

            torch.set_num_threads(int(threads))

    @classmethod
    def from_model(cls, model, cfg, precision: str = "fp32") -> "Predictor":
        """Wrap an in-memory model (e.g. during training) without a checkpoint file. Its memory
        format is left as it is (channels_last only with bf16) and its batch norms are not folded,
        so training is not disturbed."""
        self = cls.__new__(cls)
        self.weights, self.backend, self.threads, self.session, self.meta = None, "torch", None, None, {}
        self.cfg, self.precision = cfg, resolve_precision(precision)
        self._set_model(model, channels_last=self.precision == "bf16")
        return self

    def _set_model(self, model, channels_last: bool, fold: bool = False) -> None:
        model.eval()
        if fold:   # a model loaded for inference alone (not one still in training)
            from .model import fold_batchnorm

            fold_batchnorm(model)
            if self.precision == "bf16":    # (only the torch backend takes bf16: __init__ refuses it for onnx)
                cast_for_autocast(model)
        if channels_last:
            import torch

            model = model.to(memory_format=torch.channels_last)
        self.model, self.channels_last = model, channels_last

    # --- model facts ---
    @property
    def views(self) -> tuple[str, ...]:
        return tuple(self.cfg.views)

    @property
    def R(self) -> int:
        return int(self.cfg.R)

    @property
    def image_size(self) -> tuple[int, int]:
        return self.cfg.input_hw

    @property
    def layout_size(self) -> int:
        """The size S of the layouts this predictor returns: the model's trained size, or the size
        a struct model draws at after `draw_at`."""
        size = self.model.draw_size() if self._draws() else None
        return int(size or self.cfg.layout_size)

    def _draws(self) -> bool:
        """Whether the torch model predicts (not an ONNX graph) and is a struct model."""
        return self.session is None and self.model is not None and self.cfg.decoder == "struct"

    @contextlib.contextmanager
    def drawing_at(self, size: int | None):
        """`draw_at(size)` for the duration of a `with` block (nothing for None), then back to the
        size drawn before; yields whether the model draws at `size` itself."""
        before = self.model.draw_size() if self._draws() else None
        drawn = bool(size) and self.draw_at(size)
        try:
            yield drawn
        finally:
            if drawn:
                self.draw_at(before)

    def draw_at(self, size: int | None) -> bool:
        """Return layouts of `size` x `size` pixels (None: the trained size) drawn by the model
        itself where it can: a struct model on the torch backend rasterises its metric structure at
        any resolution (True). Any other model predicts at its trained size (False; the caller
        resizes, `resize_prediction`)."""
        if not self._draws():
            return False
        self.model.set_draw_size(size)
        return True

    @property
    def grid(self) -> L.Grid:
        return L.Grid(size=self.layout_size, extent=float(getattr(self.cfg, "extent", L.DEFAULT_EXTENT_M)))

    # --- inference ---
    def logits(self, x) -> dict[str, np.ndarray]:
        """Raw logits {view: (N, R, 3, S, S) float32} for a normalised batch (N, 3, H, W)
        (torch tensor or numpy array)."""
        if self.session is not None:
            arr = x.numpy() if hasattr(x, "numpy") else np.asarray(x)
            outs = self.session.run(list(self.views), {"image": np.ascontiguousarray(arr, dtype=np.float32)})
            return dict(zip(self.views, outs))
        out = self._forward(x)
        return {v: out[v].float().numpy() for v in self.views}

    def structures(self, x) -> dict:
        """A struct model's structures {view: {field: (N, R[, T]) tensor}} (`racklay.structure`:
        presence, length, extent, placement in the image, per-position box and sizes, gap) for a
        normalised batch, at the predictor's precision (torch backend)."""
        if self.model is None or self.cfg.decoder != "struct":
            raise ValueError(f"{self.weights or 'the model'}: structures need a struct model on the torch backend "
                             f"(this one: {self.cfg.decoder} decoder, {self.backend})")
        return self._forward(x, with_structure=True)[1]

    def _forward(self, x, **kw):
        """The torch model on a normalised batch: memory format and precision as this predictor runs it."""
        import torch

        t = x if isinstance(x, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))
        if self.channels_last:
            t = t.contiguous(memory_format=torch.channels_last)
        with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            return self.model(t, **kw)

    def predict_batch(self, x) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """(classes {view: (N, R, S, S) uint8}, probs {view: (N, R, 3, S, S) float32})."""
        return self.decide_logits(self.logits(x))

    def decide_logits(self, logits: dict) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Logits {view: (N, R, 3, S, S)} -> (classes, probs) as `predict_batch` returns them."""
        probs = {v: softmax_classes(z, axis=2) for v, z in logits.items()}
        classes = {v: decide(z, (self.cfg.decision_bias or {}).get(v)) for v, z in logits.items()}
        return classes, probs

    def prepare(self, image: np.ndarray, source: str = "image"):
        """RGB uint8 photo of any size -> normalised (1, 3, H, W) tensor at the model's input size."""
        from .torchdata import image_to_tensor, prepare_image

        img = prepare_image(as_rgb_uint8(image, source), self.image_size, self.cfg.letterbox)
        return image_to_tensor(img)[None]

    def crop_for(self, image: np.ndarray, rack_box, source: str = "image") -> tuple[int, int, int, int]:
        """The region of `image` the model reads for a rack box (`rack_crop` at the model's aspect)."""
        h, w = self.image_size
        return rack_crop(rack_box, image.shape[1], image.shape[0], w / h, source=source)

    def predict(self, image: np.ndarray, shelf_length: float | None = None, rack_box=None,
                source: str = "image") -> dict:
        """One RGB uint8 (H, W, 3) photo -> {"top", "front" (views the model has): (R, S, S)
        class ids; "probs": {view: (R, 3, S, S)}; "grid": Grid}. shelf_length: the shelves' known
        length in metres; it fixes the scale (every shelf scaled about its origin to that length,
        `with_shelf_length`), the shape stays as predicted. rack_box: (x0, y0, x1, y1) pixels, the
        rack to read: the model sees the photo cropped to `crop_for` it (returned as "crop")."""
        crop = None
        if rack_box is not None:
            crop = self.crop_for(image, rack_box, source)
            image = image[crop[1]:crop[3], crop[0]:crop[2]]
        x = self.prepare(image, source)
        draws = self._draws()
        if draws:    # one pass gives the layouts and the structure they are drawn from
            logits, structs = self._forward(x, with_structure=True)
            classes, probs = self.decide_logits({v: logits[v].float().numpy() for v in self.views})
        else:
            classes, probs = self.predict_batch(x)
        out: dict = {v: classes[v][0] for v in self.views}
        out["probs"] = {v: probs[v][0] for v in self.views}
        out["grid"] = self.grid
        if draws:   # shelf spans in widths of the photo (or crop) read, not of a letterboxed input
            from .torchdata import letterbox_fit, photo_columns

            h, w = self.image_size
            nw = letterbox_fit(image.shape[0], image.shape[1], (h, w), self.cfg.letterbox)[1]
            out["shelf_spans"] = photo_columns(shelf_spans(structs)[0], nw, w)
        if crop is not None:
            out["crop"] = crop
        return with_shelf_length(out, shelf_length) if shelf_length is not None else out


def shelf_spans(structs: dict) -> np.ndarray:
    """A struct model's structures -> (N, R, 2) where it places each shelf across the image it read
    (left and right ends in image widths, 0 the left edge and 1 the right: `racklay.structure.image_span`),
    NaN for a shelf it does not see. The front view's placement (the top view's in a model without
    one): both views read the same shelf."""
    from .structure import image_span

    st = structs["front"] if "front" in structs else next(iter(structs.values()))
    span = image_span(st).numpy().astype(np.float64)
    span[~(st["presence"].float() > 0).numpy()] = np.nan
    return span


#: a shelf end this close to the frame's edge (image widths) or beyond it is cut by the frame: a
#: labelled photo draws a cut bay up to the edge, a render of the whole bay past it. On 56 labelled
#: photos v11 never trained on, 88 of 116 shelf ends cut: v11's placement flags 52 of them at
#: 0.05 with 8 false alarms (0.02: 40 and 6; 0.1: 59 and 10)
FRAME_EDGE_MARGIN = 0.05


def ends_cut(span) -> tuple[bool, bool] | None:
    """Whether the frame cuts a shelf spanning `span` ([left, right], image widths) at its left
    and at its right end (the end reaches within `FRAME_EDGE_MARGIN` of the frame's edge, or past
    it); None for an unknown span (NaN)."""
    lo, hi = (float(x) for x in span)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return None
    return lo < FRAME_EDGE_MARGIN, hi > 1 - FRAME_EDGE_MARGIN


def frame_cuts(spans: np.ndarray) -> list[str]:
    """One phrase per shelf the frame cuts (`ends_cut` of its span, `shelf_spans`' (R, 2)): "shelf 2
    (both ends)", "shelf 1 (left end)". There the shelf's length is not all in the photo: the model
    infers it, and with it the metric scale, from what stands on the shelf (on `complex_paper`
    renders, 2.3 % median length error with both ends in the frame, 5.6 % with neither:
    bench/accuracy/scale_cues.py)."""
    out = []
    for k, span in enumerate(np.asarray(spans, dtype=np.float64)):
        cut = ends_cut(span)
        if cut and any(cut):
            out.append(f"shelf {k + 1} ({'both ends' if all(cut) else ('left' if cut[0] else 'right') + ' end'})")
    return out


def with_shelf_length(pred: dict, shelf_length: float) -> dict:
    """A prediction ({view: (R, S, S) classes, "probs", "grid"}) with every shelf scaled to a known
    length in metres (`racklay.layout.scale_shelves`: one factor per shelf for all its dimensions
    and both views, about the shelf origin). Adds "scale": (R,) factors applied."""
    if isinstance(shelf_length, bool) or not isinstance(shelf_length, (int, float)) \
            or not np.isfinite(shelf_length) or shelf_length <= 0:
        raise ValueError(f"shelf length must be a positive number of metres, got {shelf_length!r}")
    layouts, probs, factors = L.scale_shelves({v: pred[v] for v in L.VIEWS if v in pred}, pred["grid"],
                                              shelf_length, pred.get("probs"))
    return {**pred, **layouts, "probs": probs, "scale": factors}


# --- folders of photos -------------------------------------------------------------------
@dataclass
class PredictReport:
    done: list[str] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)  # (path, one-line message)
    cut: list[str] = field(default_factory=list)     # ids whose frame cuts a shelf (`frame_cuts`), no --shelf-length

    def scale_note(self) -> str | None:
        """One line for the end of a run where the frame cut a shelf of some photos, or None."""
        if not self.cut:
            return None
        return (f"note: the frame cuts a shelf in {len(self.cut)} of {len(self.done)} photo(s): where it does, the "
                f"shelf's length, and so the metric scale, is inferred from what stands on it, not seen; "
                f"--shelf-length fixes the scale")

    @property
    def ok(self) -> bool:
        return not self.failed

    def summary(self) -> str:
        n = len(self.done) + len(self.failed)
        if self.ok:
            return f"{len(self.done)} image(s) predicted"
        return f"{len(self.failed)} of {n} input(s) failed, {len(self.done)} predicted"


def list_inputs(inputs: Sequence[str | os.PathLike], skipped: list | None = None) -> list[Path]:
    """Files named on the command line (whatever their type: a file that is not an image gets a
    one-line error, not silence), and the photos inside named folders (sorted; `PHOTO_EXTS`).
    Other files in a folder (a README, annotations) are not photos, and its subfolders are not
    searched: both are appended to `skipped` when a list is given, so the caller can say so once."""
    from .data import PHOTO_EXTS

    files: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            inside = sorted(q for q in p.iterdir() if not q.name.startswith("."))
            files += [q for q in inside if q.is_file() and q.suffix.lower() in PHOTO_EXTS]
            if skipped is not None:
                skipped += [q for q in inside if q.is_dir() or q.suffix.lower() not in PHOTO_EXTS]
        else:
            files.append(p)  # a missing file is reported by the reader, naming it
    return files


def unique_ids(paths: Iterable[Path]) -> list[str]:
    """Sample id per input: the file stem, with _2, _3, ... when two inputs share a stem."""
    seen: dict[str, int] = {}
    ids = []
    for p in paths:
        stem = p.stem or p.name
        n = seen.get(stem, 0) + 1
        seen[stem] = n
        ids.append(stem if n == 1 else f"{stem}_{n}")
    return ids


def write_prediction(out_root, sid: str, image: np.ndarray, pred: dict, views: Sequence[str],
                     source: str = "", figure: bool = True, png: bool = True, crop: bool = True,
                     extra_meta: dict | None = None, load_width: float | None = None) -> None:
    """Write one prediction as a RackLay sample (Images/, topLayouts/, frontLayouts/, meta/),
    colour PNGs per shelf (png/ID_VIEW_shelfK.png) and a paper-style figure (figures/ID.png)
    with the box stacks outlined (read with the loads' width `load_width`, when given)."""
    from .atomic import atomic_save_png
    from .data import RackLayRoot
    from .viz import colorize, layout_figure

    root = RackLayRoot(out_root)
    g = pred["grid"]
    meta = {"source": str(source), "input_size": [int(image.shape[1]), int(image.shape[0])],
            "grid": {"D": g.size, "extent_m": g.extent}, "prediction": True, **(extra_meta or {})}
    try:
        root.write_sample(sid, image=image, top=pred.get("top"), front=pred.get("front"), meta=meta)
        if png:
            for v in views:
                for k, ch in enumerate(pred[v]):
                    atomic_save_png(root.root / "png" / f"{sid}_{v}_shelf{k + 1}.png", colorize(ch))
        if figure:
            layout_figure(image, pred.get("top"), pred.get("front"), out=root.root / "figures" / f"{sid}.png",
                          title=f"{Path(source).name or sid}: predicted layouts", grid=g, crop=crop,
                          outline_stacks=True, load_width=load_width)
    except BaseException:
        # a sample is written whole or not at all: no layouts without their figure, no stale mix
        # of this prediction's files with an earlier one's
        for f in [root.image_path(sid), root.meta_path(sid), root.root / "figures" / f"{sid}.png",
                  *(root.layout_path(v, sid) for v in L.VIEWS),
                  *(root.root / "png").glob(f"{sid}_*_shelf*.png")]:
            if f.is_file():     # the clean-up never hides the error that stopped the write
                f.unlink()
        raise


def resize_prediction(pred: dict, size: int) -> dict:
    """The prediction's class layouts resized (nearest, at pixel centres) to size x size, with
    the matching Grid (same metric extent). Probabilities are left at the model's resolution."""
    g = pred["grid"]
    if size == g.size:
        return pred
    out = {k: (L.resize_layouts(v, size) if k in L.VIEWS else v) for k, v in pred.items()}
    out["grid"] = L.Grid(size=size, extent=g.extent)
    return out


def predict_folder(predictor: Predictor, inputs: Sequence[str | os.PathLike], out, figure: bool = True,
                   png: bool = True, crop: bool = True, progress: bool = True, log=None,
                   layout_size: int | None = None, shelf_length: float | None = None,
                   rack_box=None, load_width: float | None = None) -> PredictReport:
    """Predict every input file; a file that cannot be read gets one line via `log` (default:
    stderr) and the rest still run. layout_size: write layouts at this D, e.g. a ground-truth
    dataset's D so `racklay score` can compare (a struct model on the torch backend draws them at D,
    `Predictor.draw_at`; any other model's S x S output is resized, nearest).
    shelf_length: the shelves' known length in metres (fixes the scale, `Predictor.predict`).
    rack_box: (x0, y0, x1, y1) pixels, the rack to read in every photo (`Predictor.predict`); the
    sample's image is then the crop the model read, and its meta records both.
    load_width: the loads' width in metres, when all are alike: the figures outline the stacks
    read with it (racklay.reasoning `load_width_m`, as `racklay analyze --load-width`)."""
    import sys

    from .atomic import WriteError
    from .data import read_image

    skipped: list[Path] = []
    files = list_inputs(inputs, skipped)
    ids = unique_ids(files)
    rep = PredictReport()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(files), desc="predict", unit="img", leave=False)
    if log is None:
        def log(msg: str) -> None:
            if bar is not None:
                bar.write(msg, file=sys.stderr)
            else:
                print(msg, file=sys.stderr)
    if skipped:
        for what, group in (("file(s) that are not photos", [q for q in skipped if not q.is_dir()]),
                            ("subfolder(s), not searched (name them to predict their photos)",
                             [q for q in skipped if q.is_dir()])):
            if group:
                names = ", ".join(q.name for q in group[:5]) + (", ..." if len(group) > 5 else "")
                log(f"note: skipped {len(group)} {what} ({names})")
    extra = {"weights": str(predictor.weights) if predictor.weights else None, "backend": predictor.backend}
    if shelf_length is not None:
        L.check_shelf_length(shelf_length, predictor.grid)    # before the first photo, not once per photo
        extra["shelf_length_m"] = float(shelf_length)
    if load_width:
        extra["load_width_m"] = float(load_width)
    if predictor.model is not None and predictor.model.flip_average:
        extra["flip_average"] = True
    made_out = not Path(out).exists()
    with predictor.drawing_at(layout_size):    # a struct model draws at layout_size itself
        for path, sid in zip(files, ids):
            try:
                image = read_image(path)
                if min(image.shape[:2]) < MIN_PHOTO_SIDE:
                    h, w = predictor.image_size
                    log(f"warning: {path}: {image.shape[1]}x{image.shape[0]} pixels is far smaller than the model's "
                        f"{w}x{h} input; its layouts say little about a rack")
                pred = predictor.predict(image, shelf_length=shelf_length, rack_box=rack_box, source=str(path))
                meta = extra
                if "crop" in pred:
                    x0, y0, x1, y1 = pred["crop"]
                    meta = {**extra, "rack_box_px": [float(v) for v in rack_box], "crop_px": [x0, y0, x1, y1],
                            "photo_size": [int(image.shape[1]), int(image.shape[0])]}
                    image = image[y0:y1, x0:x1]
                if "shelf_spans" in pred:
                    meta = {**meta, "shelf_spans_image": [None if not np.isfinite(sp).all() else
                                                          [round(float(x), 4) for x in sp] for sp in pred["shelf_spans"]]}
                    cuts = frame_cuts(pred["shelf_spans"])
                    if cuts and shelf_length is None:
                        rep.cut.append(sid)
                        log(f"note: {path}: the frame cuts {', '.join(cuts)}")
                if layout_size:
                    pred = resize_prediction(pred, layout_size)
                write_prediction(out, sid, image, pred, predictor.views, source=str(path), figure=figure,
                                 png=png, crop=crop, extra_meta=meta, load_width=load_width)
                rep.done.append(sid)
            except WriteError:
                # the output cannot be written (disk full, read-only): every next photo would fail the
                # same way, so stop here; the error names the file
                if bar is not None:
                    bar.close()
                raise
            except (ValueError, OSError, MemoryError) as e:  # DataError is a ValueError and names the file
                msg = str(e).splitlines()[0] if str(e) else type(e).__name__
                if isinstance(e, MemoryError):
                    msg = f"out of memory ({msg})"
                if str(path) not in msg:
                    msg = f"{path}: {msg}"
                rep.failed.append((str(path), msg))
                log(f"error: {msg}")
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    if made_out and not rep.done:   # every input failed: leave no (empty) output folder behind
        import shutil

        if not any(p.is_file() for p in Path(out).rglob("*")):
            shutil.rmtree(out, ignore_errors=True)
    return rep
