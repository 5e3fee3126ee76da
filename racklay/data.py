"""RackLay-format datasets on disk: reading, writing and validating.

Layout of a dataset root (exactly what the authors' downloads look like)::

    ROOT/
      Images/000000.png              RGB image (.png; .jpg/.jpeg also read)
      topLayouts/top000000.npy       (R, D, D) uint8, values 0 / 115 / 255
      frontLayouts/front000000.npy   (R, D, D) uint8, values 0 / 115 / 255
      meta/000000.json               optional per-image metadata (WareSynth extras; photos
                                     exported by annotate: the source photo, the labelled
                                     geometry and `level_spans`, see `level_spans`)
      splits/train.txt val.txt test.txt   one entry per line

Either layout folder may be absent (a view-specific dataset). A split entry is an image path
(`Images/000123.png`, absolute paths from another machine too) or a bare id (`000123`); the
sample id is the file stem. This module never imports torch; `racklay.torchdata` wraps it.
"""
from __future__ import annotations

import json
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from . import layout as L
from .atomic import atomic_save_npy, atomic_save_png, atomic_write_json, atomic_write_text

IMAGES_DIR, TOP_DIR, FRONT_DIR, META_DIR, SPLITS_DIR = "Images", "topLayouts", "frontLayouts", "meta", "splits"
SYNTH_MANIFEST = "waresynth.json"   # written by racklay synth; marks a generated dataset
VIEW_DIRS = {"top": TOP_DIR, "front": FRONT_DIR}
VIEW_PREFIX = {"top": "top", "front": "front"}
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
#: file types read_image decodes: what a folder of photos given to a command is taken to hold
PHOTO_EXTS = IMAGE_EXTS + (".bmp", ".webp", ".tif", ".tiff")
SPLIT_NAMES = ("train", "val", "test")


class DataError(ValueError):
    """A file in a dataset that cannot be used; the message names the file."""


def check_prediction_out(out: str | os.PathLike, data: str | os.PathLike | None = None) -> None:
    """Refuse to write predicted layouts into a folder that holds ground truth: the dataset being
    evaluated, or any dataset with split files or a WareSynth manifest. A folder of earlier
    predictions (layouts without splits) may be overwritten."""
    out = Path(out)
    if data is not None and out.resolve() == Path(data).resolve():
        raise DataError(f"{out}: is the dataset being scored; predictions would overwrite its ground "
                        "truth; choose another output folder")
    for marker in (SPLITS_DIR, SYNTH_MANIFEST):
        if (out / marker).exists():
            raise DataError(f"{out}: holds a dataset with ground truth ({marker} found); predictions "
                            "would overwrite its layouts; choose another output folder")


#: images above this many pixels (width x height) are refused from their header, before any
#: pixel is decoded: a 30000 x 30000 PNG is under 1 MB on disk but 2.7 GB decoded
DEFAULT_MAX_MEGAPIXELS = 40
MAX_MEGAPIXELS_ENV = "RACKLAY_MAX_MEGAPIXELS"


def max_image_pixels() -> int:
    """The pixel limit of read_image: RACKLAY_MAX_MEGAPIXELS (a number of megapixels) or 40 Mpx."""
    text = os.environ.get(MAX_MEGAPIXELS_ENV, "").strip()
    if not text:
        return DEFAULT_MAX_MEGAPIXELS * 10**6
    try:
        mp = float(text)
        if not (0 < mp < float("inf")):
            raise ValueError
    except ValueError:
        raise DataError(f"{MAX_MEGAPIXELS_ENV}={text!r}: expected a number of megapixels > 0") from None
    return int(mp * 10**6)


@dataclass(frozen=True)
class ImageInfo:
    """What an image file's header says: format ('PNG', 'JPEG', or PIL's name) and size as the
    image is shown and decoded, i.e. after its EXIF orientation (`orientation`, 1-8; 5-8 turn the
    stored image by 90 degrees, so a portrait phone photo stored as 4032x3024 is 3024x4032)."""

    format: str
    width: int
    height: int
    orientation: int = 1


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _read_header(f, source: str) -> ImageInfo:
    """Format and size from the header alone (PNG IHDR, JPEG frame header; other formats through
    PIL, which also reads only the header)."""
    import struct

    head = f.read(32)
    orientation = 1
    if head[:8] == b"\x89PNG\r\n\x1a\n":
        if len(head) < 24 or head[12:16] != b"IHDR":
            raise DataError(f"{source}: not a readable image (PNG without an IHDR header)")
        w, h = struct.unpack(">II", head[16:24])
        return ImageInfo("PNG", w, h)
    if head[:2] == b"\xff\xd8":
        f.seek(2)
        while True:
            b = f.read(1)
            while b and b != b"\xff":          # bytes between segments (tolerated, as decoders do)
                b = f.read(1)
            while b == b"\xff":                # fill bytes
                b = f.read(1)
            if not b:
                break
            m = b[0]
            if m == 0x01 or 0xD0 <= m <= 0xD8:  # markers without a segment
                continue
            if m in (0xD9, 0xDA):               # end of image / start of scan before any frame header
                break
            seg = f.read(2)
            if len(seg) < 2:
                break
            n = struct.unpack(">H", seg)[0]
            if m in _JPEG_SOF:
                body = f.read(5)
                if len(body) < 5:
                    break
                h, w = struct.unpack(">HH", body[1:5])
                if not (w and h):
                    break
                return ImageInfo("JPEG", *((h, w) if orientation >= 5 else (w, h)), orientation)
            if m == 0xE1 and n >= 8:
                body = f.read(n - 2)
                orientation = _exif_orientation(body) or orientation
                continue
            f.seek(n - 2, 1)
        raise DataError(f"{source}: not a readable image (JPEG without a frame header; truncated?)")
    import warnings

    from PIL import Image

    f.seek(0)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(f) as im:
                return ImageInfo(str(im.format), *im.size)
    except Image.DecompressionBombError:
        raise DataError(f"{source}: refused before decoding: its header declares over "
                        f"{2 * Image.MAX_IMAGE_PIXELS / 1e6:.0f} Mpx (a possible decompression bomb)") from None
    except Exception:  # noqa: BLE001 - PIL raises many types for junk
        raise DataError(f"{source}: not a readable image (corrupt, truncated or not an image)") from None


def _exif_orientation(app1: bytes) -> int | None:
    """The EXIF orientation (1-8) in a JPEG APP1 segment's body, or None (no EXIF, no such tag, or
    unreadable: the image is then shown as stored, as decoders do)."""
    import struct

    if app1[:6] != b"Exif\x00\x00":
        return None
    t = app1[6:]
    order = {b"II": "<", b"MM": ">"}.get(bytes(t[:2]))
    try:
        if order is None:
            return None
        off = struct.unpack(order + "I", t[4:8])[0]
        (count,) = struct.unpack(order + "H", t[off:off + 2])
        for k in range(count):
            e = t[off + 2 + 12 * k: off + 14 + 12 * k]
            tag, typ = struct.unpack(order + "HH", e[:4])
            if tag == 0x0112 and typ == 3:
                v = struct.unpack(order + "H", e[8:10])[0]
                return v if 1 <= v <= 8 else None
    except struct.error:
        return None
    return None


def check_image_pixels(info: ImageInfo, source: str, limit: int | None = None) -> None:
    """Refuse an image whose header declares more than `limit` pixels (default max_image_pixels())."""
    limit = max_image_pixels() if limit is None else limit
    w, h = info.width, info.height
    if w < 1 or h < 1:
        raise DataError(f"{source}: not a readable image (its header says {w}x{h} pixels)")
    if w * h > limit:
        raise DataError(f"{source}: {w}x{h} pixels ({w * h / 1e6:.0f} Mpx) is over the {limit / 1e6:g} Mpx "
                        f"limit; refused before decoding (a possible decompression bomb; set "
                        f"{MAX_MEGAPIXELS_ENV} to allow larger images)")


def image_info(source: str | os.PathLike | bytes, name: str | None = None) -> ImageInfo:
    """Format and size of an image file (a path, or the file's bytes) from its header, nothing
    decoded; DataError naming the file if it is not an image or is over the pixel limit."""
    import io

    if isinstance(source, (bytes, bytearray, memoryview)):
        name = name or "image"
        if not len(source):
            raise DataError(f"{name}: empty file")
        info = _read_header(io.BytesIO(source), name)
    else:
        path = Path(source)
        name = name or str(path)
        if not path.is_file():
            raise DataError(f"{name}: image file not found")
        with open(path, "rb") as f:
            if not f.read(1):
                raise DataError(f"{name}: not a readable image (empty file)")
            f.seek(0)
            info = _read_header(f, name)
    check_image_pixels(info, name)
    return info


def decode_image(data: bytes | np.ndarray, source: str, info: ImageInfo | None = None) -> np.ndarray:
    """Decode an image's bytes as RGB uint8 (H, W, 3) after the header checks of image_info()
    (`info`, when the caller has them already): the pixel limit comes first, so a decompression
    bomb is refused before a pixel is decoded. The one place the toolkit turns image bytes into
    pixels. Raises DataError naming `source`."""
    import cv2

    buf = data if isinstance(data, np.ndarray) else np.frombuffer(data, np.uint8)
    if info is None:
        info = image_info(buf.tobytes(), source)
    if info.format == "PNG" and not _png_complete(buf):
        # checked before decoding, so OpenCV prints no warning of its own
        raise DataError(f"{source}: truncated PNG (no IEND chunk)")
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(f"{source}: not a readable image (corrupt, truncated or not an image)")
    if img.shape[:2] != (info.height, info.width):
        turned = f" after EXIF orientation {info.orientation}" if info.orientation != 1 else ""
        raise DataError(f"{source}: decoded to {img.shape[1]}x{img.shape[0]} pixels but its header says "
                        f"{info.width}x{info.height}{turned}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as RGB uint8 (H, W, 3): the one function every command and the annotator
    read images with. The header is checked first (image_info: format, pixel limit), so a
    decompression bomb costs a few bytes of reading. Raises DataError naming the file."""
    path = Path(path)
    info = image_info(path)
    return decode_image(np.fromfile(str(path), dtype=np.uint8), str(path), info)


#: ITU-R BT.601 luma weights of R, G, B
LUMA_WEIGHTS = np.array([0.299, 0.587, 0.114], np.float32)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Luma (BT.601) of an RGB image (..., 3) as float32, in the image's own units (0-255 for
    uint8): what the annotator's gap cue and the benchmarks' contrast measures read."""
    return rgb[..., :3].astype(np.float32) @ LUMA_WEIGHTS


def _png_complete(data: np.ndarray) -> bool:
    tail = data[-12:].tobytes()
    return b"IEND" in tail


def load_npy(path: str | os.PathLike) -> np.ndarray:
    """np.load without pickles, with one-line errors (numpy's own advise allow_pickle for any
    file that is not .npy, which is the wrong advice here)."""
    path = Path(path)
    with open(path, "rb") as f:
        magic = f.read(6)
    if magic != b"\x93NUMPY":
        raise DataError(f"{path}: not a .npy file (no NumPy header)")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as e:  # numpy raises several types for bad files
        first = (str(e).splitlines() or [""])[0]
        raise DataError(f"{path}: not a readable .npy array ({type(e).__name__}: {first})") from None


def read_layout_file(path: str | os.PathLike, R: int | None = None, D: int | None = None) -> np.ndarray:
    """Load a RackLay .npy layout stack and return class ids (R, D, D) uint8. Strict."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: layout file not found")
    arr = load_npy(path)
    try:
        L.check_stack(arr, R=R, D=D, source=str(path))
    except L.LayoutError as e:
        raise DataError(str(e)) from None
    return L.decode(arr, str(path))


def npy_shape(path: str | os.PathLike) -> tuple[int, ...] | None:
    """The shape in a .npy file's header (the data are not read); None if it is not a readable
    .npy file (reading it properly then gives the one-line error)."""
    fmt = np.lib.format
    try:
        with open(path, "rb") as f:
            version = fmt.read_magic(f)
            read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            return tuple(read(f)[0])
    except Exception:  # noqa: BLE001 - any unreadable file: the caller reads it and reports it
        return None


def common_layout_shape(paths: Iterable[str | os.PathLike]) -> tuple[int, int] | None:
    """(R, D) of the layout stacks most of `paths` hold, from their headers; None if none is a
    readable (R, D, D) stack. A file that differs from it is the odd one out, so errors can name
    it rather than whichever file happened to be read first."""
    shapes = Counter(s for s in map(npy_shape, paths) if s is not None and len(s) == 3 and s[1] == s[2])
    if not shapes:
        return None
    R, D, _ = shapes.most_common(1)[0][0]
    return R, D


@dataclass
class RackLayRoot:
    """A RackLay-format dataset folder."""

    root: Path

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def require(self, what: str = "dataset") -> "RackLayRoot":
        """This dataset, or a one-line error naming the path: no such folder, or a file given
        where the `what` folder goes (an image or a split file instead of the dataset)."""
        if self.root.is_dir():
            return self
        if self.root.exists():
            raise DataError(f"{self.root}: is a file, not a {what} folder")
        raise FileNotFoundError(f"{self.root}: {what} folder not found")

    # --- paths ---
    def image_path(self, sid: str) -> Path:
        for ext in IMAGE_EXTS:
            p = self.root / IMAGES_DIR / f"{sid}{ext}"
            if p.exists():
                return p
        return self.root / IMAGES_DIR / f"{sid}.png"

    def layout_path(self, view: str, sid: str) -> Path:
        return self.root / VIEW_DIRS[view] / f"{VIEW_PREFIX[view]}{sid}.npy"

    def meta_path(self, sid: str) -> Path:
        return self.root / META_DIR / f"{sid}.json"

    def split_path(self, name: str) -> Path:
        return self.root / SPLITS_DIR / f"{name}.txt"

    # --- listing ---
    def layout_ids(self, view: str) -> list[str]:
        """Ids of the view's layout files (PREFIXNNNNNN.npy), sorted, whether or not a photo exists."""
        pre, d = VIEW_PREFIX[view], self.root / VIEW_DIRS[view]
        return sorted(p.stem[len(pre):] for p in d.glob(f"{pre}*.npy")) if d.is_dir() else []

    def views(self) -> tuple[str, ...]:
        """Views present in this dataset (a layout folder exists)."""
        return tuple(v for v in L.VIEWS if (self.root / VIEW_DIRS[v]).is_dir())

    def ids(self) -> list[str]:
        """All sample ids with an image, sorted."""
        d = self.root / IMAGES_DIR
        if not d.is_dir():
            return []
        return sorted(p.stem for p in d.iterdir() if p.suffix.lower() in IMAGE_EXTS and not p.name.startswith("."))

    def splits(self) -> list[str]:
        d = self.root / SPLITS_DIR
        return sorted(p.stem for p in d.glob("*.txt")) if d.is_dir() else []

    def split_ids(self, name: str) -> list[str]:
        """Sample ids listed in splits/NAME.txt, in file order. Clear error when missing."""
        p = self.split_path(name)
        if not p.is_file():
            found = ", ".join(self.splits()) or "none"
            raise DataError(f"{p}: split file not found (splits found in {self.root / SPLITS_DIR}: {found})")
        return [parse_split_entry(line) for line in p.read_text().splitlines() if line.strip()]

    def resolve(self, split: str | None) -> list[str]:
        """Ids of a split, or every image when split is None / 'all'."""
        return self.ids() if split in (None, "all") else self.split_ids(split)

    # --- reading ---
    def read_image(self, sid: str) -> np.ndarray:
        return read_image(self.image_path(sid))

    def read_layouts(self, view: str, sid: str, R: int | None = None, D: int | None = None) -> np.ndarray:
        return read_layout_file(self.layout_path(view, sid), R=R, D=D)

    def layout_shape(self, ids: Iterable[str] | None = None,
                     views: Sequence[str] | None = None) -> tuple[int, int] | None:
        """(R, D) most of the layout files of `ids` (default: all) in `views` (default: all) have;
        see common_layout_shape."""
        views = self.views() if views is None else views
        paths = [p for v in views
                 for p in (self.layout_path(v, sid) for sid in (self.layout_ids(v) if ids is None else ids))
                 if p.is_file()]
        return common_layout_shape(paths)

    def read_level_spans(self, sid: str, R: int) -> np.ndarray:
        """Sample `sid`'s labelled level spans (`level_spans`); all NaN without any."""
        return level_spans(self.read_meta(sid), R, str(self.meta_path(sid)))

    def read_meta(self, sid: str) -> dict | None:
        p = self.meta_path(sid)
        if not p.exists():
            return None
        try:
            return json.loads(p.read_text())
        except json.JSONDecodeError as e:
            raise DataError(f"{p}: invalid JSON ({e})") from None

    # --- writing (atomic) ---
    def write_sample(self, sid: str, image: np.ndarray | None = None, top: np.ndarray | None = None,
                     front: np.ndarray | None = None, meta: dict | None = None,
                     image_bytes: bytes | None = None) -> None:
        """Write one sample. `top`/`front` are class-id stacks (R, D, D); they are encoded to
        0/115/255 on the way out. `image_bytes` writes already-encoded PNG bytes."""
        from .atomic import atomic_write_bytes

        if image_bytes is not None:
            atomic_write_bytes(self.root / IMAGES_DIR / f"{sid}.png", image_bytes)
        elif image is not None:
            atomic_save_png(self.root / IMAGES_DIR / f"{sid}.png", image)
        for view, arr in (("top", top), ("front", front)):
            if arr is not None:
                L.check_stack(arr, encoded=False, source=f"{view} layouts of {sid}")
                atomic_save_npy(self.layout_path(view, sid), L.encode(arr))
        if meta is not None:
            atomic_write_json(self.meta_path(sid), meta)

    def write_split(self, name: str, ids: Iterable[str]) -> Path:
        check_split_name(name)
        lines = [f"{IMAGES_DIR}/{sid}.png" for sid in ids]
        return atomic_write_text(self.split_path(name), "\n".join(lines) + ("\n" if lines else ""))


#: the meta key of each level's span across the image (`level_spans`)
LEVEL_SPANS_KEY = "level_spans"
#: the height, as a fraction of a level's clear height above its board, at which a level's span
#: is read: low in the level, where its loads stand (a rack's front face is a trapezoid in a photo
#: taken from below or above, so the span depends on the height). `annotate export` and WareSynth
#: both write spans at this height.
SPAN_AT_CLEAR_HEIGHT = 0.3


def level_spans(meta: dict | None, R: int, source: str = "meta") -> np.ndarray:
    """A sample's labelled span of each of its first R levels across the image, (R, 2) float32:
    the image x of the rack's left and right ends (low in each level), in image widths (0 the left
    edge, 1 the right; beyond [0, 1] where the rack leaves the frame), NaN for a level without one.
    Read from meta["level_spans"], a list of [left, right] (or null) per level bottom-up, read at
    `SPAN_AT_CLEAR_HEIGHT` (`annotate export` writes it from the labelled rack, WareSynth from its
    camera); a malformed entry is a DataError naming `source`."""
    out = np.full((R, 2), np.nan, np.float32)
    raw = (meta or {}).get(LEVEL_SPANS_KEY)
    if raw is None:
        return out
    if not isinstance(raw, list):
        raise DataError(f"{source}: {LEVEL_SPANS_KEY} must be a list of [left, right] per level, got {type(raw).__name__}")
    for r, span in enumerate(raw[:R]):
        if span is None:
            continue
        ok = (isinstance(span, list) and len(span) == 2
              and all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in span))
        if not ok or not span[0] < span[1]:
            raise DataError(f"{source}: {LEVEL_SPANS_KEY}[{r}] must be [left, right] image widths with left < right, "
                            f"got {span!r}")
        out[r] = span
    return out


def check_split_name(name: str) -> str:
    """A split's name is a plain word (letters, digits, '_', '-', '.'; not starting with '.'): it
    becomes the file splits/NAME.txt inside the dataset, never a path out of it."""
    import re

    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name or ""):
        raise DataError(f"split name {name!r}: use letters, digits, '_', '-' or '.' (it names splits/NAME.txt)")
    return name


def parse_split_entry(line: str) -> str:
    """`Images/000123.png`, `/abs/path/000123.png`, `000123` -> `000123`."""
    entry = line.strip().replace("\\", "/").split()[0]
    name = entry.rsplit("/", 1)[-1]
    stem, dot, ext = name.rpartition(".")
    return stem if dot and ("." + ext.lower()) in IMAGE_EXTS + (".npy",) else name


def make_splits(ids: Sequence[str], fractions: dict[str, float] | None = None, seed: int = 0, *,
                counts: dict[str, int] | None = None) -> dict[str, list[str]]:
    """Shuffle ids reproducibly (numpy's default_rng(seed)) and cut them into named splits, in
    the order given, each sorted: by `fractions` (>= 0, summing to <= 1; when they sum to 1 the
    last split takes the rest) or by exact `counts` (whole numbers >= 0, at most len(ids) in all).
    The same ids and seed give the same shuffle either way."""
    if (fractions is None) == (counts is None):
        raise ValueError("make_splits: give either split fractions or split counts")
    if counts is not None:
        if any(int(c) != c or c < 0 for c in counts.values()):
            raise ValueError(f"split counts must be whole numbers >= 0, got {counts}")
        if sum(counts.values()) > len(ids):
            raise ValueError(f"split counts ask for {int(sum(counts.values()))} ids but there are {len(ids)}")
        sizes = {name: int(c) for name, c in counts.items()}
    else:
        total = sum(fractions.values())
        if total > 1 + 1e-9 or any(f < 0 for f in fractions.values()):
            raise ValueError(f"split fractions must be >= 0 and sum to <= 1, got {fractions}")
        names = list(fractions)
        sizes, given = {}, 0
        for i, name in enumerate(names):
            last = i == len(names) - 1 and total >= 1 - 1e-9
            sizes[name] = len(ids) - given if last else round(fractions[name] * len(ids))
            given += sizes[name]
    order = list(ids)
    np.random.default_rng(seed).shuffle(order)
    out, start = {}, 0
    for name, n in sizes.items():
        out[name] = sorted(order[start:start + n])
        start += n
    return out


# --- validation ---------------------------------------------------------------------------
@dataclass
class CheckReport:
    root: Path
    samples: int = 0
    views: tuple[str, ...] = ()
    R: int | None = None
    D: int | None = None
    splits: dict[str, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        sp = ", ".join(f"{k}={v}" for k, v in self.splits.items()) or "none"
        shape = f"R={self.R}, D={self.D}" if self.R else ("no valid layouts" if self.views else "no layouts")
        status = "OK" if self.ok else f"{len(self.problems)} problem(s)"
        return (f"{self.root}: {self.samples} samples, views: {', '.join(self.views) or 'none'}, "
                f"{shape}, splits: {sp} -> {status}")


def _stamp(p: Path) -> list:
    st = p.stat()
    return [st.st_size, st.st_mtime_ns]


def _check_ids(root, ids: Sequence[str], views: Sequence[str], R: int | None, D: int | None, passed: dict,
               decode: bool, progress: bool = False) -> list[tuple]:
    """The per-sample part of `check_samples`: for each id in order, (problems, entries newly
    passed, {layout path: shape}, (image path, (w, h)) or None)."""
    ds = RackLayRoot(root)
    out = []
    it = ids
    if progress:
        from tqdm import tqdm
        it = tqdm(ids, desc="check-data", unit="img", leave=False)
    for sid in it:
        problems: list[str] = []
        new: dict = {}
        shape_of: dict[str, tuple] = {}
        image_size = None
        img = ds.image_path(sid)
        try:
            key = str(img)
            hit = passed.get(key)
            if decode:
                h, w = read_image(img).shape[:2]
                hit = new[key] = _stamp(img) + [[w, h]]
            elif not (img.is_file() and hit is not None and hit[:2] == _stamp(img)):
                info = image_info(img)
                if info.format == "PNG":
                    with open(img, "rb") as f:
                        f.seek(max(0, img.stat().st_size - 12))
                        if b"IEND" not in f.read():
                            raise DataError(f"{img}: truncated PNG (no IEND chunk)")
                hit = new[key] = _stamp(img) + [[info.width, info.height]]
            image_size = (key, tuple(hit[2]))
        except DataError as e:
            problems.append(str(e))
        for view in views:
            p = ds.layout_path(view, sid)
            if not p.is_file():
                problems.append(f"{p}: missing {view} layout for image {img.name}")
                continue
            key = str(p)
            hit = passed.get(key)
            if hit is not None and hit[:2] == _stamp(p):
                shape = tuple(hit[2])
            else:
                try:
                    arr = load_npy(p)
                    L.check_stack(arr, R=R, D=D, source=str(p))
                except (L.LayoutError, DataError) as e:
                    problems.append(str(e))
                    continue
                shape = tuple(arr.shape)
                new[key] = _stamp(p) + [list(shape)]
            shape_of[key] = shape
        out.append((problems, new, shape_of, image_size))
    return out


def check_samples(root: str | os.PathLike, ids: Sequence[str], views: Sequence[str], R: int | None = None,
                  D: int | None = None, passed: dict | None = None, progress: bool = False,
                  sizes: dict | None = None, decode: bool = False, workers: int = 0) -> tuple[list[str], tuple | None]:
    """The per-sample checks of `check_dataset` (which decodes every image: `decode`) and of
    `racklay train` before its first step (which reads the image's header, pixel limit and PNG
    completeness only): for these sample ids, the image and every view's layout (present,
    readable, strict values, R channels, D pixels), and that all layouts share one size. Returns
    (problems, (R, D) most layouts have). `passed` ({path: [size, mtime_ns, shape]}) remembers
    files that passed: they are not read again while unchanged (updated in place), so a restart
    checks in moments. `sizes`, when given, collects the image paths by (width, height):
    {(w, h): [path, ...]}. `workers` > 1 checks in that many processes (the same result, in the
    same order)."""
    passed = {} if passed is None else passed
    if workers > 1 and len(ids) > 4 * workers:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        chunks = [list(ids[i::workers]) for i in range(workers)]   # interleaved: equal shares of slow files
        ctx = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else None)
        with ProcessPoolExecutor(workers, mp_context=ctx) as pool:
            parts = list(pool.map(_check_ids, *zip(*[(root, c, views, R, D, passed, decode) for c in chunks])))
        results = [parts[k % workers][k // workers] for k in range(len(ids))]   # back in the order of ids
    else:
        results = _check_ids(root, ids, views, R, D, passed, decode, progress)
    problems = [m for r in results for m in r[0]]
    shape_of = {}
    for _, new, shapes, image_size in results:
        passed.update(new)
        shape_of.update(shapes)
        if sizes is not None and image_size is not None:
            sizes.setdefault(image_size[1], []).append(image_size[0])
    common = None
    if shape_of:
        common = Counter(shape_of.values()).most_common(1)[0][0]
        for p, shp in shape_of.items():
            if shp != common:
                problems.append(f"{p}: shape {shp} differs from the dataset's {common}")
                passed.pop(p, None)
        common = (common[0], common[1])
    return problems, common


def check_dataset(root: str | os.PathLike, R: int | None = None, D: int | None = None,
                  progress: bool = False, workers: int = 1) -> CheckReport:
    """Validate every sample of a dataset; return a report with one line per problem."""
    ds = RackLayRoot(root)
    rep = CheckReport(root=ds.root)
    try:
        ds.require()
    except (DataError, FileNotFoundError) as e:
        rep.problems.append(str(e))
        return rep
    if not (ds.root / IMAGES_DIR).is_dir():
        rep.problems.append(f"{ds.root / IMAGES_DIR}: images folder missing")
        return rep
    ids = ds.ids()
    rep.samples = len(ids)
    rep.views = ds.views()
    if not rep.views:
        rep.problems.append(f"{ds.root}: neither {TOP_DIR}/ nor {FRONT_DIR}/ exists")
    stems = Counter(ids)
    for sid, n in stems.items():
        if n > 1:
            rep.problems.append(f"{ds.root / IMAGES_DIR}: {n} image files share the id {sid}")
    problems, common = check_samples(ds.root, ids, rep.views, R=R, D=D, progress=progress, decode=True,
                                     workers=workers)
    rep.problems += problems
    if common is not None:
        rep.R, rep.D = common
    for sid in ids:
        mp = ds.meta_path(sid)
        if mp.exists():
            try:
                json.loads(mp.read_text())
            except json.JSONDecodeError as e:
                rep.problems.append(f"{mp}: invalid JSON ({e.msg} at line {e.lineno})")
    # layouts without an image
    idset = set(ids)
    for view in rep.views:
        d = ds.root / VIEW_DIRS[view]
        for p in sorted(d.glob("*.npy")):
            sid = p.stem[len(VIEW_PREFIX[view]):]
            if not p.stem.startswith(VIEW_PREFIX[view]):
                rep.problems.append(f"{p}: unexpected file name (expected {VIEW_PREFIX[view]}NNNNNN.npy)")
            elif sid not in idset:
                rep.problems.append(f"{p}: {view} layout has no image {IMAGES_DIR}/{sid}.png")
    # splits
    seen: dict[str, str] = {}
    for name in ds.splits():
        sp = ds.split_path(name)
        entries = [parse_split_entry(l) for l in sp.read_text().splitlines() if l.strip()]
        rep.splits[name] = len(entries)
        for sid, n in Counter(entries).items():
            if n > 1:
                rep.problems.append(f"{sp}: entry {sid} listed {n} times")
        for sid in dict.fromkeys(entries):
            if sid not in idset:
                rep.problems.append(f"{sp}: entry {sid} points at a missing image")
            if sid in seen:
                rep.problems.append(f"{sp}: entry {sid} is also in split '{seen[sid]}' (splits must not overlap)")
            else:
                seen[sid] = name
    return rep
