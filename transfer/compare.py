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
from dataclasses import MISSING, dataclass
from pathlib import Path

from racklay.atomic import atomic_write_json
from racklay.config import ARCH_FIELDS, RUN_DEFINING, TrainConfig, check_fields, from_dict, option, run_defining

from . import report, workflow


@dataclass
class CompareConfig:
    """`transfer compare`'s own settings: which data, which seeds and fractions, and what differs
    between the regimes. A training option shared by every run (image size, R, decoder,
    discriminators, batch size, workers, any other) is not mirrored here: `train` holds it as an
    override of racklay.config.TrainConfig, where it is declared. keep=True: resuming an OUT with a
    different value is refused (as are changes to `train`'s run-defining options)."""
    real: str = option(MISSING, "real RackLay root with the train and test splits", keep=True)
    out: str = option(MISSING, "output folder (resumable)")
    synthetic: str | None = option(None, "synthetic root, pretrained on once per seed", keep=True)
    pretrained: str | None = option(None, "one pretrain checkpoint for every seed instead", keep=True)
    seeds: list = option([0, 1, 2], "seeds; adding some to an OUT runs only theirs")
    fractions: list = option([0.1, 0.25, 0.5, 1.0], "fractions of the real training split (learning curve)")
    real_train_split: str = option("train", "real training split", keep=True)
    real_test_split: str = option("test", "real test split", keep=True)
    pretrain_epochs: int | None = option(None, "pretrain runs' epochs (None: TrainConfig's)", keep=True)
    epochs: int | None = option(None, "real-only and fine-tune runs' epochs (None: TrainConfig's)", keep=True)
    lr: float | None = option(None, "pretrain and real-only learning rate (None: TrainConfig's)", keep=True)
    finetune_lr: float | None = option(None, "fine-tune learning rate (None: lr x workflow.FINETUNE_LR_RATIO)",
                                       keep=True)
    freeze_encoder_epochs: int = option(0, "fine-tune runs' frozen-encoder epochs", keep=True)
    imagenet_weights: str | None = option(None, "real-only (and pretrain) encoder init file", keep=True)
    val_fraction: float = option(workflow.REAL_VAL_FRACTION, "share of the real training split held out",
                                 keep=True)
    augment: bool = option(True, "the paper's augmentation on real data", keep=True)
    max_minutes: float | None = option(None, "time budget per real-only / fine-tune run", keep=True)
    pretrain_max_minutes: float | None = option(None, "time budget per pretrain run", keep=True)
    eval_batch_size: int = option(8, "images per forward pass when scoring")
    train: dict = option({}, "TrainConfig overrides for every run", keep=True)

    def __post_init__(self):
        check_fields(self)     # types and bounds; what needs the data is checked by validate()

    def settings(self) -> dict:
        """What compare.json records and a resume must match: the keep=True fields, with `train`
        reduced to TrainConfig's run-defining options (workers or patience may change)."""
        d = {k: getattr(self, k) for k in RESULT_KEYS}
        d["train"] = {k: v for k, v in self.train.items() if k in RUN_DEFINING}
        return json.loads(json.dumps(d))


#: settings that change results: resuming an OUT with different values is refused
RESULT_KEYS = run_defining(CompareConfig)


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
    # a typo or a bad value in the overrides fails now, not after the first runs
    from_dict(TrainConfig, {"data": cfg.real, **cfg.train}, "compare: train", "training option")
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
                                       layout_size=cfg.train.get("layout_size"), R=cfg.train.get("R"))


def _check_resume(out: Path, cfg: CompareConfig) -> None:
    p = out / "compare.json"
    if p.is_file():
        try:
            old = json.loads(p.read_text()).get("settings", {})
        except json.JSONDecodeError:
            old = {}
        new = cfg.settings()
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
        kw = dict(cfg.train)
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
        kw = dict(cfg.train)
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
                # the architecture comes from the checkpoint (discriminators are the run's choice)
                ft_kw = {k: v for k, v in kw.items() if k not in ARCH_FIELDS or k == "disc"}
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
            for k in ARCH_FIELDS:
                self.cfg.train.setdefault(k, getattr(m, k))
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
