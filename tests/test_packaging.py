"""Data the code needs at run time ships inside the packages (importlib.resources), in one home."""
from __future__ import annotations

from conftest import REAL_PHOTOS, REPO


def test_recipes_are_package_data():
    from racklay.synth.recipe import RECIPE_DIR, load_recipe

    assert RECIPE_DIR.is_relative_to(REPO / "racklay") or "site-packages" in str(RECIPE_DIR)
    names = sorted(p.stem for p in RECIPE_DIR.glob("*.yaml"))
    assert names == ["boltless", "complex", "complex_paper", "complex_paper_fixed", "cube", "mixed", "mixed_cover", "mixed_wide", "pallet", "proxy_real", "release", "simple", "slotted", "wire"]
    for name in names:
        assert load_recipe(name).name == name
    assert not list((REPO / "datasets" / "recipes").glob("*.yaml")), "recipes have one home: racklay/synth/recipes/"


def test_demo_photos_are_identical_copies_of_datasets_real_photos():
    """transfer/photos/ (package data) holds the demo's photos, each a byte-for-byte copy of its
    namesake in datasets/real-photos/ (the annotation project, their one home), with their rows of
    its SOURCES.tsv (the attribution travels with them)."""
    import csv

    from transfer.demo import PHOTOS

    photos = sorted(p.name for p in PHOTOS.glob("*.jpg"))
    assert len(photos) >= 20
    assert sorted(p.name for p in PHOTOS.iterdir()) == sorted(photos + ["README.md", "SOURCES.tsv"])
    for name in photos:
        assert (REAL_PHOTOS / name).is_file(), f"transfer/photos/{name} is not in datasets/real-photos/"
        assert (PHOTOS / name).read_bytes() == (REAL_PHOTOS / name).read_bytes(), f"transfer/photos/{name} differs"

    def rows(path):
        with open(path, newline="") as f:
            return {r["file"]: r for r in csv.DictReader(f, delimiter="\t")}

    home, here = rows(REAL_PHOTOS / "SOURCES.tsv"), rows(PHOTOS / "SOURCES.tsv")
    assert sorted(here) == photos
    assert all(here[n] == home[n] for n in photos), "copy the photos' rows of datasets/real-photos/SOURCES.tsv"


def test_package_data_patterns_cover_what_the_code_reads():
    import tomllib

    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    for pkg, patterns in data.items():
        for pat in patterns:
            assert list((REPO / pkg).glob(pat)), f"package-data {pkg}: {pat} matches nothing"
    assert "synth/recipes/*.yaml" in data["racklay"] and "photos/*.jpg" in data["transfer"]
