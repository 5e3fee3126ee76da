"""The one-command demo of the toolkit's main job, starting from the shipped model.

On a fresh machine with no GPU and nothing downloaded (about 5-11 minutes on 2 cores; docs/model-card.md, Demo timing):

1. the shipped model (WareSynth renders, then labelled photos of other sites than the test
   split's; docs/model-card.md) predicts
   every real photo (the copies of `datasets/real-photos/` shipped in `transfer/photos/`): a
   figure per photo and one contact sheet. Those
   photos carry no labels here: they are shown, not scored;
2. the real set of Table 2: with `real_photos` (an `annotate` project of labelled photos whose
   SOURCES.tsv gives each photo its split, e.g. `datasets/real-photos`, split by site; what
   `make demo` passes) it is exported with that split; without, WareSynth renders a small
   `proxy_real` set (train/test). **Proxy-real is rendered, not real**: a deliberately different
   domain (textures, lighting, camera noise/blur/JPEG, lens distortion) standing in for real
   photos where no labelled ones are at hand;
3. a reduced `transfer compare` (1 seed): synthetic only (the shipped model as it is), real only
   (ImageNet encoder trained on the real training split) and synthetic -> real fine-tune
   (the shipped model fine-tuned on it), all scored on the real test split;
4. prints Table 2 with the fine-tune's gain over real only, and writes the bar chart and
   learning curve.

Every training run has a time budget (`max_minutes`), so a slower machine gets a less-trained
model rather than a much longer demo. Every step resumes: running the demo again reuses finished
data and runs. Precision follows the machine (bf16 only where the CPU computes it natively).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from racklay.config import TrainConfig

#: the real photos (package data: copies of datasets/real-photos/*.jpg with their SOURCES.tsv)
PHOTOS = Path(str(resources.files("transfer") / "photos"))


#: the demo's training options, as overrides of racklay.config.TrainConfig (every other option,
#: e.g. the batch size or the precision, is TrainConfig's; `transfer demo --amp` sets one)
TRAIN_OVERRIDES = {"disc": False, "warmup_steps": 20, "progress": False, "workers": 0}


@dataclass
class DemoConfig:
    out: str = "outputs/transfer-demo"
    seed: int = 0
    weights: str | None = None      # model to start from (default: the shipped one)
    n_real: int = 200               # proxy-real images (train 82 % / test 18 %, as the paper's real set)
    layout_d: int = TrainConfig.layout_size  # D stored on disk: the layout size models predict
    epochs: int | None = None       # real-only and fine-tune epochs (None: TrainConfig's)
    fractions: tuple = (1.0,)
    seeds: int = 1
    max_minutes: float = 3.2        # per training run (real only, fine-tune): the demo's time budget
    photos: str = str(PHOTOS)
    real_photos: str | None = None  # labelled annotate project for Table 2 (None: proxy-real renders)
    workers: int = 1                # WareSynth workers
    train: dict = field(default_factory=lambda: dict(TRAIN_OVERRIDES))

    @property
    def real_seed(self) -> int:
        """WareSynth seed of the proxy-real set (another than `seed`, which seeds the training)."""
        return self.seed + 1


QUICK = dict(n_real=30, epochs=1, max_minutes=0.25)


def _synth(recipe: str, n: int, out: Path, seed: int, D: int, workers: int, log) -> Path:
    from racklay.synth.generate import generate_dataset
    from racklay.synth.recipe import load_recipe

    t0 = time.time()
    res = generate_dataset(load_recipe(recipe, {"layout_size": D}), n, out, seed=seed, workers=workers)
    splits = ", ".join(f"{k}={v}" for k, v in res.splits.items())
    log(f"      {out}: {len(res.generated)} rendered, {res.skipped} already there ({time.time() - t0:.0f} s); splits {splits}")
    return out


def _export_real(project: Path, out: Path, log) -> Path:
    """The labelled photos of an annotate project as a RackLay set, each in the split its
    SOURCES.tsv row names. Exported once and reused while the labels and splits stay the same
    (a fingerprint of every annotation's version and split is kept beside the export)."""
    import json
    import shutil

    from annotate.dataset import export_project, read_split_file
    from annotate.store import Project
    from racklay.atomic import atomic_write_json

    src = project / "SOURCES.tsv"
    if not src.is_file():
        raise ValueError(f"{src}: not found (the demo splits the labelled photos as its 'split' column says)")
    split_of = read_split_file(src)
    if not {"train", "test"} <= set(split_of.values()):
        raise ValueError(f"{src}: the 'split' column must put photos in both train and test "
                         f"(it names {', '.join(sorted(set(split_of.values())))})")
    proj = Project(project, create=False)
    stamp = {name: [split_of.get(name), (proj.read_annotation(name) or {}).get("version")]
             for name in proj.images()}
    stamp_path = out.parent / f"{out.name}.source.json"
    if out.is_dir() and stamp_path.is_file() and json.loads(stamp_path.read_text()) == stamp:
        log(f"      {out}: exported before from the same labels, reused")
        return out
    if out.exists():   # derived data of an earlier run whose labels or splits have changed since
        log(f"      {out}: the labels or splits changed since the last run: exported again "
            f"(delete the compare folder to retrain on them)")
        shutil.rmtree(out)
    res = export_project(proj, out, split_of=split_of)
    atomic_write_json(stamp_path, stamp, indent=1)
    splits = ", ".join(f"{k}={v}" for k, v in res["splits"].items())
    log(f"      {out}: {res['images']} labelled photos exported from {project}; splits {splits}")
    return out


def predict_photos(weights: Path, photos: Path, out: Path, log, title: str = "shipped model") -> list[Path]:
    """Run a checkpoint on every photo in a folder; write one paper-style figure per photo, a
    contact sheet of them all (`contact_sheet.png`) and a SOURCES.tsv copy (attribution travels
    with the figures)."""
    import shutil

    from racklay.data import read_image
    from racklay.predict import Predictor
    from racklay.viz import contact_sheet, layout_figure

    files = sorted(p for p in photos.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")) if photos.is_dir() else []
    if not files:
        log(f"      no photos in {photos}: skipped")
        return []
    pred = Predictor(str(weights), precision="auto")
    out.mkdir(parents=True, exist_ok=True)
    written, rows = [], []
    for f in files:
        img = read_image(f)
        r = pred.predict(img)
        fig = out / f"{f.stem}.png"
        layout_figure(img, r.get("top"), r.get("front"), out=fig, grid=r["grid"], outline_stacks=True,
                      title=f"{f.name}: real photo, {title}'s prediction (no labels: shown, not scored)")
        written.append(fig)
        rows.append((f.name, img, r.get("top"), r.get("front")))
    # the folder's own name, not its absolute path: the sheet is shared, the path is this machine's
    sheet = contact_sheet(rows, out / "contact_sheet.png",
                          title=f"{title} ({Path(weights).name}) on {len(files)} photos of {photos.resolve().name}/")
    written.append(sheet)
    if (photos / "SOURCES.tsv").is_file():
        shutil.copyfile(photos / "SOURCES.tsv", out / "SOURCES.tsv")
    return written


def run_demo(cfg: DemoConfig, log=print) -> dict:
    from racklay.release import resolve_weights

    from .compare import CompareConfig, compare

    t_start = time.time()
    out = Path(cfg.out)
    data = out / "data"
    weights = resolve_weights(cfg.weights)
    photos = Path(cfg.photos)
    log(f"[1/4] the shipped model ({weights.name}) on the real photos in {photos} (no labels: shown, not scored)")
    figs = predict_photos(weights, photos, out / "real-photo-predictions", log)
    if figs:
        log(f"      {len(figs) - 1} figures and a contact sheet -> {figs[-1]}")
    if cfg.real_photos:
        what = "the labelled real photos' test split"
        log(f"[2/4] the labelled real photos of {cfg.real_photos}, split as its SOURCES.tsv says -> {data / 'real-photos'}")
        real = _export_real(Path(cfg.real_photos), data / "real-photos", log)
    else:
        what = "the proxy-real test split (rendered, not real)"
        log(f"[2/4] WareSynth: {cfg.n_real} 'proxy_real' images (RENDERED stand-in for real photos, "
            f"train/test) -> {data / 'proxy_real'}")
        real = _synth("proxy_real", cfg.n_real, data / "proxy_real", cfg.real_seed, cfg.layout_d, cfg.workers, log)
    log(f"[3/4] transfer compare on {real.name}: synthetic only (the shipped model) / real only (ImageNet "
        f"encoder) / synthetic -> real fine-tune, {cfg.seeds} seed(s), at most {cfg.max_minutes:g} min per run")
    ccfg = CompareConfig(real=str(real), out=str(out / "compare"), pretrained=str(weights), seeds=list(range(cfg.seeds)),
                         fractions=list(cfg.fractions), epochs=cfg.epochs, max_minutes=cfg.max_minutes,
                         train=dict(cfg.train))
    res = compare(ccfg, log=lambda m: log("      " + m))
    log(f"[4/4] Table 2 on {what}:")
    log("")
    log(res["paths"]["table_md"].read_text())
    from .report import summarize

    means = summarize(res["records"], fraction=max(cfg.fractions))
    gain = (means["finetune"]["top box mIoU"][0], means["real"]["top box mIoU"][0]) \
        if "finetune" in means and "real" in means else None
    if gain is not None:
        log(f"fine-tuned vs real only, top-view box mIoU: {gain[0]:.2f} vs {gain[1]:.2f} ({gain[0] - gain[1]:+.2f})")
    best_f = max(cfg.fractions)
    ft = Path(ccfg.out) / "runs" / "seed0" / f"finetune_f{best_f:g}" / "best.safetensors"
    wall = time.time() - t_start
    log("")
    log(f"demo finished in {wall / 60:.1f} min. Outputs:")
    rows = [("shipped weights", weights), ("real dataset" if cfg.real_photos else "proxy-real dataset", real),
            ("comparison runs", Path(ccfg.out) / "runs"),
            *[(k, v) for k, v in res["paths"].items()], ("fine-tuned weights", ft)]
    rows += [("photo prediction", f) for f in figs]
    for k, v in rows:
        log(f"  {k:20s} {v}")
    return {"compare": res, "figures": figs, "weights": ft, "shipped": weights, "gain": gain, "wall_seconds": wall}
