"""The one-command demo of the toolkit's main job: synthetic -> real transfer (paper §5.5).

On a fresh machine with no GPU and nothing downloaded (≈9 minutes on 2 free cores):

1. WareSynth renders a small `complex` synthetic set (train/val/test);
2. and a small `proxy_real` set (train/test). **Proxy-real is rendered, not real**: a
   deliberately different domain (textures, lighting, camera noise/blur/JPEG, lens distortion)
   standing in for the authors' 542 annotated photos, which cannot be downloaded here;
3. a reduced `transfer compare` (1 seed, real fractions 25% and 100%): synthetic only, real
   only, synthetic -> real fine-tune, scored on the proxy-real test split;
4. prints Table 2 and writes the bar chart and the learning curve;
5. runs the fine-tuned model on the real photos in `datasets/real-photos/` and writes
   paper-style figures. Those photos carry no labels: they are shown, not scored.

Every run has a time budget (`max_minutes`), so a slower machine gets a less-trained model
rather than a much longer demo. Every step resumes: running the demo again reuses finished data
and runs.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PHOTOS = REPO / "datasets" / "real-photos"


@dataclass
class DemoConfig:
    out: str = "outputs/transfer-demo"
    seed: int = 0
    n_synthetic: int = 600
    n_real: int = 150
    layout_d: int = 128             # D stored on disk (RackLay's own is 512; smaller = faster I/O)
    image_size: int = 128
    layout_size: int = 128
    pretrain_epochs: int = 20
    epochs: int = 20
    fractions: tuple = (0.25, 1.0)
    seeds: int = 1
    pretrain_max_minutes: float = 7.0
    max_minutes: float = 2.0
    batch_size: int = 8
    amp: str = "bf16"              # CPU autocast; --amp none for fp32 (slower, on CPUs without AMX bf16 gains little)
    photos: str = str(PHOTOS)
    workers: int = 1                # WareSynth workers


QUICK = dict(n_synthetic=40, n_real=30, image_size=64, layout_size=32, pretrain_epochs=2, epochs=2,
             fractions=(0.5, 1.0), pretrain_max_minutes=1.0, max_minutes=0.5)


def _synth(recipe: str, n: int, out: Path, seed: int, D: int, workers: int, log) -> Path:
    from racklay.synth.generate import generate_dataset
    from racklay.synth.recipe import load_recipe

    t0 = time.time()
    res = generate_dataset(load_recipe(recipe, {"layout_size": D}), n, out, seed=seed, workers=workers)
    splits = ", ".join(f"{k}={v}" for k, v in res.splits.items())
    log(f"      {out}: {len(res.generated)} rendered, {res.skipped} already there ({time.time() - t0:.0f} s); splits {splits}")
    return out


def predict_photos(weights: Path, photos: Path, out: Path, log) -> list[Path]:
    """Run a checkpoint on every photo in a folder; write one paper-style figure per photo and a
    SOURCES.tsv copy (attribution travels with the figures)."""
    import shutil

    from racklay.data import read_image
    from racklay.predict import Predictor
    from racklay.viz import layout_figure

    files = sorted(p for p in photos.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")) if photos.is_dir() else []
    if not files:
        log(f"      no photos in {photos}: skipped")
        return []
    pred = Predictor(str(weights))
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for f in files:
        img = read_image(f)
        r = pred.predict(img)
        fig = out / f"{f.stem}.png"
        layout_figure(img, r.get("top"), r.get("front"), out=fig,
                      title=f"{f.name}: real photo, fine-tuned model's prediction (no labels: shown, not scored)")
        written.append(fig)
    if (photos / "SOURCES.tsv").is_file():
        shutil.copyfile(photos / "SOURCES.tsv", out / "SOURCES.tsv")
    return written


def run_demo(cfg: DemoConfig, log=print) -> dict:
    from .compare import CompareConfig, compare

    t_start = time.time()
    out = Path(cfg.out)
    data = out / "data"
    log(f"[1/5] WareSynth: {cfg.n_synthetic} synthetic 'complex' images -> {data / 'complex'}")
    syn = _synth("complex", cfg.n_synthetic, data / "complex", cfg.seed, cfg.layout_d, cfg.workers, log)
    log(f"[2/5] WareSynth: {cfg.n_real} 'proxy_real' images (RENDERED stand-in for real photos, "
        f"train/test) -> {data / 'proxy_real'}")
    real = _synth("proxy_real", cfg.n_real, data / "proxy_real", cfg.seed + 1, cfg.layout_d, cfg.workers, log)
    log(f"[3/5] transfer compare: synthetic only / real only / synthetic -> real fine-tune, "
        f"{cfg.seeds} seed(s), real fractions {', '.join(f'{f:g}' for f in cfg.fractions)}")
    ccfg = CompareConfig(real=str(real), out=str(out / "compare"), synthetic=str(syn), seeds=list(range(cfg.seeds)),
                         fractions=list(cfg.fractions), image_size=cfg.image_size, layout_size=cfg.layout_size,
                         disc=False, pretrain_epochs=cfg.pretrain_epochs, epochs=cfg.epochs,
                         batch_size=cfg.batch_size, pretrain_max_minutes=cfg.pretrain_max_minutes,
                         max_minutes=cfg.max_minutes, workers=0,
                         train_overrides={"amp": cfg.amp, "warmup_steps": 20, "progress": False})
    res = compare(ccfg, log=lambda m: log("      " + m))
    log("[4/5] Table 2 on the proxy-real test split (rendered, not real):")
    log("")
    log(res["paths"]["table_md"].read_text())
    best_f = max(cfg.fractions)
    ft = Path(ccfg.out) / "runs" / "seed0" / f"finetune_f{best_f:g}" / "best.safetensors"
    photos = Path(cfg.photos)
    log(f"[5/5] fine-tuned model ({ft}) on the real photos in {photos} (no labels: shown, not scored)")
    figs = predict_photos(ft, photos, out / "real-photo-predictions", log)
    wall = time.time() - t_start
    log("")
    log(f"demo finished in {wall / 60:.1f} min. Outputs:")
    rows = [("synthetic dataset", syn), ("proxy-real dataset", real), ("comparison runs", Path(ccfg.out) / "runs"),
            *[(k, v) for k, v in res["paths"].items()], ("fine-tuned weights", ft)]
    rows += [("photo prediction", f) for f in figs]
    for k, v in rows:
        log(f"  {k:20s} {v}")
    return {"compare": res, "figures": figs, "weights": ft, "wall_seconds": wall}
