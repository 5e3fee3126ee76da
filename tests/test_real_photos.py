"""The labelled real photos (datasets/real-photos/): what every real-photo score and release
decision relies on: one attributed source row and one valid label per photo, photos within the
size rule, and splits that keep sites and videos apart, the holdout above all."""
import csv
from collections import defaultdict

from annotate.dataset import HOLDOUT_SPLIT, read_split_file
from annotate.schema import load_annotation
from annotate.store import DONE_STATUSES, Project
from conftest import REAL_PHOTOS
from racklay.checkpoint import load_checkpoint
from racklay.release import release_weights

MAX_PHOTO_BYTES = 200_000   # the project's rule for photos kept in git


def source_rows() -> list[dict]:
    with open(REAL_PHOTOS / "SOURCES.tsv", newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f, delimiter="\t"))


def test_every_photo_has_one_attributed_source_row_a_finished_label_and_fits_the_size_rule():
    photos = Project(REAL_PHOTOS, create=False).images()
    split_of = read_split_file(REAL_PHOTOS / "SOURCES.tsv")      # strict: one row per photo
    assert sorted(split_of) == photos, "SOURCES.tsv rows and the photos in the folder differ"
    for r in source_rows():
        assert all(r[c].strip() for c in ("repo", "path_in_repo", "commit", "licence", "site")), r["file"]
        assert len(r["commit"]) == 40, f"{r['file']}: commit {r['commit']!r} is not a full SHA"
    for name in photos:
        assert (REAL_PHOTOS / name).stat().st_size <= MAX_PHOTO_BYTES, f"{name} is over {MAX_PHOTO_BYTES} bytes"
        ann = load_annotation(REAL_PHOTOS / "annotations" / f"{name}.json")   # validates every field
        assert ann["status"] in DONE_STATUSES and ann["boxes"] and ann["shelves"], name


def test_splits_keep_videos_apart_and_holdout_sites_away_from_every_training_photo():
    """No video is in two splits; a site of the holdout has no photo in any other split; and the
    shipped model was fine-tuned on no photo of a holdout site (its scores there are a new
    site's, as docs/model-card.md reports them)."""
    rows = source_rows()
    splits_of_site, splits_of_video = defaultdict(set), defaultdict(set)
    for r in rows:
        splits_of_site[r["site"]].add(r["split"])
        if r["video"] != "-":
            splits_of_video[r["video"]].add(r["split"])
    assert all(len(s) == 1 for s in splits_of_video.values()), dict(splits_of_video)
    holdout_sites = {site for site, splits in splits_of_site.items() if HOLDOUT_SPLIT in splits}
    assert holdout_sites, "no holdout split in SOURCES.tsv"
    mixed = {site: splits for site, splits in splits_of_site.items() if site in holdout_sites and splits != {HOLDOUT_SPLIT}}
    assert not mixed, f"holdout sites with photos in other splits: {mixed}"

    site_of = {r["file"]: r["site"] for r in rows}
    tuned = load_checkpoint(release_weights()).meta.get("fine_tuned_on_photos", [])
    assert tuned, "the shipped model's meta lists no photos it was fine-tuned on"
    assert not {site_of.get(n) for n in tuned} & holdout_sites
