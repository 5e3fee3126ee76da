"""Checkpoints as safetensors: tensors plus JSON metadata, no pickle anywhere on the load path.

Layout of one file:
- tensors `model.<name>` (RackLayNet state dict), `disc.<name>` (discriminators, "-disc" runs),
  `optim.<opt>.<index>.<key>` (optimiser state tensors, for --resume);
- metadata key `racklay` = JSON {"format", "version", "config" (ModelConfig), "meta" (free-form:
  epoch, step, metrics, train config ...), "optim" ({opt: {"param_groups", "scalars"}})};
- metadata key `racklay_sha256` = SHA-256 over the `racklay` JSON and every tensor (name, dtype,
  shape, bytes; by name), checked on every load: a file whose bytes changed after it was written
  (a flipped bit, an edit) is refused with one line. Files written before the hash existed have
  no such key and load without the check.

    save_checkpoint(path, model, cfg, optimizer=None, extra=None, disc=None)
    model, cfg, meta = load_model(path)
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from .atomic import atomic_write_bytes
from .model import (
    GROWABLE_DECODERS,
    SAME_TENSOR_DECODERS,
    Discriminators,
    ModelConfig,
    RackLayNet,
    StructDecoder,
    grown_tensor_names,
)

FORMAT = "racklay-checkpoint"
VERSION = 1
HASH_KEY = "racklay_sha256"


def content_hash(header: str, tensors: dict) -> str:
    """SHA-256 (hex) of a checkpoint's header JSON and its tensors (name, dtype, shape and raw
    bytes of each, in name order): independent of how safetensors lays the file out."""
    h = hashlib.sha256()
    h.update(header.encode("utf-8"))
    for k in sorted(tensors):
        t = tensors[k].detach()
        if t.device.type != "cpu":
            t = t.cpu()
        t = t.contiguous().reshape(-1)
        h.update(f"\0{k}\0{str(t.dtype).removeprefix('torch.')}\0{tuple(tensors[k].shape)}\0".encode())
        h.update(t.view(torch.uint8).numpy())
    return h.hexdigest()


def _optimizers(optimizer) -> dict:
    if optimizer is None:
        return {}
    if isinstance(optimizer, dict):
        return optimizer
    return {"main": optimizer}


def _plain(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to("cpu").contiguous().clone()


def save_checkpoint(path: str | os.PathLike, model: torch.nn.Module, cfg: ModelConfig, optimizer=None,
                    extra: dict | None = None, disc: torch.nn.Module | None = None) -> Path:
    """Write model (+ discriminators, + optimiser state) atomically. `optimizer` is an
    Optimizer or a dict name -> Optimizer; `extra` must be JSON-serialisable."""
    from safetensors.torch import save

    model = getattr(model, "module", model)          # unwrap DDP
    tensors = {f"model.{k}": _plain(v) for k, v in model.state_dict().items()}
    if disc is not None:
        disc = getattr(disc, "module", disc)
        tensors.update({f"disc.{k}": _plain(v) for k, v in disc.state_dict().items()})
    optim_meta = {}
    for name, opt in _optimizers(optimizer).items():
        sd = opt.state_dict()
        scalars = {}
        for idx, st in sd["state"].items():
            for key, val in st.items():
                if isinstance(val, torch.Tensor):
                    tensors[f"optim.{name}.{idx}.{key}"] = _plain(val)
                else:
                    scalars[f"{idx}.{key}"] = val
        optim_meta[name] = {"param_groups": sd["param_groups"], "scalars": scalars}
    header = {"format": FORMAT, "version": VERSION, "config": cfg.to_dict(), "meta": extra or {},
              "optim": optim_meta}
    text = json.dumps(header)
    data = save(tensors, metadata={"racklay": text, HASH_KEY: content_hash(text, tensors)})
    return atomic_write_bytes(path, data)


@dataclass
class Checkpoint:
    path: Path
    cfg: ModelConfig
    meta: dict
    tensors: dict
    optim: dict

    def section(self, prefix: str) -> dict:
        p = prefix + "."
        return {k[len(p):]: v for k, v in self.tensors.items() if k.startswith(p)}

    def has_optimizer(self, name: str = "main") -> bool:
        return name in self.optim

    def load_optimizer(self, optimizer: torch.optim.Optimizer, name: str = "main") -> None:
        if name not in self.optim:
            raise ValueError(f"{self.path}: checkpoint has no optimiser state {name!r} (cannot resume)")
        om = self.optim[name]
        state: dict = {}
        pre = f"optim.{name}."
        for k, v in self.tensors.items():
            if k.startswith(pre):
                idx, key = k[len(pre):].split(".", 1)
                state.setdefault(int(idx), {})[key] = v
        for k, v in om["scalars"].items():
            idx, key = k.split(".", 1)
            state.setdefault(int(idx), {})[key] = v
        try:
            optimizer.load_state_dict({"state": state, "param_groups": om["param_groups"]})
        except (ValueError, KeyError) as e:
            raise ValueError(f"{self.path}: optimiser state {name!r} does not fit this model ({e})") from None

    def load_discriminators(self, disc: Discriminators) -> None:
        sd = self.section("disc")
        if not sd:
            raise ValueError(f"{self.path}: checkpoint has no discriminator weights")
        load_state_strict(disc, sd, self.path, "discriminator")


def load_state_strict(module: torch.nn.Module, sd: dict, path, what: str) -> None:
    """Load `sd` into `module`, refusing (one line naming `path` and `what`) any missing,
    unexpected or wrongly shaped tensor."""
    own = module.state_dict()
    missing = [k for k in own if k not in sd]
    extra = [k for k in sd if k not in own]
    shape = [k for k in own if k in sd and sd[k].shape != own[k].shape]
    if missing or extra or shape:
        raise ValueError(f"{path}: {what} weights do not match its config "
                         f"({len(missing)} missing, {len(extra)} unexpected, {len(shape)} wrong shape"
                         f"{', e.g. ' + (missing + extra + shape)[0]})")
    module.load_state_dict(sd, strict=True)


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> Checkpoint:
    """Read a checkpoint file (tensors + header). ValueError naming the file if it is not one."""
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            md = f.metadata() or {}
            header = md.get("racklay")
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as e:  # noqa: BLE001 - safetensors raises several types on bad input
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"{path}: not a readable safetensors checkpoint ({msg})") from None
    if header is not None and HASH_KEY in md and content_hash(header, tensors) != md[HASH_KEY]:
        raise ValueError(f"{path}: checkpoint content does not match its recorded SHA-256 (the file was "
                         "corrupted or modified after it was written); use another copy")
    if str(map_location) != "cpu":
        tensors = {k: v.to(map_location) for k, v in tensors.items()}
    if header is None:
        raise ValueError(f"{path}: safetensors file without RackLay metadata (not a racklay checkpoint)")
    try:
        h = json.loads(header)
        if h.get("format") != FORMAT:
            raise ValueError(f"format {h.get('format')!r}")
        if int(h.get("version", 0)) > VERSION:
            raise ValueError(f"version {h.get('version')} is newer than this toolkit ({VERSION})")
        cfg = ModelConfig.from_dict(h["config"])
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: bad RackLay checkpoint header ({e})") from None
    return Checkpoint(path=path, cfg=cfg, meta=h.get("meta", {}), tensors=tensors, optim=h.get("optim", {}))


def load_model(path: str | os.PathLike, map_location: str | torch.device = "cpu"):
    """-> (RackLayNet in eval mode, ModelConfig, meta dict)."""
    ck = load_checkpoint(path, map_location)
    model = RackLayNet(ck.cfg)
    load_state_strict(model, ck.section("model"), ck.path, "model")
    model.to(map_location).eval()
    return model, ck.cfg, ck.meta


# ----------------------------------------------------------------------------- compatibility
# of a checkpoint with the run that starts from it (racklay.train: --init, --teacher)


def config_mismatches(ckpt_cfg: ModelConfig, run, keys, views) -> list[str]:
    """What a checkpoint's config has that the run (a ModelConfig or TrainConfig) needs otherwise:
    one phrase per differing key in `keys`, and the run's views the checkpoint lacks."""
    problems = [f"{k} {getattr(ckpt_cfg, k)} (run: {getattr(run, k)})" for k in keys
                if getattr(ckpt_cfg, k) != getattr(run, k)]
    missing = [v for v in views if v not in ckpt_cfg.views]
    if missing:
        problems.append(f"views {list(ckpt_cfg.views)} lack {missing}")
    return problems


def load_grown(model: RackLayNet, sd: dict, decoder: str, path) -> None:
    """Load a checkpoint's weights into `model`. Same decoder, or one with the same tensors arranged
    differently (SAME_TENSOR_DECODERS: the model starts close to the checkpoint): every tensor,
    strictly. A decoder grown from the checkpoint's (GROWABLE_DECODERS, or a struct decoder given
    the 1/4 detail branch, the gap output or the back interval, `ModelConfig.struct_fine` /
    `struct_gap` / `struct_back`): every tensor the checkpoint has, strictly; the new branches keep
    their initialisation (made so that the model starts by computing what the checkpoint computed:
    a zero last layer, the gap output's and the back interval's logit bias at -6)."""
    own = model.state_dict()
    extra = sorted(set(sd) - set(own))
    if extra:
        raise ValueError(f"{path}: tensors {extra[:3]} have no place in a {model.cfg.decoder} model"
                         + (" (a struct model with the 1/4 detail branch, the gap output, the brightness cue or the "
                            "back interval? train with --struct-fine / --struct-gap / --struct-cue / --struct-back)"
                            if any(f".{sub}." in k for k in extra for sub in StructDecoder.GROWN) else ""))
    grown = grown_tensor_names(model) if (decoder, model.cfg.decoder) not in SAME_TENSOR_DECODERS else set()
    lacking = sorted(set(own) - set(sd) - grown)   # only the new branches may be new
    if lacking:
        raise ValueError(f"{path}: lacks tensors {lacking[:3]} that a {model.cfg.decoder} model has")
    model.load_state_dict({**own, **sd}, strict=True)


def check_init(ck: "Checkpoint", cfg) -> None:
    """Before fine-tuning from checkpoint `ck`: the run (a TrainConfig) must predict the same
    shelves and layout size with the same encoder and the same decoder (a struct one of the same
    width, fuse kernel and trunk sharing), or one it grows into or shares its tensors with (at the
    same input size when grown); else one error naming the file and every difference. Struct to
    struct, the layout size may differ: the structure's tensors do not depend on it (it is drawn at
    any size), so a model trained on 256² layouts can be fine-tuned on 512² ones."""
    c = ck.cfg
    struct = c.decoder == cfg.decoder == "struct"
    shape = ("struct_width", "struct_fuse_k", "struct_joint") if struct else ("layout_size",)
    problems = config_mismatches(c, cfg, ("R", "encoder") + shape, cfg.views)
    pair = (c.decoder, cfg.decoder)
    if c.decoder != cfg.decoder and pair not in GROWABLE_DECODERS and pair not in SAME_TENSOR_DECODERS:
        problems.append(f"decoder {c.decoder} (run: {cfg.decoder})")
    if pair in GROWABLE_DECODERS and c.input_hw != cfg.model_config().input_hw:
        problems.append(f"image_size {c.image_size} (run: {cfg.image_size}; a grown decoder keeps the input size)")
    if problems:
        raise ValueError(f"{ck.path}: cannot fine-tune from this checkpoint: it has " + "; ".join(problems))


__all__ = ["save_checkpoint", "load_checkpoint", "load_model", "load_state_strict", "Checkpoint", "content_hash",
           "config_mismatches", "load_grown", "check_init"]
