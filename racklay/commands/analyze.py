"""racklay analyze IMAGE_OR_FOLDER --weights W --out DIR
   racklay analyze --layouts ROOT [--split test] --out DIR"""
from __future__ import annotations

import sys
from pathlib import Path

from racklay.config import add_flags, at_least, positive_float

FORMATS = ("glb", "ply", "both", "none")
#: racklay.reasoning.ReasoningConfig fields that `racklay analyze` exposes as flags
KNOBS = ("open_m", "min_box_area_m2", "split_step_m", "min_stack_m", "slope_fraction", "load_width_m")


def register(sub) -> None:
    from racklay.predict import add_flip_average_arg, add_rack_box_arg, add_shelf_length_arg
    from racklay.reasoning import ReasoningConfig
    from racklay.release import add_weights_arg

    p = sub.add_parser(
        "analyze", help="count box stacks and measure free space; export a 3D reconstruction",
        description="Rack reasoning (paper §5.6). Fuse every shelf's top- and front-view layout into 3D "
                    "box stacks, count them, and measure each shelf's capacity (footprint x clear height), "
                    "occupied and free volume in m³. Layouts come from a trained model run on photos "
                    "(IMAGE_OR_FOLDER with --weights) or from a RackLay-format dataset's ground truth "
                    "(--layouts ROOT). Per image it prints one line (e.g. 'Rack has 4 shelves, 12 box "
                    "stacks, and 0.83 m³ of free space available (41%)') and writes OUT/ID.json (shelves, "
                    "boxes with metric extents, counts, volumes), OUT/ID.glb (binary glTF: opens in "
                    "Blender or any glTF viewer) and OUT/ID.png (3D render beside the photo), plus "
                    "OUT/summary.json. A file that cannot be read gets one error line naming it; the "
                    "others are still analysed and the exit code is 1.")
    p.add_argument("inputs", nargs="*", metavar="IMAGE_OR_FOLDER",
                   help="photos, folders of photos, or RackLay datasets (their Images/, of --split "
                        "when given) to run the model on (with --weights)")
    add_weights_arg(p)
    p.add_argument("--backend", choices=("torch", "onnx"), default=None,
                   help="inference backend (default: onnx for .onnx files, else torch)")
    add_shelf_length_arg(p)
    add_rack_box_arg(p)
    add_flip_average_arg(p)
    p.add_argument("--layouts", metavar="ROOT", help="analyse the ground-truth layouts of this RackLay dataset")
    p.add_argument("--split", default=None,
                   help="only this split (e.g. test) of the --layouts dataset or of dataset inputs; default all")
    p.add_argument("--extent", type=positive_float, default=None,
                   help="with --layouts: metres covered by the layout grid (default: meta/ID.json's "
                        "grid.extent_m, else 8.0 as in RackLay)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--format", choices=FORMATS, default="glb", help="3D file(s) to write (default: glb)")
    p.add_argument("--no-render", action="store_true", help="skip the PNG render (about 1 s per image)")
    p.add_argument("--limit", type=at_least(1), default=None, help="analyse at most this many images")
    g = p.add_argument_group("analysis knobs (metric; see docs/reasoning.md)")
    add_flags(g, ReasoningConfig, list(KNOBS), default=None)
    p.set_defaults(func=run)


def _config(args):
    from racklay.reasoning import ReasoningConfig

    return ReasoningConfig(**{k: getattr(args, k) for k in KNOBS if getattr(args, k) is not None})


def write_outputs(result, out: Path, sid: str, image=None, fmt: str = "glb", render: bool = True) -> list[Path]:
    """JSON (+ GLB/PLY, + PNG render) for one analysed rack. Returns the files written."""
    from racklay.atomic import atomic_write_text
    from racklay.export3d import render_figure, write_glb, write_ply

    try:
        files = [atomic_write_text(out / f"{sid}.json", result.to_json() + "\n")]
        if fmt in ("glb", "both"):
            files.append(write_glb(result, out / f"{sid}.glb"))
        if fmt in ("ply", "both"):
            files.append(write_ply(result, out / f"{sid}.ply"))
        if render:
            render_figure(result, image, out=out / f"{sid}.png", title=f"{sid}: {result.report()}")
            files.append(out / f"{sid}.png")
    except BaseException:
        # a rack's outputs are written whole or not at all: no JSON without its GLB
        for suffix in (".json", ".glb", ".ply", ".png"):
            f = out / f"{sid}{suffix}"
            if f.is_file():
                f.unlink()
        raise
    return files


def _samples_from_layouts(args):
    """Yield (sid, thunk) where thunk() -> (result, image or None, warning or None)."""
    from racklay import layout as L
    from racklay.data import DataError, RackLayRoot
    from racklay.reasoning import analyze_layouts

    ds = RackLayRoot(args.layouts).require()
    views = ds.views()
    if not views:
        raise DataError(f"{ds.root}: no topLayouts/ or frontLayouts/ folder")
    ids = ds.resolve(args.split)
    if args.split in (None, "all"):
        # every sample with layouts, photo or not (the photo only decorates the render): a layout
        # file without an image is analysed, never skipped
        ids = sorted(set(ids) | set(ds.layout_ids(views[0])))
    cfg = _config(args)

    def one(sid):
        layouts = {v: ds.read_layouts(v, sid) for v in views}
        meta = ds.read_meta(sid) or {}
        D = next(iter(layouts.values())).shape[-1]
        extent = args.extent or float((meta.get("grid") or {}).get("extent_m", L.DEFAULT_EXTENT_M))
        result = analyze_layouts(layouts.get("top"), layouts.get("front"), L.Grid(D, extent), cfg,
                                 source=str(ds.layout_path(views[0], sid)))
        image, warn = None, None
        if ds.image_path(sid).exists():
            try:
                image = ds.read_image(sid)
            except DataError as e:
                warn = f"{e} (rendered without the photo)"
        return result, image, warn

    for sid in ids:
        yield sid, (lambda s=sid: one(s))


def _samples_from_photos(args):
    from racklay.data import RackLayRoot, read_image
    from racklay.predict import Predictor, frame_cuts, list_inputs, unique_ids
    from racklay.reasoning import analyze_layouts

    files = []
    for item in args.inputs:
        root = RackLayRoot(item)
        if Path(item).is_dir() and (root.root / "Images").is_dir():
            # a RackLay-format dataset: its images (of --split, when given)
            files += [root.image_path(sid) for sid in root.resolve(args.split)]
        else:
            files += list_inputs([item])
    if not files:
        raise FileNotFoundError(f"no images found in {', '.join(args.inputs)}")
    backend = args.backend or ("onnx" if str(args.weights).endswith(".onnx") else "torch")
    predictor = Predictor(args.weights, backend=backend, flip_average=args.flip_average)
    cfg = _config(args)
    if args.shelf_length is not None:
        from racklay.layout import check_shelf_length
        check_shelf_length(args.shelf_length, predictor.grid)   # before the first photo

    def one(path):
        image = read_image(path)
        pred = predictor.predict(image, shelf_length=args.shelf_length, rack_box=args.rack_box, source=str(path))
        if "crop" in pred:          # the render shows the photo the layouts describe: the rack's crop
            x0, y0, x1, y1 = pred["crop"]
            image = image[y0:y1, x0:x1]
        result = analyze_layouts(pred.get("top"), pred.get("front"), pred["grid"], cfg, source=str(path))
        cuts = frame_cuts(pred["shelf_spans"]) if "shelf_spans" in pred and args.shelf_length is None else []
        warn = (f"{path}: the frame cuts {', '.join(cuts)}: a cut shelf's length, and so every metric size and "
                f"volume, is inferred from what stands on it, not seen (--shelf-length fixes the scale)") if cuts else None
        return result, image, warn

    for sid, path in zip(unique_ids(files), files):
        yield sid, (lambda p=path: one(p))


def run(args) -> int:
    from racklay.atomic import atomic_write_json
    from racklay.commands import CLIError, check_out_folder

    if args.layouts and args.inputs:
        raise CLIError("give either --layouts ROOT or IMAGE_OR_FOLDER, not both")
    if args.layouts and args.weights:
        raise CLIError("--weights is for photos; --layouts ROOT analyses ground-truth layouts (no model)")
    if args.layouts and args.shelf_length:
        raise CLIError("--shelf-length scales a model's predictions; --layouts are ground truth, already metric")
    if args.layouts and args.rack_box:
        raise CLIError("--rack-box tells a model which rack to read; --layouts are ground truth")
    if args.layouts and args.flip_average:
        raise CLIError("--flip-average is how a model predicts; --layouts are ground truth")
    if not args.layouts:
        if not args.inputs:
            raise CLIError("nothing to analyse: give IMAGE_OR_FOLDER with --weights, or --layouts ROOT")
        from racklay.release import weights_for_cli

        args.weights = weights_for_cli(args.weights)
    out = Path(args.out)
    check_out_folder(out)
    samples = _samples_from_layouts(args) if args.layouts else _samples_from_photos(args)
    summary, failed = [], 0
    for n, (sid, thunk) in enumerate(samples):
        if args.limit is not None and n >= args.limit:
            break
        try:
            result, image, warn = thunk()
        except (ValueError, OSError) as e:  # an input that cannot be read (DataError / LayoutError name the file)
            failed += 1
            print(f"racklay analyze: error: {e}", file=sys.stderr)
            summary.append({"id": sid, "error": str(e)})
            continue
        if warn:
            print(f"racklay analyze: warning: {warn}", file=sys.stderr)
        # an output that cannot be written stops the command (one line naming the file), as in predict
        write_outputs(result, out, sid, image, args.format, render=not args.no_render)
        print(f"{sid}: {result.report()}", flush=True)
        summary.append({"id": sid, "n_shelves": result.n_shelves, "n_box_stacks": result.n_box_stacks,
                        "capacity_m3": round(result.capacity_m3, 6), "free_m3": round(result.free_m3, 6),
                        "free_fraction": None if result.free_fraction is None else round(result.free_fraction, 6),
                        "warnings": result.warnings()})
    if not summary:
        raise CLIError("nothing analysed (empty dataset or split)")
    atomic_write_json(out / "summary.json", {"analysed": len(summary) - failed, "failed": failed, "images": summary})
    done = len(summary) - failed
    print(f"{done} rack(s) analysed, {failed} failed; results in {out}")
    return 1 if failed else 0
