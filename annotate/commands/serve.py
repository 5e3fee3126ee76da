"""annotate serve PROJECT_DIR"""
from __future__ import annotations

import argparse


def port_number(text: str) -> int:
    """argparse type of --port: a whole number from 1 to 65535."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number (1-65535)") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is not a port number (1-65535)")
    return port


def pixel_aspect_value(text: str) -> float:
    """argparse type of --pixel-aspect: a number (1.778) or a ratio W:H of the photo as taken over
    the photo as stored, e.g. 16:9 for 16:9 frames stored as squares."""
    from annotate.schema import PIXEL_ASPECT_RANGE

    try:
        if ":" in text:
            w, h = (float(x) for x in text.split(":"))
            value = w / h
        else:
            value = float(text)
    except (ValueError, ZeroDivisionError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a pixel aspect (a number like 1.778 or a ratio like 16:9)") from None
    lo, hi = PIXEL_ASPECT_RANGE
    if not lo <= value <= hi:
        raise argparse.ArgumentTypeError(f"pixel aspect {value:g} is outside {lo:g}-{hi:g}")
    return value


def register(sub) -> None:
    from annotate.geometry import GapSplit
    from racklay.config import add_flags
    from racklay.predict import add_precision_args

    p = sub.add_parser(
        "serve", help="open the annotation tool in the browser",
        description="Serve the annotation tool for the photos in PROJECT_DIR (a folder of .jpg/.png "
                    "files; the tool keeps project.json and annotations/ there). Every click is saved at "
                    "once. Binds to 127.0.0.1 unless --host says otherwise; nothing is fetched from the "
                    "internet. Open the printed address in a browser.")
    p.add_argument("project", help="project folder (created if missing)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=port_number, default=7860,
                   help="port, 1-65535 (default 7860); a busy port is refused with a one-line error")
    p.add_argument("--model", default=None, metavar="FILE",
                   help="checkpoint for model-assisted pre-labels (default: the shipped model, docs/model-card.md)")
    p.add_argument("--no-model", action="store_true", help="no model-assisted pre-labels")
    p.add_argument("--backend", default="torch", choices=("torch", "onnx"), help="prediction backend for --model")
    add_precision_args(p)
    p.add_argument("--pixel-aspect", type=pixel_aspect_value, default=None, metavar="W:H",
                   help="the project's photos are stored squeezed: width / height of one stored pixel, as a "
                        "ratio (16:9 for 16:9 frames stored as squares) or a number; saved in project.json, so "
                        "give it once (1 undoes it). The tool shows the photos as taken, the model and the "
                        "camera see them so, and `annotate export` writes them so")
    p.add_argument("--auth-file", default=None, metavar="FILE",
                   help="require a login; FILE lists the users with salted password hashes "
                        "(create it with `annotate passwd FILE USER`)")
    g = p.add_argument_group("cutting at the photo's gaps (model proposals and W; docs/annotate.md)")
    add_flags(g, GapSplit, ["depth", "close_m", "min_part_m"], default=None)
    # removed: it put the password on the command line (ps, shell history); kept only to say so
    p.add_argument("--auth", default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def run(args) -> int:
    from annotate.auth import Authenticator
    from annotate.geometry import GapSplit
    from annotate.server import serve
    from racklay.commands import CLIError

    if args.auth is not None:
        raise CLIError("--auth USER:PASSWORD is no longer accepted: it puts the password on the command line "
                       "(visible in ps and the shell history). Create a login file with `annotate passwd FILE "
                       "USER` (asks for the password) and pass --auth-file FILE")
    auth = Authenticator(args.auth_file) if args.auth_file else None
    model = None
    if not args.no_model:
        from racklay.release import weights_for_cli

        model = weights_for_cli(args.model, quiet=True, flag="--model")   # serve names its model once it listens
    if args.pixel_aspect is not None:
        from annotate.store import Project

        project = Project(args.project)
        project.save_settings(dict(project.settings, pixel_aspect=round(args.pixel_aspect, 6)))
        print(f"annotate: {args.project}: pixel aspect {args.pixel_aspect:.4g} saved in project.json")
    gap_split = GapSplit(**{k: getattr(args, k) for k in ("depth", "close_m", "min_part_m")
                            if getattr(args, k) is not None})      # the flags' bounds are checked by argparse
    serve(args.project, host=args.host, port=args.port, model=model, backend=args.backend, auth=auth,
          gap_split=gap_split, precision=args.precision)
    return 0
