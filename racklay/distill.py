"""`racklay distill`: a faster struct model that does what a trained one does.

The student is the teacher with narrower struct decoders (`--struct-width`, `--struct-fuse-k`,
no 1/4 detail branch): it keeps the teacher's encoder (copied and frozen) and learns the
teacher's structures (`racklay.structure.distill_structure_loss`: presence, length, extent,
placement, per-position box and gap logits, box heights and depth fractions) on images the
teacher reads: renders (`--data`) and photos (`--photos`, drawn `--photo-share` of the time, each
photo also in colour-jittered copies), every image also mirrored. No labels are used, so any
photos of the user's site can teach it; never the photos it will be scored on.

As the encoder is frozen, its features and the teacher's structures are computed once and held in
memory (fp16, ~0.2 MB per image at 256 x 160); training then runs the student's decoders alone,
~11 ms per image on 2 cores where a `racklay train` step of the full model costs ~150 ms. The
schedule is a time budget (`--minutes`) or a number of steps (`--steps`: the same student bit for
bit from the same seed): warm-up, then cosine decay over it, as `racklay train`'s
(`racklay.train.warmup_cosine`).
Measured against the shipped model and its speed: docs/model-card.md.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from .config import check_fields, option

#: where a distilled student reads its images from: "ROOT" or "ROOT:SPLIT"
DATA_SPEC = "ROOT[:SPLIT]"


@dataclass
class DistillConfig:
    """Every option of `racklay distill` (the flag of field foo_bar is --foo-bar)."""

    out: str = option("", "the student checkpoint to write (.safetensors)", metavar="FILE", path=True)
    teacher: str | None = option(None, "the struct model to distil (default: the shipped model)", metavar="CKPT")
    data: tuple = option((), f"renders (or any RackLay dataset) the teacher reads, {DATA_SPEC} (default split: "
                             "train); repeat the flag to pool several", action="append", metavar=DATA_SPEC)
    photos: tuple = option((), f"photos the teacher reads (a RackLay dataset, e.g. `annotate export`'s), {DATA_SPEC} "
                               "(default split: train); repeat to pool; never the photos you will score on",
                           action="append", metavar=DATA_SPEC)
    photo_share: float = option(0.15, "share of the training samples drawn from --photos (default {default})",
                                gt=0, lt=1)
    photo_jitter: int = option(2, "colour-jittered copies of each photo (the training augmentation's colour "
                                  "jitter, racklay/augment.py), beside the photo and its mirror image "
                                  "(default {default})", lo=0)
    struct_width: int = option(32, "the student's struct decoder width (racklay train's --struct-width; the "
                                   "teacher's is usually 128) (default {default})", lo=4)
    struct_fuse_k: int = option(1, "the student's fuse conv kernel (racklay train's --struct-fuse-k) "
                                   "(default {default})", choices=(1, 3))
    struct_joint: bool = option(False, "one struct trunk for both of the student's views, each keeping its own "
                                       "heads (racklay train's --struct-joint): up to a third less decoder time, "
                                       "2-3 box points lower on photos when measured (default {default})")
    gap_weight: float = option(5.0, "weight of the positions the teacher calls gaps between loads in the gap "
                                    "output's loss (1: unweighted; docs/training.md) (default {default})", lo=1)
    minutes: float = option(45.0, "training time budget in minutes, after the teacher's pass (default {default})",
                            gt=0)
    steps: int | None = option(None, "stop after this many steps, if sooner than --minutes", lo=1)
    batch_size: int = option(32, "images per step (default {default})", lo=1)
    lr: float = option(2e-3, "peak AdamW learning rate; warm-up, then cosine decay over the budget "
                             "(default {default})", gt=0)
    warmup_steps: int = option(100, "linear warm-up steps (default {default})", lo=0)
    weight_decay: float = option(1e-4, "AdamW weight decay (default {default})", lo=0)
    init: str = option("random", "how the student's decoders start: random (seeded) or pruned, the teacher's own "
                                 "decoder layers cut to the student's width, keeping each layer's channels of largest "
                                 "batch-norm scale (a 3 x 3 fuse conv summed to 1 x 1; the 1/4 branch dropped) "
                                 "(default {default})", choices=("random", "pruned"))
    seed: int = option(0, "seed of the student's initialisation, the jitter and the sampling (default {default})",
                       lo=0)

    def __post_init__(self):
        if not self.out:
            raise ValueError("--out: the student checkpoint to write is required")
        if not str(self.out).endswith(".safetensors"):
            raise ValueError(f"{self.out}: --out must be a .safetensors file")
        if not self.data and not self.photos:
            raise ValueError("nothing to distil on: give --data (renders) and/or --photos")
        check_fields(self)


def split_spec(spec: str) -> tuple[str, str]:
    """"ROOT" or "ROOT:SPLIT" -> (root, split); the split defaults to train."""
    root, sep, split = str(spec).rpartition(":")
    if not sep or not split or "/" in split or "\\" in split:
        return str(spec), "train"
    return root, split


def load_teacher(path: str | None):
    """(teacher in eval mode, its ModelConfig, its file) — a struct model, else one error naming the file."""
    from .checkpoint import load_model
    from .release import resolve_weights

    weights = resolve_weights(path, flag="--teacher")
    teacher, tcfg, _ = load_model(weights)
    if tcfg.decoder != "struct":
        raise ValueError(f"{weights}: has the {tcfg.decoder} decoder; distil needs a struct teacher")
    return teacher.requires_grad_(False), tcfg, weights


def student_for(teacher, tcfg, cfg: DistillConfig):
    """The student: the teacher's architecture with cfg's struct width, fuse kernel and trunk sharing, no 1/4
    branch, its encoder a frozen copy of the teacher's, its decoders freshly initialised (seeded), or
    with `init="pruned"` cut from the teacher's (`prune_decoder`).
    The teacher's decision biases (`racklay calibrate`), if any, carry over: the student learns
    the teacher's logits, so the same biases apply to them."""
    from .model import RackLayNet

    torch.manual_seed(cfg.seed)
    scfg = replace(tcfg, struct_width=cfg.struct_width, struct_fuse_k=cfg.struct_fuse_k, struct_fine=False,
                   struct_joint=cfg.struct_joint)
    student = RackLayNet(scfg)
    student.encoder.load_state_dict(teacher.encoder.state_dict())
    student.encoder.requires_grad_(False).eval()
    if cfg.init == "pruned":
        if tcfg.struct_joint or cfg.struct_joint:
            raise ValueError("--init pruned: needs a teacher and a student with a trunk per view (no --struct-joint)")
        if cfg.struct_width > tcfg.struct_width:
            raise ValueError(f"--init pruned: the student's width {cfg.struct_width} is wider than the teacher's "
                             f"{tcfg.struct_width}")
        for view, dec in student.decoders.items():
            prune_decoder(teacher.decoders[view], dec)
    return student, scfg


def _keep(bn_or_weight: torch.Tensor, n: int) -> torch.Tensor:
    """The n channels (sorted) with the largest |scale| (a batch norm's weight), or for a layer
    without a norm the largest row norms of its weight."""
    score = bn_or_weight.abs() if bn_or_weight.dim() == 1 else bn_or_weight.flatten(1).norm(dim=1)
    return score.topk(n).indices.sort().values


@torch.no_grad()
def prune_decoder(src, dst) -> None:
    """Start struct decoder `dst` (narrower, no 1/4 branch, same view, R and T) from `src`, the
    network-slimming way: every layer keeps the output channels of largest batch-norm scale, and
    the next layer reads those channels of its input. The reductions of the encoder's maps are
    copied whole; a 3 x 3 fuse conv becomes the 1 x 1 conv it is on a locally constant input (its
    taps summed); heads are cut to the kept channels. `dst` then computes roughly what `src`
    computed with its strongest channels alone, and distillation trains it from there."""
    def conv_bn(s, d, cin=None):
        """Copy conv-bn-relu `s` into `d`, keeping the outputs of largest scale; -> their indices."""
        keep = _keep(s[1].weight, d[1].weight.shape[0])
        w = s[0].weight[keep] if cin is None else s[0].weight[keep][:, cin]
        if w.shape[2:] != d[0].weight.shape[2:]:
            w = w.sum(dim=tuple(range(2, w.dim())), keepdim=True)
        d[0].weight.copy_(w)
        for name in ("weight", "bias", "running_mean", "running_var"):
            getattr(d[1], name).copy_(getattr(s[1], name)[keep])
        return keep

    for name in ("red8", "red16", "red32"):
        getattr(dst, name).load_state_dict(getattr(src, name).state_dict())
    C = src.shelf_emb.shape[1]
    k1 = conv_bn(src.fuse, dst.fuse)
    dst.row_att.weight.copy_(src.row_att.weight[:, k1])
    dst.row_att.bias.copy_(src.row_att.bias)
    dst.shelf_emb.copy_(src.shelf_emb[:, k1])
    k2 = conv_bn(src.img_seq[0], dst.img_seq[0], k1)
    k3 = conv_bn(src.img_seq[1], dst.img_seq[1], k2)
    lin = src.glob[0]
    k4 = _keep(lin.weight, dst.glob[0].weight.shape[0])
    dst.glob[0].weight.copy_(lin.weight[k4][:, torch.cat([k3, C + k3, 2 * C + k1])])
    dst.glob[0].bias.copy_(lin.bias[k4])
    n_pos = src.pos_seq[0][0].weight.shape[1] - 2 * C
    k = conv_bn(src.pos_seq[0], dst.pos_seq[0], torch.cat([k3, C + k4, 2 * C + torch.arange(n_pos)]))
    for i in (1, 2):
        k = conv_bn(src.pos_seq[i], dst.pos_seq[i], k)
    dst.shelf_head.weight.copy_(src.shelf_head.weight[:, k4])
    dst.shelf_head.bias.copy_(src.shelf_head.bias)
    heads = ("pos_head",) + (("gap_head",) if src.gap and dst.gap else ()) + (("back_head",) if src.back and dst.back else ())
    for h in heads:
        getattr(dst, h).weight.copy_(getattr(src, h).weight[:, k])
        getattr(dst, h).bias.copy_(getattr(src, h).bias)


def resolve_specs(specs) -> list[tuple]:
    """(dataset, ids, name) of every "ROOT[:SPLIT]" spec, all checked before any image is read:
    a missing folder, split or empty split is one error naming it."""
    from .data import RackLayRoot

    out = []
    for spec in specs:
        root, split = split_spec(spec)
        ds = RackLayRoot(root).require()
        ids = ds.resolve(split)
        if not ids:
            raise ValueError(f"{root}: split {split!r} holds no images")
        out.append((ds, ids, f"{root}:{split} ({len(ids)} images)"))
    return out


def read_images(sets, input_hw, letterbox: bool, jitter: int, seed: int, progress: bool) -> list:
    """The input-size images of every resolved set (`resolve_specs`), each also mirrored and in
    `jitter` colour-jittered copies, each mirrored or not at random: the training augmentation's
    colour jitter and flip (`racklay.augment`, the paper's ranges, the jitter always applied),
    seeded by `seed`."""
    from .augment import Augment, AugmentConfig
    from .torchdata import prepare_image

    aug = Augment(seed, AugmentConfig(jitter_p=1.0)) if jitter else None
    images = []
    for ds, ids, name in sets:
        it = ids
        if progress:
            from tqdm import tqdm
            it = tqdm(ids, desc=f"read {name}", unit="img", leave=False)
        for sid in it:
            im = prepare_image(ds.read_image(sid), input_hw, letterbox)
            images += [im, np.ascontiguousarray(im[:, ::-1])]
            images += [aug(im, {})[0] for _ in range(jitter)]
    return images


@torch.no_grad()
def teacher_pass(teacher, images: list, taps: tuple, progress: bool, batch: int = 16) -> tuple[dict, dict]:
    """The frozen encoder's features at `taps` (fp16) and the teacher's per-view structures (its
    decoders' own, before the views are tied) for every image."""
    from .structure import DISTILL_FIELDS
    from .torchdata import image_to_tensor

    feats = {k: [] for k in taps}
    structs = {v: {} for v in teacher.decoders}
    starts = range(0, len(images), batch)
    if progress:
        from tqdm import tqdm
        starts = tqdm(starts, desc="teacher", unit="batch", leave=False)
    for i in starts:
        f = teacher.features(torch.stack([image_to_tensor(a) for a in images[i:i + batch]]))
        for k in taps:
            feats[k].append(f[k].half())
        for v, st in teacher.structures(f).items():
            for k in DISTILL_FIELDS:
                if k in st:
                    structs[v].setdefault(k, []).append(st[k].float())
    return ({k: torch.cat(x) for k, x in feats.items()},
            {v: {k: torch.cat(x) for k, x in d.items()} for v, d in structs.items()})


def sample_weights(n_renders: int, n_photos: int, photo_share: float) -> np.ndarray:
    """Sampling probabilities: photos `photo_share` of the draws (all of them without renders), renders the rest."""
    if not n_photos or not n_renders:
        return np.full(n_renders + n_photos, 1.0 / (n_renders + n_photos))
    return np.concatenate([np.full(n_renders, (1 - photo_share) / n_renders), np.full(n_photos, photo_share / n_photos)])


def distill(cfg: DistillConfig, progress: bool = False, log=print) -> Path:
    """Distil cfg.teacher into a narrower struct student (module docstring); returns the checkpoint written."""
    from .checkpoint import save_checkpoint
    from .release import sha256_file
    from .structure import distill_structure_loss
    from .train import warmup_cosine

    t0 = time.time()
    rng = np.random.default_rng(cfg.seed)
    r_sets, p_sets = resolve_specs(cfg.data), resolve_specs(cfg.photos)
    r_names, p_names = [n for *_, n in r_sets], [n for *_, n in p_sets]
    teacher, tcfg, weights = load_teacher(cfg.teacher)
    student, scfg = student_for(teacher, tcfg, cfg)
    renders = read_images(r_sets, tcfg.input_hw, tcfg.letterbox, 0, cfg.seed, progress)
    photos = read_images(p_sets, tcfg.input_hw, tcfg.letterbox, cfg.photo_jitter, cfg.seed, progress)
    n_r, n_p = len(renders), len(photos)
    log(f"teacher {Path(weights).name}: {n_r} render samples ({', '.join(r_names) or 'none'}), {n_p} photo samples "
        f"({', '.join(p_names) or 'none'}), each image also mirrored")
    feats, targets = teacher_pass(teacher, renders + photos, (2, 3, 4), progress)   # what a student without the 1/4 branch reads
    del renders, photos
    mb = sum(f.numel() * f.element_size() for f in feats.values()) / 2**20
    log(f"teacher pass done in {time.time() - t0:.0f} s; features held in memory: {mb:.0f} MB")

    probs = sample_weights(n_r, n_p, cfg.photo_share)
    params = [p for name, p in student.named_parameters() if not name.startswith("encoder.")]
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    student.decoders.train()
    t1, budget, step, recent, first = time.time(), cfg.minutes * 60, 0, [], None
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=cfg.steps, desc="distil", unit="step", leave=False)
    while (time.time() - t1) < budget and (cfg.steps is None or step < cfg.steps):
        if cfg.steps:                                   # steps given: reproducible
            done = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
        else:
            done = (time.time() - t1) / budget
        for g in opt.param_groups:
            g["lr"] = warmup_cosine(cfg.lr, step, cfg.warmup_steps, done)
        idx = torch.from_numpy(rng.choice(len(probs), cfg.batch_size, p=probs))
        f = [None, None] + [feats[k][idx].float() for k in (2, 3, 4)]
        loss = sum(distill_structure_loss(v, st, {k: t[idx] for k, t in targets[v].items()}, cfg.gap_weight)
                   for v, st in student.structures(f).items())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        recent = (recent + [float(loss.detach())])[-200:]
        first = first if first is not None else recent[0]
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{np.mean(recent):.3f}")
        elif step % 500 == 0:
            log(f"step {step}: {(time.time() - t1) / 60:.1f} min, loss {np.mean(recent):.4f}")
    if bar is not None:
        bar.close()
    student.eval()
    minutes = (time.time() - t0) / 60
    meta = {"distilled_from": {"file": Path(weights).name, "sha256": sha256_file(weights)},
            "data": list(r_names), "photos": list(p_names), "steps": step, "batch_size": cfg.batch_size,
            "gap_weight": cfg.gap_weight,
            "seed": cfg.seed, "wall_minutes": round(minutes, 2), "threads": torch.get_num_threads(),
            "loss_first": first, "loss_last_200": float(np.mean(recent)) if recent else None}
    out = save_checkpoint(cfg.out, student, scfg, extra=meta)
    log(f"{step} steps, loss {first:.4f} -> {np.mean(recent):.4f} (mean of the last {len(recent)}); "
        f"{minutes:.1f} min in all; student written to {out}" if recent else f"no step done; student written to {out}")
    return out
