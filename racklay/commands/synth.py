"""racklay synth --recipe complex --n 2000 --out datasets/generated/complex --seed 0"""
from __future__ import annotations

from racklay.commands import add_progress_arg, show_progress
from racklay.config import at_least


def register(sub) -> None:
    import argparse

    from racklay.synth.recipe import builtin_recipes

    p = sub.add_parser(
        "synth", help="generate a synthetic RackLay dataset (WareSynth: procedural racks, exact ground truth)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Generate a RackLay-format dataset with WareSynth: procedural warehouse racks rendered with "
            "moderngl (EGL; CPU llvmpipe or GPU) with exact layouts plus depth, normals, semantic/instance "
            "masks, 2D/3D boxes, COCO and KITTI labels.\n\n"
            "Every image depends only on (recipe, --seed, index): re-running resumes (finished indices are "
            "kept), --workers and --shard give byte-identical files. To scale out, run `--shard i/n` for "
            "i = 0..n-1 on several machines with the same --out name, copy the folders together, and run "
            "the same command once more without --shard: it finds every index finished and rebuilds the "
            "split files and COCO annotations. See docs/waresynth.md."),
        epilog="recipe keys (override with --set key=value):\n" + _keys_help())
    p.add_argument("--recipe", default=None,
                   help=f"built-in recipe name ({', '.join(builtin_recipes())}: racklay/synth/recipes/, "
                        "docs/waresynth.md) or a YAML path (default complex)")
    p.add_argument("--n", type=at_least(1), default=None, help="number of images in the whole dataset (all shards; "
                   "required unless --relayout)")
    p.add_argument("--out", required=True, help="output dataset folder")
    p.add_argument("--seed", type=at_least(0), default=None, help="dataset seed (default 0)")
    p.add_argument("--shard", default=None, metavar="i/n", help="generate only indices with index %% n == i")
    p.add_argument("--workers", type=at_least(1), default=1, help="worker processes, each with its own GL context (default 1)")
    p.add_argument("--lp-threads", type=at_least(0), default=None,
                   help="llvmpipe rasteriser threads per worker (LP_NUM_THREADS; 0 = the worker's own thread, "
                        "the default with --workers > 1; with one worker llvmpipe's default, one per core)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a recipe key, YAML value: --set box_density=[0.2,0.9] --set shadows=false")
    p.add_argument("--fsync", action="store_true",
                   help="force every file to disk before its rename (survives power loss; slower). Without it "
                        "files are still written to a temporary name and renamed, so an interrupted run never "
                        "leaves half a file")
    p.add_argument("--relayout", default=None, metavar="SET",
                   help="instead of rendering, copy the WareSynth set SET to --out with its layouts redrawn under "
                        "the layout keys given with --set (layout_extent, layout_size, extent_m): every scene is "
                        "sampled again and checked against its meta, images and maps are hard-linked (or copied). "
                        "E.g. --relayout sets/mixed --out sets/mixed-row --set layout_extent=row")
    add_progress_arg(p)
    p.set_defaults(func=run)


def _keys_help() -> str:
    from racklay.synth.recipe import Recipe
    return Recipe.fields_help()


def run(args) -> int:
    from racklay.commands import CLIError
    from racklay.synth.generate import WorkerCrash, generate_dataset, parse_shard
    from racklay.synth.recipe import RecipeError, load_recipe

    if args.relayout:
        return _relayout(args)
    if args.n is None:
        raise CLIError("--n is required: the number of images in the whole dataset (all shards)")
    try:
        recipe = load_recipe(args.recipe or "complex", args.set)
        parse_shard(args.shard)
    except RecipeError as e:
        raise CLIError(str(e)) from None
    if args.n < 1:
        raise CLIError(f"--n must be >= 1, got {args.n}")
    if args.workers < 1:
        raise CLIError(f"--workers must be >= 1, got {args.workers}")
    try:
        res = generate_dataset(recipe, args.n, args.out, seed=args.seed or 0, shard=args.shard, workers=args.workers,
                               progress=show_progress(args), lp_threads=args.lp_threads, fsync=args.fsync)
    except WorkerCrash as e:
        raise CLIError(str(e)) from None
    done = len(res.generated)
    rate = done / res.wall * 60 if res.wall > 0 and done else 0.0
    splits = ", ".join(f"{k}={v}" for k, v in res.splits.items())
    print(f"{args.out}: generated {done}, already finished {res.skipped} ({rate:.0f} images/min); splits: {splits}")
    return 0


def _relayout(args) -> int:
    from racklay.commands import CLIError
    from racklay.synth.generate import RelayoutError, relayout_dataset
    from racklay.synth.recipe import RecipeError

    given = [f for f, v in (("--recipe", args.recipe), ("--n", args.n), ("--seed", args.seed),
                            ("--shard", args.shard)) if v is not None]
    if given:
        raise CLIError(f"--relayout takes the recipe, --n and --seed of the set it copies: drop {', '.join(given)}")
    try:
        res = relayout_dataset(args.relayout, args.out, args.set, progress=show_progress(args))
    except (RecipeError, RelayoutError) as e:
        raise CLIError(str(e)) from None
    splits = ", ".join(f"{k}={v}" for k, v in res.splits.items())
    print(f"{args.out}: layouts redrawn for {len(res.generated)}, already finished {res.skipped} "
          f"(from {args.relayout}); splits: {splits}")
    return 0
