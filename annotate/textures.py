"""Box faces of labelled photos as WareSynth carton textures (`annotate textures`).

Renders whose cartons wear the faces of real loads look more like a site's photos: a renders-only
model trained on `mixed` with the faces of 36 labelled photos of other sites as carton textures
scored 49.7 / 47.9 box IoU on the real test site against 40.6 / 43.6 without (two render draws
each; level once both are calibrated on photos, docs/results/2026-11-27-thirteenth-session.md). Each labelled box's front face is
rectified through the rack plane (annotate.geometry), cut into tiles about TILE_M metres a side
(a pallet load is many cartons; one synthetic carton face should show about one), brought to one
median brightness (the renderer lights the texture; the photo's own lighting would be applied
twice) and written as TEXTURE_PX-square JPEGs, which `racklay synth --set texture_dir=FOLDER`
adds to every carton category's textures. A box the frame cuts gives the tiles of its visible
part (appearance, not size, is what a texture needs); tiles smaller than MIN_TILE_PX in the
photo, or reaching outside it, are left out (counted in the summary). The folder is built beside
`out` and renamed into place at the end, so a failure leaves nothing half-written.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from annotate import geometry as G
from annotate.dataset import check_statuses, staged_folder
from annotate.store import DONE_STATUSES, Project

#: a tile's side on the rack plane, metres (about one carton)
TILE_M = 0.45
#: the --tile values accepted, metres: from a small carton's face to a pallet load's (a tile of
#: millimetres would cut each box into thousands of textures, for minutes)
TILE_RANGE_M = (0.05, 3.0)
#: written texture size, pixels a side (WareSynth's texture layers are 256 x 256)
TEXTURE_PX = 256
#: a tile narrower or lower than this in the photo has too few pixels to be a texture
MIN_TILE_PX = 24
#: every texture's median luminance is scaled to this (0-255)
TARGET_LUMA = 150.0
#: boxes smaller than this (metres, width or height) are not textures of a load
MIN_BOX_M = 0.1


def box_tiles(box: G.MetricBox, tile: float = TILE_M) -> list[tuple[float, float, float, float]]:
    """A box's front face (u0, u1, v0, v1 on the rack plane) cut into round(size / tile) tiles
    along each side (at least one)."""
    w, h = box.u1 - box.u0, box.v1 - box.v0
    nx, ny = max(1, round(w / tile)), max(1, round(h / tile))
    return [(box.u0 + w * i / nx, box.u0 + w * (i + 1) / nx, box.v0 + h * j / ny, box.v0 + h * (j + 1) / ny)
            for i in range(nx) for j in range(ny)]


def face_texture(image: np.ndarray, plane: G.RackPlane, rect, size: int = TEXTURE_PX) -> np.ndarray | None:
    """The photo's pixels inside `rect` (u0, u1, v0, v1 on the rack plane) rectified to a
    size x size RGB texture with its median luminance at TARGET_LUMA; None when the rectangle
    leaves the photo or covers fewer than MIN_TILE_PX pixels a side."""
    import cv2

    u0, u1, v0, v1 = rect
    src = plane.to_image([[u0, v1], [u1, v1], [u1, v0], [u0, v0]])      # TL, TR, BR, BL in the photo
    h, w = image.shape[:2]
    if src[:, 0].min() < 0 or src[:, 1].min() < 0 or src[:, 0].max() > w or src[:, 1].max() > h:
        return None
    if np.ptp(src[:, 0]) < MIN_TILE_PX or np.ptp(src[:, 1]) < MIN_TILE_PX:
        return None
    dst = np.float32([[0, 0], [size - 1, 0], [size - 1, size - 1], [0, size - 1]])
    tex = cv2.warpPerspective(image, cv2.getPerspectiveTransform(src.astype(np.float32), dst), (size, size),
                              flags=cv2.INTER_LINEAR).astype(np.float32)
    luma = float(np.median(tex.mean(2)))
    return np.clip(tex * (TARGET_LUMA / max(luma, 8.0)), 0, 255).astype(np.uint8)


def texture_prefixes(names: list[str]) -> dict[str, str]:
    """Photo name -> the prefix of its texture files: the file stem, or stem_EXT where two photos
    share a stem ('a.jpg' and 'a.png' give 'a_jpg' and 'a_png', so neither overwrites the other)."""
    stems = [Path(n).stem for n in names]
    return {n: s if stems.count(s) == 1 else f"{s}_{Path(n).suffix.lstrip('.').lower()}"
            for n, s in zip(names, stems)}


def export_textures(project: Project, out: str | os.PathLike, split_of: dict[str, str] | None = None,
                    split: str | None = None, only_status=DONE_STATUSES, tile: float = TILE_M,
                    progress: bool = False) -> dict:
    """Write the tiles of every labelled box of the finished photos (those of `split` in
    `split_of` when given) as JPEG textures into the new or empty folder `out`, named
    PHOTO-STEM_bBOXID_KK.jpg (KK: the tile; texture_prefixes). Returns a summary: photos, textures, and what was
    left out (boxes too small; tiles too small or reaching outside the photo). An annotation that
    gives no scene is an error naming its file."""
    import cv2

    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: not a new or empty folder; choose a new folder")
    if not TILE_RANGE_M[0] <= tile <= TILE_RANGE_M[1]:
        raise ValueError(f"--tile: {tile} m is not a carton face's size (use {TILE_RANGE_M[0]} to {TILE_RANGE_M[1]} m)")
    if split is not None and split_of is None:
        raise ValueError("--split needs --split-file (which photo is in which split)")
    check_statuses(only_status)
    names = []
    for name in project.images():
        ann = project.read_annotation(name)
        if ann is None or ann["status"] not in only_status:
            continue
        if split is not None and split_of.get(name) != split:
            continue
        names.append((name, ann))
    if not names:
        known = f" (the split file names: {', '.join(sorted(set(split_of.values())))})" if split else ""
        raise ValueError(f"{project.root}: no photo with status {', '.join(only_status)}"
                         + (f" in split {split!r}{known}" if split else ""))
    prefix = texture_prefixes([name for name, _ in names])
    left = {"boxes too small": 0, "tiles too small or outside the photo": 0}
    n = 0
    with staged_folder(out) as tmp:
        it = names
        if progress:
            from tqdm import tqdm
            it = tqdm(names, desc="textures", unit="photo")
        for name, ann in it:
            try:
                scene = G.build_scene(ann, project.settings)
            except G.GeometryError as e:
                raise ValueError(f"{project.annotation_path(name)}: cannot rebuild the rack ({e})") from None
            image = project.read_image(name)
            for b in scene.boxes:
                if b.shelf is None or min(b.u1 - b.u0, b.v1 - b.v0) < MIN_BOX_M:
                    left["boxes too small"] += 1
                    continue
                for k, rect in enumerate(box_tiles(b, tile)):
                    tex = face_texture(image, scene.plane, rect)
                    if tex is None:
                        left["tiles too small or outside the photo"] += 1
                        continue
                    path = tmp / f"{prefix[name]}_b{b.id}_{k:02d}.jpg"
                    if not cv2.imwrite(str(path), tex[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90]):
                        raise OSError(f"{path}: could not be written")
                    n += 1
        if n == 0:
            raise ValueError(f"{project.root}: no box gave a texture ("
                             + ", ".join(f"{v} {k}" for k, v in left.items()) + ")")
    return {"out": str(out), "photos": len(names), "textures": n, "left_out": left}
