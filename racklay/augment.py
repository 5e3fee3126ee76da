"""Training augmentation, built on albumentations: the paper's (RackLay §5.5) and a stronger
photometric set for synthetic-to-real training.

- `paper`: colour jitter (brightness, contrast and saturation factors in [0.8, 1.2], hue shift
  within ±0.1, p = 0.5) and a horizontal flip (p = 0.5).
- `strong`: the paper's two, then what a camera does to a photo and a render does not: exposure
  and contrast (brightness/contrast, gamma), colour casts (RGB shift, hue/saturation), grey
  photos, sensor noise (Gaussian, ISO), motion and focus blur, down-scaling and JPEG; and, for
  models that letterbox their input (`ModelConfig.letterbox`), a random horizontal letterbox:
  the image is squeezed to a narrower aspect and padded, as a square or portrait photo is at
  prediction time (`racklay.torchdata.prepare_image`).

Every top- and front-view layout channel is handed to albumentations as a mask, so the flip that
albumentations applies to the image is the flip applied to the layouts: there is no hand-written
flip. The photometric transforms and the letterbox are image-only, so layouts never change
value: the layouts are metric, shelf-centred grids, and padding the photo changes no shelf.
Each level's span across the image (`spans`, image widths; placement supervision) is moved with
the image: mirrored by the flip (x -> 1 - x, ends swapped) and squeezed by the letterbox.

Layouts are D×D metric grids and photos are not, so `Compose(..., is_check_shapes=False)`:
albumentations 2.0.8 flips each mask by its own width (x -> -x in the shelf frame, exactly
`racklay.layout.hflip_layouts`). Geometric transforms other than flips would need the image
and the layouts to share a frame and are deliberately not offered.

Plugs into `racklay.torchdata.RackLayDataset(transform=...)` and `racklay.train.train(cfg,
transform=...)` (`TrainConfig.augment` names a preset): `aug(img_uint8_hwc, {view: (R, S, S)
uint8}) -> (img, layouts)`.

Reproducibility: the pipeline owns its random state (`Compose(seed=...)`). `racklay.train`
re-seeds it per sample from (run seed, epoch, index) through `set_random_seed`, which makes a
resumed run repeat the same draws. Used elsewhere, note that albumentations 2.0.8 does not know
about DataLoader workers: every worker would start from the same state (and, with
non-persistent workers, replay the same draws every epoch). Unless `set_random_seed` has been
called, the pipeline therefore re-seeds itself on its first call in a worker process from
(seed, torch's per-worker seed), which torch derives from its own seed and changes every epoch.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .config import AUGMENT_PRESETS as PRESETS
from .config import to_dict

# albumentations asks PyPI for its latest version when imported; nothing here goes online at run
# time (and on a machine without a network the lookup waits for DNS)
os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")


@dataclass(frozen=True)
class AugmentConfig:
    """Parameters of the augmentation (defaults = the paper / reference repository; `strong`
    switches on the camera set)."""

    brightness: tuple[float, float] = (0.8, 1.2)
    contrast: tuple[float, float] = (0.8, 1.2)
    saturation: tuple[float, float] = (0.8, 1.2)
    hue: tuple[float, float] = (-0.1, 0.1)
    jitter_p: float = 0.5
    flip_p: float = 0.5
    strong: bool = False          # the camera set (exposure, casts, grey, noise, blur, JPEG)
    letterbox_p: float = 0.0      # probability of a random horizontal letterbox
    letterbox_min: float = 0.45   # narrowest squeeze (fraction of the width kept)

    def to_dict(self) -> dict:
        return to_dict(self)


def preset_config(name: str, letterbox: bool = False) -> AugmentConfig | None:
    """The AugmentConfig of a preset name (None for 'none')."""
    if name not in PRESETS:
        raise ValueError(f"augment must be one of {PRESETS}, got {name!r}")
    if name == "none":
        return None
    if name == "paper":
        return AugmentConfig()
    return AugmentConfig(strong=True, letterbox_p=0.3 if letterbox else 0.0)


def _camera_transforms():
    import albumentations as A

    return [
        A.RandomBrightnessContrast(brightness_limit=(-0.35, 0.25), contrast_limit=(-0.3, 0.3), p=0.6),
        A.RandomGamma(gamma_limit=(70, 150), p=0.3),
        A.OneOf([A.RGBShift(r_shift_limit=(-20, 20), g_shift_limit=(-20, 20), b_shift_limit=(-20, 20)),
                 A.HueSaturationValue(hue_shift_limit=(-12, 12), sat_shift_limit=(-40, 30), val_shift_limit=(-20, 10))],
                p=0.4),
        A.ToGray(p=0.05),
        A.OneOf([A.GaussNoise(std_range=(0.01, 0.06)), A.ISONoise(color_shift=(0.01, 0.05), intensity=(0.1, 0.5))],
                p=0.35),
        A.OneOf([A.MotionBlur(blur_limit=(3, 7)), A.GaussianBlur(blur_limit=(3, 5))], p=0.25),
        A.Downscale(scale_range=(0.5, 0.9), p=0.15),
        A.ImageCompression(quality_range=(40, 95), p=0.4),
    ]


class Augment:
    """Callable `(image uint8 HxWx3, {view: (R, S, S) uint8}) -> (image, layouts)`, or with
    `spans=` (R, 2) level spans in image widths -> `(image, layouts, spans)`."""

    #: moves level spans with the image (`racklay.torchdata.RackLayDataset(spans=True)`)
    maps_spans = True

    def __init__(self, seed: int | None = 0, config: AugmentConfig | None = None):
        import albumentations as A

        self.seed = seed
        self.config = c = config or AugmentConfig()
        steps = [A.ColorJitter(brightness=c.brightness, contrast=c.contrast, saturation=c.saturation,
                               hue=c.hue, p=c.jitter_p),
                 A.HorizontalFlip(p=c.flip_p)]
        if c.strong:
            steps += _camera_transforms()
        self.compose = A.Compose(steps, is_check_shapes=False, seed=seed, save_applied_params=True)
        self._rng = np.random.default_rng(seed)
        self._worker_seed: int | None = None
        self._external_seed = False

    def set_random_seed(self, seed: int | None) -> None:
        """Re-seed the pipeline (racklay.train calls this per sample with a seed derived from
        (run seed, epoch, index)); from then on the worker re-seeding is off."""
        self._external_seed = True
        self.compose.set_random_seed(seed)
        self._rng = np.random.default_rng(seed)

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
        s = int(np.random.SeedSequence([base, info.seed % 2**63]).generate_state(1)[0])
        self.compose.set_random_seed(s)
        self._rng = np.random.default_rng(s)

    def __call__(self, image: np.ndarray, layouts: dict[str, np.ndarray], spans: np.ndarray | None = None):
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
        img = out["image"]
        if spans is not None:
            spans = np.asarray(spans, np.float32)
            if any(name == "HorizontalFlip" for name, _ in self.last_applied):
                spans = 1.0 - spans[:, ::-1]
        c = self.config
        if c.letterbox_p > 0 and self._rng.random() < c.letterbox_p:
            from .torchdata import padded_columns, squeeze_letterbox, squeeze_width

            keep = float(self._rng.uniform(c.letterbox_min, 1.0))
            if spans is not None:
                spans = padded_columns(spans, squeeze_width(img.shape[1], keep), img.shape[1])
            img = squeeze_letterbox(img, keep)
        return (img, res) if spans is None else (img, res, np.ascontiguousarray(spans))

    def describe(self) -> dict:
        name = "strong (paper + camera set" + (" + letterbox" if self.config.letterbox_p else "") + ")" \
            if self.config.strong else "paper (colour jitter + horizontal flip, albumentations)"
        return {"name": name, "seed": self.seed, **self.config.to_dict()}


#: the paper's augmentation class (kept under the name transfer has always used)
PaperAugment = Augment


def paper_augment(seed: int | None = 0) -> Augment:
    """The paper's augmentation with its default parameters."""
    return Augment(seed=seed)


def make_augment(name: str, seed: int | None = 0, letterbox: bool = False) -> Augment | None:
    """A preset by name ('none' -> None)."""
    cfg = preset_config(name, letterbox)
    return None if cfg is None else Augment(seed=seed, config=cfg)
