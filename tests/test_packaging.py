"""Data the code needs at run time ships inside the packages (importlib.resources), in one home."""
from __future__ import annotations

from conftest import REAL_PHOTOS, REPO


def test_recipes_are_package_data():
    from racklay.synth.recipe import RECIPE_DIR, load_recipe

    assert RECIPE_DIR.is_relative_to(REPO / "racklay") or "site-packages" in str(RECIPE_DIR)
    names = sorted(p.stem for p in RECIPE_DIR.glob("*.yaml"))
    assert names == ["complex", "mixed", "pallet", "proxy_real", "release", "simple"]
    for name in names:
        assert load_recipe(name).name == name
    assert not list((REPO / "datasets" / "recipes").glob("*.yaml")), "recipes have one home: racklay/synth/recipes/"


def test_demo_photos_are_identical_copies_of_datasets_real_photos():
    """transfer/photos/ (package data) mirrors datasets/real-photos/ (the annotation project):
    same photos, same bytes, same attribution file."""
    from transfer.demo import PHOTOS

    home = REAL_PHOTOS
    want = sorted(p.name for p in home.iterdir() if p.suffix == ".jpg") + ["SOURCES.tsv"]
    got = sorted(p.name for p in PHOTOS.iterdir() if p.name != "README.md")
    assert sorted(got) == sorted(want), "copy datasets/real-photos/*.jpg and SOURCES.tsv to transfer/photos/"
    for name in want:
        assert (PHOTOS / name).read_bytes() == (home / name).read_bytes(), f"transfer/photos/{name} differs"


def test_package_data_patterns_cover_what_the_code_reads():
    import tomllib

    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    for pkg, patterns in data.items():
        for pat in patterns:
            assert list((REPO / pkg).glob(pat)), f"package-data {pkg}: {pat} matches nothing"
    assert "synth/recipes/*.yaml" in data["racklay"] and "photos/*.jpg" in data["transfer"]
