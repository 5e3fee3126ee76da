"""annotate import DATASET_ROOT PROJECT_DIR"""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "import", help="bring a RackLay-format dataset into a project for review",
        description="Copy the photos of a RackLay-format dataset into PROJECT_DIR (as DATASET_ID.png) "
                    "with their top/front layouts attached read-only, status 'needs review'. In the tool "
                    "the imported layouts are shown beside the photo and, once the rack corners and "
                    "shelves are marked, their boxes are outlined on the photo. Every photo and layout "
                    "file is checked before anything is written: a bad or missing one (e.g. layouts "
                    "without a photo) stops the import with a message naming it, and the project is "
                    "left as it was.")
    p.add_argument("dataset", help="RackLay-format dataset folder")
    p.add_argument("project", help="project folder (created if missing)")
    p.add_argument("--split", default=None, help="import only this split (default: every image)")
    p.set_defaults(func=run)


def run(args) -> int:
    from annotate.dataset import check_import, import_dataset
    from annotate.store import Project

    plan = check_import(args.dataset, split=args.split)  # before the project folder is created
    added = import_dataset(plan, Project(args.project))
    print(f"imported {len(added)} image(s) into {args.project} (status: needs review)")
    return 0
