"""A torch Dataset over a RackLay-format root, for training and evaluation.

Each item is a dict: `image` float32 (3, H, W), ImageNet-normalised; `top` and/or `front`
uint8 (R, S, S) class ids at the model's layout size S (nearest-neighbour resize at pixel
centres, see `racklay.layout.resize_layouts`); `id` the sample id; with `spans=True`, `spans`
float32 (R, 2): each level's labelled span across the input image in image widths, NaN where
the sample has none (`racklay.data.level_spans`), moved with the image by letterboxing and by
the transform.

`transform(image_uint8_hwc, layouts: dict[view -> (R, S, S) uint8]) -> (image, layouts)` runs
on the uint8 arrays before normalisation (transfer's albumentations pipeline plugs in here).
With `spans=True` it is called as `transform(image, layouts, spans=spans)` and returns
`(image, layouts, spans)`; a transform that can move spans says so with `maps_spans = True`
(`racklay.augment.Augment` does).
With `cache=True` decoded, resized uint8 arrays are kept in memory: on 2 CPU cores decoding
PNGs every epoch costs real time.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from . import layout as L
from .config import TrainConfig
from .data import LUMA_WEIGHTS, RackLayRoot

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def batch_luminance(x: torch.Tensor) -> torch.Tensor:
    """(N, 1, H, W) luminance (BT.601, 0-1, float32) of an ImageNet-normalised batch (N, 3, H, W)
    (`image_to_tensor`'s inverse, then `data.luminance`'s weights)."""
    def col(a):
        return torch.from_numpy(a).to(x.device).view(1, 3, 1, 1)

    return ((x.float() * col(IMAGENET_STD) + col(IMAGENET_MEAN)) * col(LUMA_WEIGHTS)).sum(1, keepdim=True)


def _hw(size) -> tuple[int, int]:
    if isinstance(size, int):
        return size, size
    h, w = size
    return int(h), int(w)


#: aspect ratios within this log-ratio of the input's (about 10 %) are stretched, not padded
LETTERBOX_TOLERANCE = 0.1
#: colour of letterbox padding: the ImageNet mean, i.e. zeros after normalisation
PAD_RGB = tuple(int(round(255 * m)) for m in IMAGENET_MEAN)


def _resize(image: np.ndarray, h: int, w: int) -> np.ndarray:
    import cv2

    if image.shape[:2] == (h, w):
        return image
    interp = cv2.INTER_AREA if image.shape[0] > h else cv2.INTER_LINEAR
    return cv2.resize(image, (w, h), interpolation=interp)


def _pad_to(image: np.ndarray, h: int, w: int) -> np.ndarray:
    """Centre `image` on an (h, w) canvas of PAD_RGB."""
    out = np.empty((h, w, 3), np.uint8)
    out[:] = PAD_RGB
    y, x = (h - image.shape[0]) // 2, (w - image.shape[1]) // 2
    out[y:y + image.shape[0], x:x + image.shape[1]] = image
    return out


def letterbox_fit(ih: int, iw: int, size, letterbox: bool = True) -> tuple[int, int]:
    """The (height, width) a photo of (ih, iw) pixels is resized to inside the model input `size`:
    the input itself (stretched) without `letterbox` or at about the input's aspect, else the
    largest size of the photo's aspect that fits (the rest is padding, centred)."""
    h, w = _hw(size)
    if not letterbox or abs(math.log((iw / ih) / (w / h))) <= LETTERBOX_TOLERANCE:   # about the same aspect
        return h, w
    scale = min(h / ih, w / iw)
    return min(h, max(1, round(ih * scale))), min(w, max(1, round(iw * scale)))


def padded_columns(x: np.ndarray, inner_w: int, w: int) -> np.ndarray:
    """Image x in widths of an image `inner_w` pixels wide -> in widths of the `w`-pixel canvas
    `_pad_to` centres it on."""
    return ((w - inner_w) // 2 + np.asarray(x, np.float32) * inner_w) / w


def photo_columns(x: np.ndarray, inner_w: int, w: int) -> np.ndarray:
    """The inverse of `padded_columns`: x in widths of the `w`-pixel canvas -> in widths of the
    `inner_w`-pixel image centred on it."""
    return (np.asarray(x, np.float64) * w - (w - inner_w) // 2) / inner_w


def prepare_image(image: np.ndarray, size, letterbox: bool = False) -> np.ndarray:
    """Resize an RGB uint8 image to the model input size (H, W) with area/linear filtering.
    With `letterbox`, a photo of another aspect keeps its aspect and is padded (PAD_RGB) to the
    input instead of being stretched, as models trained with letterbox augmentation expect."""
    h, w = _hw(size)
    nh, nw = letterbox_fit(*image.shape[:2], (h, w), letterbox)
    img = _resize(image, nh, nw)
    return img if (nh, nw) == (h, w) else _pad_to(img, h, w)


def squeeze_width(w: int, keep: float) -> int:
    """The width `squeeze_letterbox` squeezes a `w`-pixel image to."""
    return max(1, min(w, round(w * keep)))


def squeeze_letterbox(image: np.ndarray, keep: float) -> np.ndarray:
    """Training-time letterbox: squeeze an input-size image to `keep` of its width and pad it
    back (what `prepare_image(letterbox=True)` does to a narrower photo)."""
    h, w = image.shape[:2]
    nw = squeeze_width(w, keep)
    return image if nw == w else _pad_to(_resize(image, h, nw), h, w)


def data_loader(dataset, workers: int = 0, **kw) -> torch.utils.data.DataLoader:
    """A DataLoader over these datasets. With worker processes, OpenCV runs on one thread in this
    process from now on, so every worker inherits one thread: OpenCV's own pool (a thread per CPU
    in every worker) oversubscribes the cores (one thread each: +40 % images/s with 7 and +15 % with
    14 workers on 16 CPUs, bench/speed/loader_speed.py); setting it inside a forked worker instead
    can deadlock on the pool the fork copied."""
    if workers > 0:
        import cv2

        cv2.setNumThreads(1)
    return torch.utils.data.DataLoader(dataset, num_workers=workers, **kw)


def image_to_tensor(image: np.ndarray) -> torch.Tensor:
    """RGB uint8 (H, W, 3) -> normalised float32 (3, H, W)."""
    x = (image.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))


class RackLayDataset(Dataset):
    def __init__(self, root, split: str | None = "train", image_size=TrainConfig.image_size,
                 layout_size: int = TrainConfig.layout_size,
                 views: Sequence[str] = ("top", "front"), R: int | None = None,
                 transform: Callable | None = None, cache: bool = False, ids: Sequence[str] | None = None,
                 letterbox: bool = False, spans: bool = False):
        if spans and transform is not None and not getattr(transform, "maps_spans", False):
            raise ValueError(f"{type(transform).__name__}: this transform cannot move the level spans with the image "
                             "(placement supervision needs racklay.augment.Augment)")
        self.root = RackLayRoot(root)
        self.ids = list(ids) if ids is not None else self.root.resolve(split)
        present = self.root.views()
        missing = [v for v in views if v not in present]
        if missing:
            raise FileNotFoundError(f"{self.root.root}: dataset has no {'/'.join(missing)} layouts "
                                    f"(views present: {', '.join(present) or 'none'})")
        self.views = tuple(views)
        self.image_size = _hw(image_size)
        self.layout_size = int(layout_size)
        self.R = R
        self.transform = transform
        self.cache = cache
        self.letterbox = letterbox
        self.spans = spans
        self._cache: dict[int, tuple] = {}

    def __len__(self) -> int:
        return len(self.ids)

    def prepared_image(self, i: int) -> np.ndarray:
        """Sample i's uint8 image at the input size, read from disk."""
        return prepare_image(self.root.read_image(self.ids[i]), self.image_size, self.letterbox)

    def prepared_layouts(self, i: int) -> dict[str, np.ndarray]:
        """Sample i's class-id layouts at the layout size, read from disk."""
        return {v: L.resize_layouts(self.root.read_layouts(v, self.ids[i], R=self.R), self.layout_size)
                for v in self.views}

    def prepared_spans(self, i: int, image_hw: tuple[int, int], R: int) -> np.ndarray:
        """Sample i's level spans (R, 2) on the input image, for a photo of `image_hw` pixels: the
        labelled spans moved by the letterbox padding (`letterbox_fit`)."""
        sp = self.root.read_level_spans(self.ids[i], R)
        w = self.image_size[1]
        nw = letterbox_fit(*image_hw, self.image_size, self.letterbox)[1]
        return sp if nw == w else padded_columns(sp, nw, w)

    def load_raw(self, i: int) -> tuple:
        """uint8 image at the input size and class-id layouts at the layout size (and, with
        `spans`, the level spans on that image)."""
        if self.cache and i in self._cache:
            return self._cache[i]
        raw = self.root.read_image(self.ids[i])
        img, lays = prepare_image(raw, self.image_size, self.letterbox), self.prepared_layouts(i)
        out = (img, lays)
        if self.spans:
            out += (self.prepared_spans(i, raw.shape[:2], next(iter(lays.values())).shape[0]),)
        if self.cache:
            self._cache[i] = out
        return out

    def __getitem__(self, i: int) -> dict:
        img, lays, *spans = self.load_raw(i)
        if self.transform is not None:
            if self.spans:
                img, lays, spans[0] = self.transform(img, dict(lays), spans=spans[0])
            else:
                img, lays = self.transform(img, dict(lays))
        item = {"image": image_to_tensor(img), "id": self.ids[i]}
        if self.spans:
            item["spans"] = torch.from_numpy(np.ascontiguousarray(spans[0], dtype=np.float32))
        for v, arr in lays.items():
            # uint8 class ids (the model's loss takes them as int64 on its device): 8x less to pass
            # from loader workers to the training process and to a GPU than int64
            item[v] = torch.from_numpy(np.ascontiguousarray(arr, dtype=np.uint8))
        return item


class ReplayMix(Dataset):
    """A small (real) training set plus synthetic *replay*: every epoch holds all of `real` and
    `round(ratio x len(real))` samples of `pool` (a large synthetic set, or several pooled in the
    order given: one index over all their samples), drawn afresh each epoch from (seed, epoch), so
    a fine-tune on a few dozen photos keeps seeing the renders the model learnt from and does not
    forget them. Items are addressed as `item(i, epoch)`; indices below `len(real)` are the real
    samples. Both parts run the real set's transform."""

    def __init__(self, real: RackLayDataset, pool: RackLayDataset | Sequence[RackLayDataset], ratio: float,
                 seed: int = 0):
        if not ratio > 0:
            raise ValueError(f"replay ratio must be > 0, got {ratio}")
        self.pools = [pool] if isinstance(pool, RackLayDataset) else list(pool)
        for p in self.pools:
            if len(p) == 0:
                raise ValueError(f"{p.root.root}: the replay set is empty")
            p.transform, p.spans = real.transform, real.spans
        self.real, self.seed = real, int(seed)
        self._ends = np.cumsum([len(p) for p in self.pools])
        self.n_real = len(real)
        self.n_replay = min(int(self._ends[-1]), max(1, round(ratio * self.n_real)))
        self._perm: tuple[int, np.ndarray] | None = None

    @property
    def transform(self):
        return self.real.transform

    def __len__(self) -> int:
        return self.n_real + self.n_replay

    def _locate(self, j: int) -> tuple[RackLayDataset, int]:
        """Pool index j -> (the set holding it, its index there)."""
        k = int(np.searchsorted(self._ends, j, side="right"))
        return self.pools[k], j - (int(self._ends[k - 1]) if k else 0)

    def replay_ids(self, epoch: int) -> list[str]:
        """The pool samples of epoch `epoch`, in order (with several sets: `root:id`)."""
        located = (self._locate(int(j)) for j in self._draw(epoch))
        if len(self.pools) == 1:
            return [p.ids[i] for p, i in located]
        return [f"{p.root.root}:{p.ids[i]}" for p, i in located]

    def _draw(self, epoch: int) -> np.ndarray:
        if self._perm is None or self._perm[0] != epoch:
            rng = np.random.default_rng([self.seed, int(epoch), 0x5E1A])
            self._perm = (epoch, rng.choice(int(self._ends[-1]), self.n_replay, replace=False))
        return self._perm[1]

    def item(self, i: int, epoch: int) -> dict:
        """Sample i of epoch `epoch`, with "replay": whether it is a pool sample (a render)."""
        if i < self.n_real:
            return {**self.real[i], "replay": torch.tensor(False)}
        p, k = self._locate(int(self._draw(epoch)[i - self.n_real]))
        return {**p[k], "replay": torch.tensor(True)}

    def __getitem__(self, i: int) -> dict:
        return self.item(i, 0)
