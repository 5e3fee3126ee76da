"""`transfer compare`: the three training regimes of the paper's Table 2 on one real test split,
over several seeds, plus a learning curve over fractions of the real training split.

    synthetic only            pretrain on the synthetic root, evaluate on the real test split
    real only                 same architecture, random init (or local ImageNet weights), trained on
                              a fraction of the real training split with the paper's augmentation
    synthetic -> real         the seed's pretrain checkpoint fine-tuned on the same real fraction

Every run lives in its own folder `OUT/runs/seed<S>/<job>/`; its `result.json` (written
atomically, last) is the done marker. A killed compare, started again with the same command,
skips every run that has one and redoes only the unfinished ones. Adding seeds or fractions to
an existing OUT runs only the new jobs; changing a setting that affects results is refused.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from racklay.atomic import atomic_write_json

from . import report, workflow

#: settings that change results: resuming an OUT with different values is refused
RESULT_KEYS = ("synthetic", "real", "pretrained", "real_train_split", "real_test_split", "image_size",
               "layout_size", "R", "decoder", "encoder", "letterbox", "disc", "pretrain_epochs", "epochs", "batch_size", "lr",
               "finetune_lr", "freeze_encoder_epochs", "imagenet_weights", "val_fraction", "patience",
               "augment", "max_minutes", "pretrain_max_minutes", "train_overrides")


@dataclass
class CompareConfig:
    real: str
    out: str
    synthetic: str | None = None
    pretrained: str | None = None          # one checkpoint for every seed instead of pretraining per seed
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    fractions: list[float] = field(default_factory=lambda: [0.1, 0.25, 0.5, 1.0])
    real_train_split: str = "train"
    real_test_split: str = "test"
    image_size: int | None = None
    layout_size: int | None = None
    R: int | None = None
    decoder: str | None = None
    encoder: str | None = None
    letterbox: bool | None = None
    disc: bool | None = None
    pretrain_epochs: int | None = None
    epochs: int | None = None              # real-only and fine-tune epochs
    batch_size: int | None = None
    lr: float | None = None                # pretrain and real-only
    finetune_lr: float | None = None       # default: lr x workflow.FINETUNE_LR_RATIO
    freeze_encoder_epochs: int = 0
    imagenet_weights: str | None = None    # real-only init (and pretrain init)
    val_fraction: float = workflow.REAL_VAL_FRACTION
    patience: int | None = None
    augment: bool = True
    max_minutes: float | None = None       # per real-only / fine-tune run
    pretrain_max_minutes: float | None = None
    workers: int | None = None
    eval_batch_size: int = 8
    train_overrides: dict = field(default_factory=dict)  # any other TrainConfig fields

    def settings(self) -> dict:
        d = asdict(self)
        return {k: d[k] for k in RESULT_KEYS}


def _frac_name(f: float) -> str:
    return f"f{f:g}"


def validate(cfg: CompareConfig) -> None:
    if not cfg.seeds:
        raise ValueError("--seeds must be at least 1")
    bad = [f for f in cfg.fractions if not 0 < f <= 1]
    if bad or not cfg.fractions:
        raise ValueError(f"--fractions must be in (0, 1], got {cfg.fractions}")
    if (cfg.synthetic is None) == (cfg.pretrained is None):
        raise ValueError("give exactly one of --synthetic ROOT (pretrain here) or --pretrained CHECKPOINT")
    workflow.require_split(cfg.real, cfg.real_train_split, "real")
    workflow.require_split(cfg.real, cfg.real_test_split, "real")
    if cfg.synthetic is not None:
        workflow.require_split(cfg.synthetic, "train", "synthetic")
        sR, _ = workflow.dataset_shape(cfg.synthetic, "train")
        rR, _ = workflow.dataset_shape(cfg.real, cfg.real_train_split)
        if sR != rR:
            raise ValueError(f"{cfg.synthetic} has R={sR} shelf channels but {cfg.real} has R={rR}: "
                             "the regimes must share one architecture")
    else:
        workflow.check_init_compatible(cfg.pretrained, cfg.real, cfg.real_train_split,
                                       layout_size=cfg.layout_size, R=cfg.R)


def _check_resume(out: Path, cfg: CompareConfig) -> None:
    p = out / "compare.json"
    if p.is_file():
        try:
            old = json.loads(p.read_text()).get("settings", {})
        except json.JSONDecodeError:
            old = {}
        new = json.loads(json.dumps(cfg.settings()))
        diff = [k for k in RESULT_KEYS if k in old and old[k] != new[k]]
        if diff:
            k = diff[0]
            raise ValueError(f"{p}: this compare folder was started with {k}={old[k]!r}, now {k}={new[k]!r}; "
                             "use the same settings to resume, or a new --out")
    atomic_write_json(p, {"settings": cfg.settings(), "seeds": cfg.seeds, "fractions": cfg.fractions})


def _load_done(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError:
        return None  # cannot happen with atomic writes, but never trust a broken marker


def _common(cfg: CompareConfig) -> dict:
    kw = dict(image_size=cfg.image_size, layout_size=cfg.layout_size, R=cfg.R, decoder=cfg.decoder, disc=cfg.disc,
              encoder=cfg.encoder, letterbox=cfg.letterbox,
              batch_size=cfg.batch_size, patience=cfg.patience, workers=cfg.workers)
    kw.update(cfg.train_overrides)
    return kw


class Compare:
    def __init__(self, cfg: CompareConfig, log=print):
        self.cfg = cfg
        self.out = Path(cfg.out)
        self.log = log
        self.ran: list[str] = []       # jobs run (not skipped) in this invocation

    def jobs(self) -> list[tuple[int, str, float | None]]:
        """(seed, regime, fraction) in run order: seed-major so one seed's full table lands first,
        largest fraction first."""
        js = []
        for s in self.cfg.seeds:
            if not self.cfg.pretrained or s == self.cfg.seeds[0]:
                # with --pretrained there is one synthetic-only model: score it once
                js.append((s, "synthetic", None))
            for f in sorted(self.cfg.fractions, reverse=True):
                js.append((s, "real", f))
                js.append((s, "finetune", f))
        return js

    def job_dir(self, seed: int, regime: str, fraction: float | None) -> Path:
        name = regime if fraction is None else f"{regime}_{_frac_name(fraction)}"
        return self.out / "runs" / f"seed{seed}" / name

    def pretrain_weights(self, seed: int) -> Path:
        cfg = self.cfg
        if cfg.pretrained:
            return Path(cfg.pretrained)
        d = self.out / "runs" / f"seed{seed}" / "pretrain"
        done = _load_done(d / "result.json")
        if done:
            return Path(done["weights"])
        self.log(f"  pretraining on {cfg.synthetic} (seed {seed}) -> {d}")
        t0 = time.time()
        kw = _common(cfg)
        run = workflow.pretrain(cfg.synthetic, d.parent, name=d.name, seed=seed, epochs=cfg.pretrain_epochs,
                                lr=cfg.lr, imagenet_weights=cfg.imagenet_weights,
                                max_minutes=cfg.pretrain_max_minutes,
                                resume=workflow.has_partial_run(d.parent, d.name) or None, **kw)
        w = workflow.best_weights(run)
        atomic_write_json(d / "result.json", {"kind": "pretrain", "seed": seed, "weights": str(w), "run": str(run),
                                              "train_seconds": time.time() - t0})
        self.ran.append(f"seed{seed}/pretrain")
        return w

    def run_job(self, seed: int, regime: str, fraction: float | None) -> dict:
        cfg = self.cfg
        d = self.job_dir(seed, regime, fraction)
        done = _load_done(d / "result.json")
        if done is not None:
            return done
        t0 = time.time()
        pre = self.pretrain_weights(seed) if regime in ("synthetic", "finetune") else None
        t_pre = time.time() - t0
        t0 = time.time()
        kw = _common(cfg)
        if regime == "synthetic":
            weights, run, n_train = pre, pre.parent, None
        else:
            common = dict(seed=seed, epochs=cfg.epochs, val_fraction=cfg.val_fraction, augment=cfg.augment,
                          train_split=cfg.real_train_split, train_fraction=fraction, max_minutes=cfg.max_minutes,
                          resume=workflow.has_partial_run(d.parent, d.name) or None)
            if regime == "real":
                run = workflow.train_on_real(cfg.real, d.parent, name=d.name, init=None, lr=cfg.lr,
                                             imagenet_weights=cfg.imagenet_weights, **common, **kw)
            else:
                ft_kw = {k: v for k, v in kw.items()
                         if k not in ("image_size", "layout_size", "R", "decoder", "encoder", "letterbox")}
                lr = cfg.finetune_lr if cfg.finetune_lr is not None else (
                    None if cfg.lr is None else cfg.lr * workflow.FINETUNE_LR_RATIO)
                run = workflow.finetune(pre, cfg.real, d.parent, name=d.name, lr=lr,
                                        freeze_encoder_epochs=cfg.freeze_encoder_epochs, **common, **ft_kw)
            weights = workflow.best_weights(run)
            n_train = workflow.train_images(run)
        t_train = time.time() - t0
        t0 = time.time()
        from racklay.evaluate import evaluate

        metrics = evaluate(str(weights), cfg.real, split=cfg.real_test_split, batch_size=cfg.eval_batch_size,
                           progress=False)
        rec = {"regime": regime, "fraction": fraction, "seed": seed, "n_train": n_train, "weights": str(weights),
               "run": str(run), "train_seconds": t_train if regime != "synthetic" else t_pre,
               "eval_seconds": time.time() - t0, "metrics": metrics}
        atomic_write_json(d / "result.json", rec)
        self.ran.append(f"seed{seed}/{d.name}")
        return rec

    def collect(self) -> list[dict]:
        recs = []
        for s, regime, f in self.jobs():
            r = _load_done(self.job_dir(s, regime, f) / "result.json")
            if r is not None and "metrics" in r:
                recs.append(r)
        return recs

    def run(self) -> dict:
        validate(self.cfg)
        if self.cfg.pretrained:
            # one architecture for all three regimes: the checkpoint's
            m = workflow.checkpoint_config(self.cfg.pretrained)
            for k in ("image_size", "layout_size", "R", "decoder", "encoder", "letterbox", "disc"):
                if getattr(self.cfg, k) is None:
                    setattr(self.cfg, k, getattr(m, k))
        self.out.mkdir(parents=True, exist_ok=True)
        _check_resume(self.out, self.cfg)
        jobs = self.jobs()
        t_start = time.time()
        todo = [j for j in jobs if _load_done(self.job_dir(*j) / "result.json") is None]
        self.log(f"compare: {len(jobs)} runs ({len(jobs) - len(todo)} already done) -> {self.out}")
        for i, (s, regime, f) in enumerate(jobs, 1):
            d = self.job_dir(s, regime, f)
            if (d / "result.json").is_file():
                continue
            label = report.REGIME_LABELS[regime] + ("" if f is None else f", real fraction {f:g}")
            self.log(f"[{i}/{len(jobs)}] seed {s}: {label}")
            rec = self.run_job(s, regime, f)
            self.log(f"        top box mIoU {report.record_values(rec)['top box mIoU']:.2f} "
                     f"(dataset IoU {report.record_values(rec)['top box IoU']:.2f}), "
                     f"train {rec['train_seconds']:.0f}s, eval {rec['eval_seconds']:.0f}s")
        records = self.collect()
        n_seeds = len(self.cfg.seeds)
        header = (f"Compare: synthetic {self.cfg.synthetic or self.cfg.pretrained} vs real {self.cfg.real} "
                  f"(test split '{self.cfg.real_test_split}'), {n_seeds} seed(s), fractions "
                  f"{', '.join(f'{f:g}' for f in sorted(self.cfg.fractions))}.\n")
        paths = report.write_report(self.out, records, fraction=max(self.cfg.fractions), header=header)
        wall = time.time() - t_start
        summary = {"records": len(records), "ran": self.ran, "wall_seconds_this_invocation": wall,
                   "outputs": {k: str(v) for k, v in paths.items()}}
        atomic_write_json(self.out / "summary.json", summary)
        return {"records": records, "paths": paths, "summary": summary}


def compare(cfg: CompareConfig, log=print) -> dict:
    return Compare(cfg, log=log).run()
