"""Sim-to-real transfer: the paper's augmentation, pretrain -> finetune, compare (Table 2), and
their error messages. Tiny sizes throughout (image 64, layout 32) on toy datasets."""
from __future__ import annotations

import json
import shutil
import types
from pathlib import Path

import numpy as np
import pytest

from racklay import layout as L
from racklay.toy import build_toy_dataset
from transfer.augment import AugmentConfig, PaperAugment


# --------------------------------------------------------------------------- augmentation
def _asymmetric_sample(R=4, S=32, H=40, W=72):
    """An image whose left third is bright red with a white stripe, and layouts in which every
    channel of both views has its own off-centre content (so any column swap or channel mix-up
    shows)."""
    img = np.zeros((H, W, 3), np.uint8)
    img[:, : W // 3] = (200, 30, 30)
    img[5:9, 2:10] = 255
    img[:, W // 3: W // 2] = (20, 150, 40)
    lays = {}
    for k, v in enumerate(("top", "front")):
        a = np.zeros((R, S, S), np.uint8)
        for r in range(R):
            c0 = 1 + 3 * r + k
            a[r, 2 + r: 12 + r, c0: c0 + 6] = L.SHELF
            a[r, 4 + r: 8 + r, c0 + 1: c0 + 3 + r] = L.BOX
        lays[v] = a
    return img, lays


def test_flip_moves_image_and_every_layout_channel_together():
    img, lays = _asymmetric_sample()
    aug = PaperAugment(seed=0, config=AugmentConfig(jitter_p=0.0, flip_p=1.0))
    out, got = aug(img, {v: a.copy() for v, a in lays.items()})
    np.testing.assert_array_equal(out, img[:, ::-1])
    W, S = img.shape[1], 32
    for v in ("top", "front"):
        assert got[v].shape == lays[v].shape and got[v].dtype == np.uint8
        np.testing.assert_array_equal(got[v], L.hflip_layouts(lays[v]))
        for r in range(lays[v].shape[0]):
            # pixel correspondence: column c of the original is column S-1-c after the flip
            rows, cols = np.nonzero(lays[v][r] == L.BOX)
            assert (got[v][r][rows, S - 1 - cols] == L.BOX).all()
            assert not (got[v][r][rows, cols] == L.BOX).all()  # it really moved (off-centre content)
    # the image's red third is now on the right, and so is the marker stripe
    assert (out[:, -1] == (200, 30, 30)).all() and (out[5:9, W - 10: W - 2] == 255).all()


def test_random_draws_flip_image_and_layouts_consistently_and_keep_values():
    img, lays = _asymmetric_sample()
    aug = PaperAugment(seed=123)  # the paper's parameters: jitter p=0.5, flip p=0.5
    flips = jitters = 0
    for _ in range(40):
        out, got = aug(img, {v: a.copy() for v, a in lays.items()})
        applied = [name for name, _ in aug.last_applied]
        jittered = "ColorJitter" in applied
        # which way is the image? compare against both orientations (robust to colour jitter)
        d_same = np.abs(out.astype(int) - img).mean()
        d_flip = np.abs(out.astype(int) - img[:, ::-1]).mean()
        image_flipped = d_flip < d_same
        for v in ("top", "front"):
            expect = L.hflip_layouts(lays[v]) if image_flipped else lays[v]
            np.testing.assert_array_equal(got[v], expect)
            assert set(np.unique(got[v])) == set(np.unique(lays[v]))
        assert image_flipped == ("HorizontalFlip" in applied)
        flips += image_flipped
        jitters += jittered
    assert 8 <= flips <= 32 and 8 <= jitters <= 32  # both p = 0.5


def test_colour_jitter_never_touches_layouts():
    img, lays = _asymmetric_sample()
    aug = PaperAugment(seed=1, config=AugmentConfig(jitter_p=1.0, flip_p=0.0))
    changed = 0
    for _ in range(10):
        out, got = aug(img, {v: a.copy() for v, a in lays.items()})
        changed += not np.array_equal(out, img)
        for v in ("top", "front"):
            np.testing.assert_array_equal(got[v], lays[v])
    assert changed >= 9
    # jitter parameters within the paper's ranges
    params = dict(aug.last_applied)["ColorJitter"]
    assert 0.8 <= params["brightness"] <= 1.2 and -0.1 <= params["hue"] <= 0.1


def test_augmentation_is_reproducible_by_seed():
    img, lays = _asymmetric_sample()

    def run(seed):
        aug = PaperAugment(seed=seed)
        return [aug(img, lays)[0] for _ in range(8)]

    a, b, c = run(7), run(7), run(8)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


def test_augmentation_reseeds_per_dataloader_worker(monkeypatch):
    import torch.utils.data as tud

    img, lays = _asymmetric_sample()

    def draws(worker_seed):
        monkeypatch.setattr(tud, "get_worker_info", lambda: types.SimpleNamespace(seed=worker_seed, id=0))
        aug = PaperAugment(seed=5)
        return [tuple(n for n, _ in (aug(img, lays), aug.last_applied)[1]) for _ in range(16)]

    assert draws(1000) == draws(1000)
    assert draws(1000) != draws(1001)


def test_augmentation_plugs_into_racklay_dataset(tmp_path):
    from racklay.torchdata import RackLayDataset

    build_toy_dataset(tmp_path / "toy", n=6, seed=0, D=64)
    plain = RackLayDataset(tmp_path / "toy", split=None, image_size=64, layout_size=32)
    aug = RackLayDataset(tmp_path / "toy", split=None, image_size=64, layout_size=32,
                         transform=PaperAugment(seed=0, config=AugmentConfig(jitter_p=0.0, flip_p=1.0)))
    for i in range(len(plain)):
        a, b = plain[i], aug[i]
        assert b["image"].shape == (3, 64, 64) and b["top"].shape == (4, 32, 32)
        np.testing.assert_allclose(b["image"].numpy(), a["image"].numpy()[:, :, ::-1])
        for v in ("top", "front"):
            np.testing.assert_array_equal(b[v].numpy(), a[v].numpy()[..., ::-1])


def test_augmentation_rejects_bad_input():
    img, lays = _asymmetric_sample()
    aug = PaperAugment(seed=0)
    with pytest.raises(ValueError, match="RGB uint8"):
        aug(img.astype(np.float32), lays)
    with pytest.raises(ValueError, match=r"\(R, S, S\)"):
        aug(img, {"top": lays["top"][0]})
