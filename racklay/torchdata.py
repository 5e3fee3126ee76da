"""A torch Dataset over a RackLay-format root, for training and evaluation.

Each item is a dict: `image` float32 (3, H, W), ImageNet-normalised; `top` and/or `front`
int64 (R, S, S) class ids at the model's layout size S (nearest-neighbour resize at pixel
centres, see `racklay.layout.resize_layouts`); `id` the sample id.

`transform(image_uint8_hwc, layouts: dict[view -> (R, S, S) uint8]) -> (image, layouts)` runs
on the uint8 arrays before normalisation (transfer's albumentations pipeline plugs in here).
With `cache=True` decoded, resized uint8 arrays are kept in memory: on 2 CPU cores decoding
PNGs every epoch costs real time.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from . import layout as L
from .data import RackLayRoot

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def _hw(size) -> tuple[int, int]:
    if isinstance(size, int):
        return size, size
    h, w = size
    return int(h), int(w)


def prepare_image(image: np.ndarray, size) -> np.ndarray:
    """Resize an RGB uint8 image to the model input size (H, W) with area/linear filtering."""
    import cv2

    h, w = _hw(size)
    if image.shape[:2] == (h, w):
        return image
    interp = cv2.INTER_AREA if image.shape[0] > h else cv2.INTER_LINEAR
    return cv2.resize(image, (w, h), interpolation=interp)


def image_to_tensor(image: np.ndarray) -> torch.Tensor:
    """RGB uint8 (H, W, 3) -> normalised float32 (3, H, W)."""
    x = (image.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))


class RackLayDataset(Dataset):
    def __init__(self, root, split: str | None = "train", image_size=256, layout_size: int = 256,
                 views: Sequence[str] = ("top", "front"), R: int | None = None,
                 transform: Callable | None = None, cache: bool = False, ids: Sequence[str] | None = None):
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
        self._cache: dict[int, tuple] = {}

    def __len__(self) -> int:
        return len(self.ids)

    def load_raw(self, i: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """uint8 image at the input size and class-id layouts at the layout size."""
        if self.cache and i in self._cache:
            return self._cache[i]
        sid = self.ids[i]
        img = prepare_image(self.root.read_image(sid), self.image_size)
        lays = {v: L.resize_layouts(self.root.read_layouts(v, sid, R=self.R), self.layout_size) for v in self.views}
        if self.cache:
            self._cache[i] = (img, lays)
        return img, lays

    def __getitem__(self, i: int) -> dict:
        img, lays = self.load_raw(i)
        if self.transform is not None:
            img, lays = self.transform(img, dict(lays))
        item = {"image": image_to_tensor(img), "id": self.ids[i]}
        for v, arr in lays.items():
            item[v] = torch.from_numpy(np.ascontiguousarray(arr).astype(np.int64))
        return item
