"""The ImageNet EfficientNet-Lite0 encoder: the architecture written here matches the weight file
shipped in the PyPI package (a wrong padding, normalisation or block order would not rank shop
shelves and cartons on real rack photos), the loader is strict, and the RackLay network built on
it handles non-square inputs."""
from __future__ import annotations

import pytest
import torch

from racklay.data import read_image
from racklay.model import (
    EfficientNetLite0Encoder,
    ModelConfig,
    RackLayNet,
    build_model,
    lite0_weights_path,
    load_lite0_weights,
)
from racklay.torchdata import image_to_tensor, prepare_image
from transfer.demo import PHOTOS  # the demo's real photos: one of each kind

#: ImageNet classes a rack photo plausibly shows: carton, crate, bookcase, bookshop, grocery store,
#: file cabinet, tobacco shop, shoe shop, library, forklift
PLAUSIBLE = {478, 519, 453, 454, 582, 553, 860, 788, 624, 561}


@pytest.mark.slow
def test_pretrained_classifier_ranks_rack_classes_on_real_photos():
    enc = EfficientNetLite0Encoder(with_classifier=True)
    load_lite0_weights(enc)
    enc.eval()
    photos = sorted(PHOTOS.glob("*.jpg"))
    assert len(photos) >= 20
    hits = []
    with torch.no_grad():
        for p in photos:
            x = image_to_tensor(prepare_image(read_image(p), 224))[None]
            top5 = set(enc.classify(x)[0].topk(5).indices.tolist())
            hits.append(bool(top5 & PLAUSIBLE))
    # measured: 19 of 21 (the two wrapped-pallet aisle shots read as vehicles); a randomly
    # initialised or mis-wired network gets about 5 % of photos by chance
    assert sum(hits) >= 0.8 * len(photos), f"{sum(hits)} of {len(photos)} photos with a plausible top-5 class"


def test_loader_is_strict(tmp_path):
    sd = torch.load(lite0_weights_path(), map_location="cpu", weights_only=True)
    enc = EfficientNetLite0Encoder()
    load_lite0_weights(enc)          # the classifier may be extra for an encoder without one
    assert torch.equal(enc._blocks[7]._depthwise_conv.weight, sd["_blocks.7._depthwise_conv.weight"])
    bad = dict(sd)
    del bad["_blocks.3._bn1.running_var"]
    torch.save(bad, tmp_path / "partial.pth")
    with pytest.raises(ValueError, match="partial.pth.*missing.*_blocks.3._bn1.running_var"):
        load_lite0_weights(enc, tmp_path / "partial.pth")
    bad = dict(sd)
    bad["_conv_head.weight"] = torch.zeros(1280, 192, 1, 1)
    torch.save(bad, tmp_path / "lite1ish.pth")
    with pytest.raises(ValueError, match="lite1ish.pth.*shape"):
        load_lite0_weights(enc, tmp_path / "lite1ish.pth")


def test_racklay_net_on_lite0_non_square_input():
    cfg = ModelConfig(R=2, image_size=(64, 96), layout_size=32, encoder="efficientnet-lite0")
    assert cfg.input_hw == (64, 96) and ModelConfig.from_dict(cfg.to_dict()) == cfg
    net = build_model(cfg, pretrained=True).eval()
    with torch.no_grad():
        out = net(torch.randn(2, 3, 64, 96))
    assert out["top"].shape == (2, 2, 3, 32, 32) and out["front"].shape == (2, 2, 3, 32, 32)
    with pytest.raises(ValueError, match="multiple of 32"):
        ModelConfig(image_size=(60, 96))
    with pytest.raises(ValueError, match="ResNet-18"):
        build_model(ModelConfig(R=2, image_size=64, layout_size=32, encoder="resnet18"), pretrained=True)
    assert isinstance(RackLayNet(ModelConfig(R=1, image_size=64, layout_size=16)).encoder, torch.nn.Module)
