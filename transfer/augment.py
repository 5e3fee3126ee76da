"""The paper's fine-tuning augmentation (RackLay §5.5), built on albumentations.

Colour jitter (brightness, contrast and saturation factors in [0.8, 1.2], hue shift within
±0.1, applied with p = 0.5) and a horizontal flip (p = 0.5). Every top- and front-view layout
channel is handed to albumentations as a mask, so the flip that albumentations applies to the
image is the flip applied to the layouts: there is no hand-written flip here. Colour jitter
is an image-only transform, so layouts never change value.

Layouts are D×D metric grids and photos are not, so `Compose(..., is_check_shapes=False)`:
albumentations 2.0.8 flips each mask by its own width (x -> -x in the shelf frame, exactly
`racklay.layout.hflip_layouts`). Geometric transforms other than flips would need the image
and the layouts to share a frame and are deliberately not offered.

Plugs into `racklay.torchdata.RackLayDataset(transform=...)` and `racklay.train.train(cfg,
transform=...)`: `aug(img_uint8_hwc, {view: (R, S, S) uint8}) -> (img, layouts)`.

Reproducibility: the pipeline owns its random state (`Compose(seed=...)`). `racklay.train`
re-seeds it per sample from (run seed, epoch, index) through `set_random_seed`, which makes a
resumed run repeat the same draws. Used elsewhere, note that albumentations 2.0.8 does not know
about DataLoader workers: every worker would start from the same state (and, with
non-persistent workers, replay the same draws every epoch). Unless `set_random_seed` has been
called, the pipeline therefore re-seeds itself on its first call in a worker process from
(seed, torch's per-worker seed), which torch derives from its own seed and changes every epoch.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class AugmentConfig:
    """Parameters of the paper's augmentation (defaults = the paper / reference repository)."""

    brightness: tuple[float, float] = (0.8, 1.2)
    contrast: tuple[float, float] = (0.8, 1.2)
    saturation: tuple[float, float] = (0.8, 1.2)
    hue: tuple[float, float] = (-0.1, 0.1)
    jitter_p: float = 0.5
    flip_p: float = 0.5

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


class PaperAugment:
    """Callable `(image uint8 HxWx3, {view: (R, S, S) uint8}) -> (image, layouts)`."""

    def __init__(self, seed: int | None = 0, config: AugmentConfig | None = None):
        import albumentations as A

        self.seed = seed
        self.config = c = config or AugmentConfig()
        self.compose = A.Compose(
            [A.ColorJitter(brightness=c.brightness, contrast=c.contrast, saturation=c.saturation,
                           hue=c.hue, p=c.jitter_p),
             A.HorizontalFlip(p=c.flip_p)],
            is_check_shapes=False, seed=seed, save_applied_params=True)
        self._worker_seed: int | None = None
        self._external_seed = False

    def set_random_seed(self, seed: int | None) -> None:
        """Re-seed the pipeline (racklay.train calls this per sample with a seed derived from
        (run seed, epoch, index)); from then on the worker re-seeding is off."""
        self._external_seed = True
        self.compose.set_random_seed(seed)

    def _reseed_in_worker(self) -> None:
        if self._external_seed:
            return
        try:
            from torch.utils.data import get_worker_info
        except ImportError:  # pragma: no cover - torch is a dependency
            return
        info = get_worker_info()
        if info is None or info.seed == self._worker_seed:
            return
        self._worker_seed = info.seed
        base = 0 if self.seed is None else int(self.seed)
        self.compose.set_random_seed(int(np.random.SeedSequence([base, info.seed % 2**63]).generate_state(1)[0]))

    def __call__(self, image: np.ndarray, layouts: dict[str, np.ndarray]):
        self._reseed_in_worker()
        image = np.ascontiguousarray(image)
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"augmentation expects an RGB uint8 image (H, W, 3), got {image.dtype} {image.shape}")
        views = list(layouts)
        stacks = {v: np.asarray(layouts[v]) for v in views}
        for v, s in stacks.items():
            if s.ndim != 3 or s.shape[1] != s.shape[2]:
                raise ValueError(f"{v} layouts must be (R, S, S), got {s.shape}")
        # one mask per shelf channel per view: albumentations transforms them with the image
        masks = [np.ascontiguousarray(stacks[v][r]) for v in views for r in range(stacks[v].shape[0])]
        out = self.compose(image=image, masks=masks)
        self.last_applied = out.get("applied_transforms", [])
        got = out["masks"]
        res, i = {}, 0
        for v in views:
            R = stacks[v].shape[0]
            res[v] = np.stack([np.asarray(m) for m in got[i:i + R]]).astype(stacks[v].dtype, copy=False) if R else stacks[v]
            i += R
        return out["image"], res

    def describe(self) -> dict:
        return {"name": "paper (colour jitter + horizontal flip, albumentations)", "seed": self.seed,
                **self.config.to_dict()}


def paper_augment(seed: int | None = 0) -> PaperAugment:
    """The paper's augmentation with its default parameters."""
    return PaperAugment(seed=seed)
