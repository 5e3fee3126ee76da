"""Training engine: `train(TrainConfig(...)) -> run directory`.

One run lives in `OUT/NAME/`: `config.yaml` (the resolved TrainConfig + ModelConfig),
`metrics.csv` (one row per epoch), `loss.png` and `metrics.png` (curves), `last.safetensors`
(model + discriminators + optimiser state + progress, for `resume`) and `best.safetensors` (the
epoch with the best validation score, weights only).

Loss (`racklay.losses`): per-shelf pixel cross-entropy with class weights (default [1, 5, 5] for
background, shelf, box) summed over views; in "-disc" runs, from epoch `disc_start` on, + λ·L_adv
with one least-squares patch discriminator per view that sees the decoder's softmax probabilities
(so its gradient reaches the decoder) and the one-hot ground truth. Adam, linear warm-up + cosine
decay per step, early stopping on the validation score = mean over views of the dataset-level IoU
of shelf and box (`racklay.metrics.LayoutMetrics`).

Determinism and resume (the process group, seeds and batches: `racklay.distributed`): the order
of samples in epoch e is a pure function of (seed, e) (a DistributedSampler seeded with `seed`,
`set_epoch(e)`); a transform gets, per sample, global RNGs
(and its own `reseed(int)` / `set_random_seed(int)` if it has one) seeded from (seed, e, index).
`last.safetensors` is written every `checkpoint_every` steps and at each epoch end with the step
within the epoch; `resume` reloads it and skips the batches already done. Killed at any point
(SIGKILL included: files are written atomically), a resumed run repeats the same computation and
ends with the same weights and metrics as an uninterrupted one (bit-for-bit on the same machine,
thread count and world size; see docs/training.md).

Multi-process: started under `torchrun`, RANK/WORLD_SIZE/LOCAL_RANK select a process group (gloo
on CPU, nccl on GPU), the model is wrapped in DistributedDataParallel, each process reads its
shard of every epoch, and only rank 0 validates and writes files.
"""
from __future__ import annotations

import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from .checkpoint import check_init, config_mismatches, load_grown
from .config import PATH_FIELDS, RUN_DEFINING, TrainConfig
from .distributed import Batches, Dist, Seeded, epoch_batches, seed_everything
from .history import history_row, write_history
from .losses import (
    distill_loss,
    layout_iou_loss,
    layout_loss,
    lsgan_discriminator_loss,
    lsgan_generator_loss,
    one_hot_layouts,
)
from .model import (
    Discriminators,
    ModelConfig,
    RackLayNet,
    load_imagenet_weights,
    load_lite0_weights,
)
from .precision import resolve_precision
from .structure import structure_loss

# ----------------------------------------------------------------------------- helpers


def warmup_cosine(peak: float, step: int, warmup_steps: int, t: float) -> float:
    """The learning rate of step `step`: linear warm-up over `warmup_steps`, then cosine decay to
    1% of `peak` as `t` (the fraction of the decay done) goes from 0 to 1."""
    if step < warmup_steps:
        return peak * (step + 1) / warmup_steps
    return peak * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(1.0, t))))


def lr_at(step: int, total: int, cfg: TrainConfig, elapsed_s: float = 0.0) -> float:
    """`warmup_cosine` decaying over the steps after warm-up up to `total` or, with `schedule:
    time`, over the time budget if that comes first (`elapsed_s` of it spent)."""
    t = min(1.0, (step - cfg.warmup_steps) / max(1, total - cfg.warmup_steps))
    if cfg.schedule == "time":
        t = max(t, min(1.0, elapsed_s / (cfg.max_minutes * 60)))
    return warmup_cosine(cfg.lr, step, cfg.warmup_steps, t)


def load_teacher(cfg: TrainConfig, device) -> RackLayNet:
    """The distillation teacher in eval mode without gradients; it must see the same input (size,
    letterboxing) and give the run's layouts (R, layout size, views)."""
    from .checkpoint import load_model

    teacher, tc, _ = load_model(cfg.teacher, map_location=device)
    mc = cfg.model_config()
    problems = config_mismatches(tc, mc, ("R", "layout_size", "letterbox"), cfg.views)
    if tc.input_hw != mc.input_hw:
        problems.append(f"input {tc.input_hw} (run: {mc.input_hw})")
    if problems:
        raise ValueError(f"{cfg.teacher}: cannot be the teacher of this run: it has " + "; ".join(problems))
    return teacher.requires_grad_(False)


def split_ids(cfg: TrainConfig) -> tuple[list[str], list[str]]:
    from .data import RackLayRoot, make_splits

    root = RackLayRoot(cfg.data).require()
    train = root.resolve(cfg.train_split)
    if cfg.val_fraction:
        parts = make_splits(train, {"train": 1 - cfg.val_fraction, "val": cfg.val_fraction}, seed=cfg.seed)
        train, val = parts["train"], parts["val"]
    else:
        if cfg.val_split not in root.splits():
            raise ValueError(f"{root.split_path(cfg.val_split)}: no validation split "
                             f"(splits: {', '.join(root.splits()) or 'none'}); use --val-fraction to carve one "
                             f"from {cfg.train_split}")
        val = root.resolve(cfg.val_split)
    if cfg.train_fraction < 1:
        order = list(train)
        np.random.default_rng(cfg.seed + 1).shuffle(order)
        train = sorted(order[:max(1, round(cfg.train_fraction * len(order)))])
    if len(train) < 2:
        raise ValueError(f"{root.root}: training split has {len(train)} sample(s); need at least 2")
    if not val:
        raise ValueError(f"{root.root}: validation set is empty")
    return train, val


def replay_ids(cfg: TrainConfig) -> list[list[str]]:
    """The pool of `--replay`, per replay root: its train split (all its samples if it has no
    split files). Each root's R must match the run's; its layouts are resized to the layout size
    like the data's."""
    from .data import RackLayRoot

    pools = []
    for path in cfg.replay:
        root = RackLayRoot(path).require("replay dataset")
        ids = root.resolve("train" if "train" in root.splits() else None)
        if not ids:
            raise ValueError(f"{root.root}: replay dataset has no samples")
        shape = root.layout_shape(ids[:50])
        if shape is not None and shape[0] != cfg.R:
            raise ValueError(f"{root.root}: replay layouts have R={shape[0]} shelves, the run has R={cfg.R}")
        pools.append(ids)
    return pools


@torch.no_grad()
def validate(model, loader, cfg: TrainConfig, weight, device, progress=False, bf16: bool = False) -> dict:
    """Validation loss and LayoutMetrics result on a loader."""
    from tqdm import tqdm

    from .metrics import LayoutMetrics
    from .predict import decide

    was = model.training
    model.eval()
    m = LayoutMetrics()
    loss, n = 0.0, 0
    for batch in tqdm(loader, desc="val", leave=False, disable=not progress):
        x = batch["image"].to(device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            out = model(x)
        for v, logits in out.items():
            tgt = batch[v].to(device)
            loss += float(layout_loss(logits, tgt, weight)) * x.shape[0]
            # numpy's argmax: torch's over the 3-class axis of (B, R, 3, S, S) takes 0.4-0.8 s a batch on CPU,
            # 10x numpy's, and was 3/4 of a struct run's validation
            m.update(v, decide(logits.detach().float().cpu().numpy()), batch[v].numpy())
        n += x.shape[0]
    model.train(was)
    res = m.result()
    return {"loss": loss / max(1, n), "result": res, "score": val_score(res)}


def val_score(result: dict) -> float:
    """Mean over views of the dataset-level IoU of shelf and box (nan classes count as 0)."""
    vals = []
    for v in result:
        for c in ("shelf", "box"):
            x = result[v]["dataset"][c]["IoU"]
            vals.append(0.0 if x != x else x)
    return float(np.mean(vals)) if vals else 0.0


def write_config(run_dir: Path, cfg: TrainConfig) -> None:
    import yaml

    from .atomic import atomic_write_text

    d = cfg.to_dict()
    d["model"] = cfg.model_config().to_dict()
    atomic_write_text(run_dir / "config.yaml", yaml.safe_dump(d, sort_keys=False))


# ----------------------------------------------------------------------------- train


@dataclass
class RunState:
    """A run's progress: saved with every last.safetensors (its meta), restored by resume."""
    epoch: int = 0                   # the current epoch (0-based)
    step: int = 0                    # steps done within it
    global_step: int = 0
    history: list = field(default_factory=list)   # metrics.csv, one row per epoch
    best_score: float = -1.0
    best_epoch: int = -1
    bad_epochs: int = 0              # epochs since the best one (early stopping)
    elapsed_s: float = 0.0           # training time over every start of the run (the time budget)
    finished: bool = False
    stop_reason: str = ""
    epoch_sums: dict | None = None   # the interrupted epoch's running loss sums


@dataclass
class Run:
    """What the training helpers share: settings, process group, models, optimisers, files, clock."""
    cfg: TrainConfig
    dist: Dist
    dir: Path
    model: RackLayNet
    disc: Discriminators | None
    optimizers: dict                 # "gen" (+ "disc")
    bf16: bool
    channels_last: bool
    weight: torch.Tensor             # cross-entropy class weights
    t_start: float
    base_elapsed: float = 0.0        # elapsed_s when this start of the run began
    teacher: RackLayNet | None = None     # distillation teacher (cfg.teacher), eval mode
    anchor: dict | None = None            # --anchor-weight: parameter -> its --init value
    gen: torch.nn.Module | None = None    # the model as trained this epoch (DDP-wrapped in multi-process runs)
    frozen: bool | None = None       # whether the encoder is frozen in `gen`

    @property
    def mcfg(self) -> ModelConfig:
        return self.cfg.model_config()

    def elapsed(self) -> float:
        return self.base_elapsed + time.time() - self.t_start

    def budget_over(self) -> bool:
        over = self.cfg.max_minutes is not None and self.elapsed() >= self.cfg.max_minutes * 60
        return self.dist.broadcast_flag(over)


def train(cfg: TrainConfig, transform=None) -> Path:
    """Train (or resume) a run; returns its directory."""
    from tqdm import tqdm

    t_start = time.time()
    dist = Dist(cfg.device)
    run_dir = cfg.run_dir()
    made_dir = False   # this call created the run folder (removed again if it fails before a checkpoint)
    try:
        if dist.device.type == "cpu":
            torch.set_num_threads(cfg.threads or max(1, (os.cpu_count() or 1) // dist.world))
        elif cfg.threads:   # on a GPU the host threads of the training process (its loader workers need cores)
            torch.set_num_threads(cfg.threads)
        resume_ck = open_resume(cfg, run_dir, dist.main)
        run = build_run(cfg, dist, run_dir, t_start, init=resume_ck is None)
        st = RunState() if resume_ck is None else restore(run, resume_ck)
        del resume_ck
        if st.finished:
            if dist.main:
                print(f"{run_dir}: run already finished ({st.stop_reason})")
            return run_dir
        train_ds, loader, batches, val_loader, checked = make_loaders(cfg, transform, dist, run_dir)
        steps_per_epoch = len(epoch_batches(len(train_ds), cfg.batch_size, 0, cfg.seed, dist.world, dist.rank))
        total_steps = steps_per_epoch * cfg.epochs
        if dist.main:
            made_dir = not run_dir.exists()
            start_run_dir(run, getattr(train_ds, "n_real", len(train_ds)), len(val_loader.dataset),
                          getattr(train_ds, "n_replay", 0))
            from .atomic import atomic_write_json
            atomic_write_json(run_dir / DATA_CHECK, checked)
        run.base_elapsed = st.elapsed_s
        stop = False
        while st.epoch < cfg.epochs and not stop:
            epoch = st.epoch
            gen, disc = models_for_epoch(run, epoch)
            all_batches = epoch_batches(len(train_ds), cfg.batch_size, epoch, cfg.seed, dist.world, dist.rank)
            batches.batches = [[(i, epoch) for i in b] for b in all_batches[st.step:]]
            sums = {"loss": 0.0, "ce": 0.0, "iou": 0.0, "adv": 0.0, "disc": 0.0,
                    **({"kd": 0.0} if cfg.teacher else {}), **({"struct": 0.0} if cfg.decoder == "struct" else {}),
                    **(st.epoch_sums or {})}
            t_epoch = time.time()
            bar = tqdm(total=len(all_batches), initial=st.step, desc=f"epoch {epoch + 1}/{cfg.epochs}",
                       disable=not (cfg.progress and dist.main), dynamic_ncols=True)
            for batch in loader:
                lr = lr_at(st.global_step, total_steps, cfg, run.elapsed())
                for g in run.optimizers["gen"].param_groups:
                    g["lr"] = lr * g.get("lr_mult", 1.0)
                losses = train_step(run, gen, disc, batch)
                count_step(st, sums, losses)
                bar.update(1)
                bar.set_postfix(loss=f"{sums['loss'] / st.step:.4f}", lr=f"{lr:.2e}")
                over = run.budget_over()
                st.elapsed_s = run.elapsed()
                if over:
                    stop = True
                    st.stop_reason = f"time budget of {cfg.max_minutes} min reached"
                    break
                if cfg.checkpoint_every and st.step % cfg.checkpoint_every == 0 and st.step < len(all_batches):
                    save_last(run, st)
            bar.close()
            # epoch end (or budget stop mid-epoch): validate, record, checkpoint
            stop = end_of_epoch(run, st, sums, val_loader, len(all_batches), total_steps, t_epoch, stop)
        if dist.main:
            print(f"{run_dir}: {st.stop_reason}; best val score {st.best_score:.4f} "
                  f"(epoch {st.best_epoch + 1}), {st.elapsed_s / 60:.1f} min")
        return run_dir
    except BaseException:
        # a run that fails before its first checkpoint (bad data, a mismatched R, Ctrl-C) leaves
        # no folder behind: nothing in it could be resumed, and its name stays free
        if dist.main and made_dir and not (run_dir / "last.safetensors").exists():
            shutil.rmtree(run_dir, ignore_errors=True)
        raise
    finally:
        dist.close()


def open_resume(cfg: TrainConfig, run_dir: Path, main: bool):
    """The checkpoint to resume (None for a new run), checked against `cfg`; removes half-written
    checkpoints of a killed run and refuses to start a new run over an existing one."""
    from .checkpoint import load_checkpoint

    last_path = run_dir / "last.safetensors"
    if main and run_dir.is_dir():
        from .atomic import remove_stale_temps
        for name in ("last.safetensors", "best.safetensors"):
            remove_stale_temps(run_dir, name)
    if not cfg.resume:
        if last_path.exists():
            raise ValueError(f"{run_dir}: run exists; pass --resume to continue it or choose another --name")
        return None
    if not last_path.is_file():
        raise FileNotFoundError(f"{last_path}: nothing to resume (no last checkpoint)")
    ck = load_checkpoint(last_path)
    saved = ck.meta.get("train_config", {})
    diff = [k for k in RUN_DEFINING if k in saved and not _same_setting(k, saved[k], getattr(cfg, k))]
    if diff:
        raise ValueError(f"{last_path}: resume must keep the run's settings; differs in "
                         + ", ".join(f"{k} ({saved[k]!r} vs {getattr(cfg, k)!r})" for k in diff))
    return ck


def param_groups(model: torch.nn.Module, cfg: TrainConfig, init_names: set | None = None) -> list[dict]:
    """The generator's Adam parameter groups over the weights that train (`--train-only` leaves
    out the rest): one, or with `--init` and `--new-lr-mult` a second for the tensors the init
    checkpoint lacks (the branches the model grows), whose learning rate is `new_lr_mult` times
    the schedule's (`lr_mult`, applied each step). `init_names`: the init checkpoint's model
    tensor names where the caller has read it; None (a `--resume`, which restores its weights from
    the run's own checkpoint) reads them from `cfg.init`, so a resumed run has the same groups."""
    named = [(n, p) for n, p in model.named_parameters() if p.requires_grad]
    if not cfg.init or cfg.new_lr_mult == 1.0:
        return [{"params": [p for _, p in named], "lr_mult": 1.0}]
    if init_names is None:
        from .checkpoint import load_checkpoint

        init_names = set(load_checkpoint(cfg.init).section("model"))
    new = [p for n, p in named if n not in init_names]
    if not new:
        raise ValueError(f"--new-lr-mult {cfg.new_lr_mult:g}: the model grows nothing from {cfg.init} "
                         "(every tensor is in the checkpoint)")
    return [{"params": [p for n, p in named if n in init_names], "lr_mult": 1.0},
            {"params": new, "lr_mult": cfg.new_lr_mult}]


def freeze_to(model: torch.nn.Module, parts: tuple) -> None:
    """`--train-only`: every weight whose name contains none of `parts` stops training (the
    optimiser never sees it; `models_for_epoch` also keeps the BatchNorm layers with no trainable
    weight in eval mode, so their statistics stay the init's too). A part that names no weight is
    an error, so a typo cannot silently train nothing."""
    names = [n for n, _ in model.named_parameters()]
    unknown = [part for part in parts if not any(part in n for n in names)]
    if unknown:
        raise ValueError(f"train_only: no weight of this model is named like {', '.join(map(repr, unknown))} "
                         f"(names look like {names[0]!r})")
    for n, p in model.named_parameters():
        p.requires_grad_(any(part in n for part in parts))


def build_run(cfg: TrainConfig, dist: Dist, run_dir: Path, t_start: float, init: bool) -> Run:
    """Seeded models (initialised from `cfg.init` or ImageNet weights when `init`) on the device,
    their optimisers and the precision."""
    from .checkpoint import load_checkpoint

    device, mcfg = dist.device, cfg.model_config()
    seed_everything(cfg.seed)
    model = RackLayNet(mcfg)
    disc = Discriminators(mcfg) if cfg.disc else None
    init_names = None                     # the init checkpoint's tensor names, once read (param_groups)
    if init and cfg.init:
        ck = load_checkpoint(cfg.init)
        check_init(ck, cfg)
        load_grown(model, ck.section("model"), ck.cfg.decoder, ck.path)
        init_names = set(ck.section("model"))
    elif init and cfg.imagenet_weights:
        load_imagenet_weights(model.encoder, cfg.imagenet_weights)
    elif init and cfg.pretrained and cfg.encoder == "efficientnet-lite0":
        load_lite0_weights(model.encoder)
    model.to(device)
    if disc is not None:
        disc.to(device)
    bf16 = resolve_precision(cfg.amp, device) == "bf16"
    # channels_last: faster convolutions on CPU (oneDNN) in fp32 too (measured 12 % per step for
    # EfficientNet-Lite0 at 160x256), and what bf16 autocast wants
    channels_last = bf16 or device.type == "cpu"
    teacher = load_teacher(cfg, device) if cfg.teacher else None
    if channels_last:
        model.to(memory_format=torch.channels_last)
        if teacher is not None:
            teacher.to(memory_format=torch.channels_last)
    anchor = None
    if cfg.anchor_weight:
        held = (ck if init else load_checkpoint(cfg.init)).section("model")   # a resumed run pulls toward --init too
        anchor = {p: torch.empty_like(p).copy_(held[n]) for n, p in model.named_parameters()
                  if n in held and held[n].shape == p.shape}
    if cfg.train_only:
        freeze_to(model, cfg.train_only)
    optimizers = {"gen": torch.optim.Adam(param_groups(model, cfg, init_names), lr=cfg.lr, weight_decay=cfg.weight_decay)}
    if disc is not None:
        optimizers["disc"] = torch.optim.Adam(disc.parameters(), lr=cfg.disc_lr, betas=(0.5, 0.999))
    weight = torch.tensor(cfg.class_weights, dtype=torch.float32, device=device)
    return Run(cfg, dist, run_dir, model, disc, optimizers, bf16, channels_last, weight, t_start, teacher=teacher,
               anchor=anchor)


@torch.no_grad()
def pull_to_anchor(run: Run) -> None:
    """--anchor-weight λ: every anchored weight w <- w + λ·lr·(w_init - w), at its group's current
    learning rate (decoupled from Adam's scaling, as AdamW's decay, but toward the start)."""
    for group in run.optimizers["gen"].param_groups:
        k = min(1.0, run.cfg.anchor_weight * group["lr"])
        for p in group["params"]:
            start = run.anchor.get(p)
            if start is not None:
                p.lerp_(start, k)


def restore(run: Run, ck) -> RunState:
    """Weights, optimiser state and progress from the resumed checkpoint. A run stopped by its
    time budget is not finished any more when a larger `max_minutes` leaves time and epochs."""
    from .checkpoint import load_state_strict

    device = run.dist.device
    load_state_strict(run.model, {k: v.to(device) for k, v in ck.section("model").items()}, ck.path, "model")
    if run.disc is not None:
        ck.load_discriminators(run.disc)
    for name, opt in run.optimizers.items():
        ck.load_optimizer(opt, name)
    st = RunState(**{f.name: ck.meta[f.name] for f in fields(RunState) if f.name in ck.meta})
    cfg = run.cfg
    budget_left = cfg.max_minutes is None or st.elapsed_s < cfg.max_minutes * 60
    if st.finished and st.stop_reason.startswith("time budget") and budget_left and st.epoch < cfg.epochs:
        st.finished = False
    return st


#: files of the run's data that passed the check before the first step (racklay.data.check_samples)
DATA_CHECK = "data-check.json"


def check_run_data(cfg: TrainConfig, run_dir: Path, train_ids, val_ids) -> dict:
    """Every training and validation sample checked before the first step (image header, layouts
    present with strict values, the run's R, one layout size), as `racklay check-data` would: a bad
    file fails the run in seconds, naming it, not at step 7 or after an epoch; in `workers`
    processes. Files that passed in an earlier start of the run (run_dir/data-check.json) and are
    unchanged are not read again.
    Returns the updated record of passed files."""
    import json

    from .data import VIEW_DIRS, DataError, RackLayRoot, check_samples

    have = RackLayRoot(cfg.data).views()
    missing = [v for v in cfg.views if v not in have]
    if missing:    # a view-specific dataset: say so, rather than one missing file per sample
        raise DataError(f"{cfg.data}: has no {'/'.join(missing)} layouts (no {VIEW_DIRS[missing[0]]}/ folder); "
                        f"train on the views it has with --views {','.join(have) or '?'}")
    passed = {}
    cache = run_dir / DATA_CHECK
    if cache.is_file():
        try:
            passed = json.loads(cache.read_text())
        except (OSError, ValueError):
            passed = {}
    ids = list(dict.fromkeys([*train_ids, *val_ids]))
    sizes: dict = {}
    problems, _ = check_samples(cfg.data, ids, cfg.views, R=cfg.R, passed=passed, progress=cfg.progress,
                                sizes=sizes, workers=cfg.workers)
    if problems:
        more = f" (and {len(problems) - 1} more: racklay check-data {cfg.data})" if len(problems) > 1 else ""
        raise DataError(f"training data not usable: {problems[0]}{more}")
    if len(sizes) > 1:     # allowed (photos vary), never silent: each is resized to the input
        (w, h), common = max(sizes.items(), key=lambda kv: len(kv[1]))
        odd = [(p, wh) for wh, paths in sizes.items() if wh != (w, h) for p in paths]
        print(f"warning: {len(odd)} image(s) are not {w}x{h} like the other {len(common)} (e.g. {odd[0][0]}: "
              f"{odd[0][1][0]}x{odd[0][1][1]}); every image is resized to the model's input", flush=True)
    return passed


def check_level_spans(ds) -> None:
    """Placement supervision needs labelled level spans (`racklay.data.level_spans`): every
    sample's are read (a malformed one names its file) and a training set without any fails here,
    before the first step; how many samples have them is said."""
    from .data import DataError

    n = sum(bool(np.isfinite(ds.root.read_level_spans(sid, ds.R)).any()) for sid in ds.ids)
    if not n:
        raise DataError(f"{ds.root.root}: --placement-weight needs level_spans in the training samples' meta "
                        f"(photos exported by annotate export and renders of racklay synth have them) and none of {len(ds.ids)} has")
    print(f"placement supervision: {n} of {len(ds.ids)} training samples have labelled level spans", flush=True)


def make_loaders(cfg: TrainConfig, transform, dist: Dist, run_dir: Path):
    """(training dataset, its loader, the loader's batch sampler, validation loader (rank 0 only), the
    record of checked files), after `check_run_data`."""
    from .torchdata import RackLayDataset, ReplayMix, data_loader

    train_ids, val_ids = split_ids(cfg)
    checked = check_run_data(cfg, run_dir, train_ids, val_ids)
    kw = dict(image_size=cfg.image_size, layout_size=cfg.layout_size, views=cfg.views, R=cfg.R, cache=cfg.cache)
    if transform is None and cfg.augment != "none":
        from .augment import make_augment
        transform = make_augment(cfg.augment, seed=cfg.seed, letterbox=cfg.letterbox)
    kw["letterbox"] = cfg.letterbox
    train_ds = RackLayDataset(cfg.data, ids=train_ids, transform=transform, spans=cfg.placement_weight > 0, **kw)
    if cfg.placement_weight:
        check_level_spans(train_ds)
    if cfg.replay:
        pools = [RackLayDataset(path, ids=ids, **{**kw, "cache": False}) for path, ids in zip(cfg.replay, replay_ids(cfg))]
        train_ds = ReplayMix(train_ds, pools, cfg.replay_ratio, seed=cfg.seed)
    val_ds = RackLayDataset(cfg.data, ids=val_ids, **kw) if dist.main else None
    batches = Batches()
    pin = dist.device.type == "cuda"   # page-locked batches: the copy to the GPU overlaps the step
    loader = data_loader(Seeded(train_ds, cfg.seed), cfg.workers, batch_sampler=batches,
                         persistent_workers=cfg.workers > 0, pin_memory=pin)
    val_loader = (data_loader(val_ds, cfg.workers, batch_size=cfg.batch_size, shuffle=False, pin_memory=pin)
                  if dist.main else None)
    return train_ds, loader, batches, val_loader, checked


def start_run_dir(run: Run, n_train: int, n_val: int, n_replay: int = 0) -> None:
    """Create the run folder, write config.yaml and say what is being trained."""
    cfg, mcfg = run.cfg, run.mcfg
    run.dir.mkdir(parents=True, exist_ok=True)
    write_config(run.dir, cfg)
    hw = mcfg.input_hw
    replay = f" + {n_replay} replay from {' + '.join(cfg.replay)} (new each epoch)" if n_replay else ""
    print(f"{mcfg.variant()} ({cfg.encoder} encoder, {cfg.decoder}{' + 1/4 detail' if cfg.struct_fine else ''}{' + gap output' if cfg.struct_gap else ''}{' + back interval' if cfg.struct_back else ''} decoder), {n_train} train{replay} / "
          f"{n_val} val images, {hw[1]}x{hw[0]}->{cfg.layout_size}, {'bf16' if run.bf16 else 'fp32'}, "
          f"{run.dist.world} process(es) on {run.dist.device}, "
          f"{torch.get_num_threads()} thread(s) each -> {run.dir}")


def models_for_epoch(run: Run, epoch: int):
    """(generator, discriminators or None) as trained in `epoch`: the encoder frozen during the
    first `freeze_encoder_epochs`, every BatchNorm in eval mode with `freeze_bn` (with `train_only`,
    those with no trainable weight), the discriminators from `disc_start` on; DDP-wrapped in a
    multi-process run (re-wrapped when the trainable set changes)."""
    from torch.nn.parallel import DistributedDataParallel as DDP

    cfg, dist = run.cfg, run.dist
    ids = [dist.device.index] if dist.device.type == "cuda" else None
    frozen = epoch < cfg.freeze_encoder_epochs
    if frozen != run.frozen:
        if cfg.freeze_encoder_epochs:    # (`train_only`, which excludes it, set what trains once: `freeze_to`)
            for p in run.model.encoder.parameters():
                p.requires_grad_(not frozen)
        run.gen = DDP(run.model, device_ids=ids) if dist.enabled else run.model
        run.frozen = frozen
    disc = None
    if run.disc is not None and epoch >= cfg.disc_start:
        disc = DDP(run.disc, device_ids=ids) if dist.enabled else run.disc
    run.model.train()
    if frozen:
        run.model.encoder.eval()
    for m in run.model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm) and (
                cfg.freeze_bn or (cfg.train_only and not any(p.requires_grad for p in m.parameters()))):
            m.eval()
    return run.gen, disc


def train_step(run: Run, gen, disc, batch) -> dict[str, float]:
    """One optimisation step: the generator on cross-entropy (+ soft IoU, + the distillation loss
    with a teacher, + λ·adversarial loss when `disc` is given), then the discriminators on the
    one-hot truth vs the generator's probabilities."""
    cfg, device, bf16 = run.cfg, run.dist.device, run.bf16
    x = batch["image"].to(device, non_blocking=True)
    if run.channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    targets = {v: batch[v].to(device, non_blocking=True).long() for v in cfg.views}
    structured = cfg.decoder == "struct"
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
        out = gen(x, with_structure=True) if structured else gen(x)
    if structured:
        out, structs = out
    ce = sum(layout_loss(out[v], targets[v], run.weight) for v in cfg.views)
    iou = sum(layout_iou_loss(out[v], targets[v]) for v in cfg.views) if cfg.iou_weight else torch.zeros(())
    loss, adv_loss, d_loss = cfg.label_weight * (ce + cfg.iou_weight * iou), torch.zeros(()), torch.zeros(())
    sl = {}
    if structured and cfg.struct_weight:
        extent = run.mcfg.extent
        spans = batch.get("spans") if cfg.placement_weight else None
        sl["struct"] = sum(structure_loss(v, structs[v], targets[v], extent, cfg.gap_weight, cfg.gap_loss_weight,
                                          spans, cfg.placement_weight) for v in cfg.views)
        loss = loss + cfg.label_weight * cfg.struct_weight * sl["struct"]
    kd = {}
    if run.teacher is not None:
        # --distill-on replay: only the renders; a batch with none adds a zero the step still records
        keep = batch["replay"].to(device) if cfg.distill_on == "replay" else slice(None)
        if len(x[keep]):
            with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                t_out = run.teacher(x[keep])
            kd["kd"] = sum(distill_loss(out[v][keep], t_out[v]) for v in cfg.views)
        else:
            kd["kd"] = torch.zeros((), device=device)
        loss = loss + cfg.distill_weight * kd["kd"]
    probs = {}
    if disc is not None:
        run.disc.requires_grad_(False)
        for v in cfg.views:
            probs[v] = out[v].float().softmax(2)
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                d_fake = run.disc(v, probs[v])
            adv_loss = adv_loss + lsgan_generator_loss(d_fake.float())
        run.disc.requires_grad_(True)
        loss = loss + cfg.disc_weight * adv_loss
    gen_opt = run.optimizers["gen"]
    gen_opt.zero_grad(set_to_none=True)
    loss.backward()
    gen_opt.step()
    if run.anchor is not None:
        pull_to_anchor(run)
    if disc is not None:
        # one forward per view on [real; fake] so DDP sees a single pass
        for v in cfg.views:
            both = torch.cat([one_hot_layouts(targets[v]), probs[v].detach()])
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                scores = disc(v, both).float()
            n = x.shape[0]
            d_loss = d_loss + lsgan_discriminator_loss(scores[:n], scores[n:])
        disc_opt = run.optimizers["disc"]
        disc_opt.zero_grad(set_to_none=True)
        d_loss.backward()
        disc_opt.step()
    return {"loss": float(loss.detach()), "ce": float(ce.detach()), "iou": float(iou.detach()), "adv": float(adv_loss.detach()),
            "disc": float(d_loss.detach()), **{k: float(v.detach()) for k, v in {**kd, **sl}.items()}}


def count_step(st: RunState, sums: dict, losses: dict) -> None:
    """Add a step's losses to the epoch's sums and advance the step counters."""
    for k, v in losses.items():
        sums[k] += v
    st.step += 1
    st.global_step += 1
    st.epoch_sums = dict(sums)
    _maybe_crash(st.global_step)


def end_of_epoch(run: Run, st: RunState, sums: dict, val_loader, n_batches: int, total_steps: int,
                 t_epoch: float, stop: bool) -> bool:
    """Validate, record the epoch (metrics.csv, curves, best.safetensors), decide early stopping,
    move to the next epoch (unless the time budget stopped this one midway: a resume with more
    time finishes it) and write last.safetensors. Returns whether training stops."""
    cfg, dist = run.cfg, run.dist
    epoch = st.epoch
    n_steps = max(1, st.step)
    tr = dict(zip(sums, dist.mean([sums[k] / n_steps for k in sums])))
    if dist.main:
        record_epoch(run, st, tr, val_loader, total_steps, t_epoch)
    early = dist.broadcast_flag(bool(cfg.patience) and st.bad_epochs >= (cfg.patience or 0))
    if early and not stop:
        stop = True
        st.stop_reason = f"early stop: no improvement for {cfg.patience} epochs"
    if st.step >= n_batches or not stop or early:
        st.epoch, st.step, st.epoch_sums = epoch + 1, 0, None
    if st.epoch >= cfg.epochs and not stop:
        stop = True
        st.stop_reason = f"{cfg.epochs} epochs done"
    st.finished = stop
    st.elapsed_s = run.elapsed()
    save_last(run, st)
    if dist.main:
        write_history(run.dir, st.history)
    dist.barrier()
    return stop


def record_epoch(run: Run, st: RunState, tr: dict, val_loader, total_steps: int, t_epoch: float) -> None:
    """Rank 0: validate, append the history row, keep best.safetensors, print the epoch line."""
    from .checkpoint import save_checkpoint

    cfg, epoch = run.cfg, st.epoch
    t_val = time.time()
    val = validate(run.model, val_loader, cfg, run.weight, run.dist.device, progress=cfg.progress, bf16=run.bf16)
    val_s = time.time() - t_val
    row = history_row(epoch, st.step, lr_at(max(0, st.global_step - 1), total_steps, cfg, st.elapsed_s),
                       tr, val, time.time() - t_epoch, st.elapsed_s, val_seconds=val_s,
                       threads=torch.get_num_threads() * run.dist.world if run.dist.device.type == "cpu" else None)
    st.history.append(row)
    improved = val["score"] > st.best_score
    if improved:
        st.best_score, st.best_epoch, st.bad_epochs = val["score"], epoch, 0
        meta = {"epoch": epoch, "val_score": val["score"], "val": val["result"],
                "train_config": cfg.to_dict(), "variant": run.mcfg.variant()}
        save_checkpoint(run.dir / "best.safetensors", run.model, run.mcfg, extra=meta)
    else:
        st.bad_epochs += 1
    print(f"epoch {epoch + 1}: train loss {tr['loss']:.4f}, val loss {val['loss']:.4f}, "
          f"val score {val['score']:.4f}" + (" (best)" if improved else "")
          + f", {time.time() - t_epoch:.0f} s ({val_s:.0f} s of it validation)")


def save_last(run: Run, st: RunState) -> None:
    """last.safetensors (rank 0): model, discriminators, optimisers and the run state."""
    from .checkpoint import save_checkpoint

    if run.dist.main:
        meta = {**asdict(st), "train_config": run.cfg.to_dict(), "variant": run.mcfg.variant()}
        save_checkpoint(run.dir / "last.safetensors", run.model, run.mcfg, optimizer=run.optimizers,
                        extra=meta, disc=run.disc)


def _same_setting(key: str, saved, now) -> bool:
    """A run-defining setting unchanged? Paths compare as the files they name (resolved)."""
    if key in PATH_FIELDS and saved and now:
        return Path(saved).resolve() == Path(now).resolve()
    return _norm(saved) == _norm(now)


def _norm(v):
    if isinstance(v, (list, tuple)):
        return [_norm(x) for x in v]
    return v


def _maybe_crash(global_step: int) -> None:
    """Test hook: RACKLAY_TEST_SIGKILL_AT_STEP=N kills this process (SIGKILL) after step N, to
    test that --resume recovers from a hard crash."""
    at = os.environ.get("RACKLAY_TEST_SIGKILL_AT_STEP")
    if at and int(at) == global_step:
        import signal
        os.kill(os.getpid(), signal.SIGKILL)


__all__ = ["TrainConfig", "train", "validate", "val_score", "lr_at", "warmup_cosine", "split_ids"]
