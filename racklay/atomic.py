"""Write files so that a reader never sees half of one: write a temporary file beside the
target, flush it, then rename it over the target (atomic on POSIX file systems)."""
from __future__ import annotations

import io
import json
import os
import struct
import tempfile
import zlib
from functools import cache
from pathlib import Path

import numpy as np


def _file_mode() -> int:
    """The mode a plain open() would give a new file (0666 minus the umask): mkstemp makes its
    temporary files 0600, which would leave datasets and annotations unreadable to teammates."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _file_mode()


class WriteError(OSError):
    """An output file could not be written (disk full, read-only, no permission): an OSError that
    names the file, so the message says which output failed. Commands stop on it: the next file
    would fail the same way."""


def atomic_write_bytes(path: str | os.PathLike, data: bytes, fsync: bool = True, mode: int | None = None) -> Path:
    """Write `data` to a temporary file beside `path`, then rename it over `path`. With
    fsync=False the data is not forced to disk before the rename: readers and interrupted
    processes still never see half a file, but a power loss may (bulk generators use it).
    `mode`: the file's permissions (default: what a plain open() gives, 0666 minus the umask)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise WriteError(e.errno, e.strerror or str(e), str(path)) from None
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), _FILE_MODE if mode is None else mode)
            f.write(data)
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(e, OSError) and not isinstance(e, WriteError):
            raise WriteError(e.errno, e.strerror or str(e), str(path)) from None
        raise
    return path


def remove_stale_temps(folder: str | os.PathLike, name: str) -> list[Path]:
    """Remove the temporary files atomic_write_bytes left beside `folder/name` when its process
    was killed mid-write (`.NAME.XXXXXXXX.tmp`). Call it only when no other process can be
    writing that file (e.g. a run folder at the start of its run). Returns what was removed."""
    gone = []
    for p in Path(folder).glob(f".{name}.*.tmp"):
        try:
            p.unlink()
            gone.append(p)
        except FileNotFoundError:
            pass
    return gone


def atomic_write_text(path: str | os.PathLike, text: str, fsync: bool = True, mode: int | None = None) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"), fsync=fsync, mode=mode)


def atomic_write_json(path: str | os.PathLike, obj, indent: int | None = 2, fsync: bool = True) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=indent, sort_keys=False) + "\n", fsync=fsync)


def npy_bytes(arr: np.ndarray) -> bytes:
    """The bytes np.save writes for `arr` (no pickles), built in one piece: saving through a
    growing BytesIO costs several times the write of a 1 MB layout stack."""
    arr = np.asarray(arr)
    if not arr.flags.c_contiguous:
        arr = np.ascontiguousarray(arr)
    head = io.BytesIO()
    try:
        np.lib.format.write_array_header_1_0(head, np.lib.format.header_data_from_array_1_0(arr))
    except ValueError:   # a header too long for format 1.0: np.save's own choice of version
        np.save(head := io.BytesIO(), arr, allow_pickle=False)
        return head.getvalue()
    if arr.dtype.hasobject:
        raise ValueError("object arrays are not saved (no pickles)")
    return head.getvalue() + arr.tobytes()


def atomic_save_npy(path: str | os.PathLike, arr: np.ndarray, fsync: bool = True) -> Path:
    return atomic_write_bytes(path, npy_bytes(arr), fsync=fsync)


def encode_png(image: np.ndarray, row_filter: str | None = None) -> bytes:
    """PNG bytes of an RGB (H, W, 3) uint8 or a (H, W) uint8/uint16 array. Deterministic.
    `row_filter` None: OpenCV's encoder (zlib level 1, adaptive row filters); "sub" (photo-like
    images) or "up" (piecewise-constant maps: normals, ids, depth): that one filter on every row
    and a fast deflate (`_png_fixed_filter`), as WareSynth writes its files."""
    arr = np.asarray(image)
    rgb8 = arr.dtype == np.uint8 and arr.ndim == 3 and arr.shape[2] == 3
    grey = arr.dtype in (np.uint8, np.uint16) and arr.ndim == 2
    if not (rgb8 or grey) or 0 in arr.shape:
        raise ValueError(f"encode_png: need an (H, W, 3) uint8 or (H, W) uint8/uint16 array, got {arr.dtype} {arr.shape}")
    if row_filter is not None:
        return _png_fixed_filter(arr, row_filter)
    import cv2

    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", arr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError("could not encode PNG")
    return buf.tobytes()


#: PNG row filter types (the PNG specification, section 9.2)
_PNG_FILTERS = {"sub": 1, "up": 2}


@cache
def _deflate_module():
    """ISA-L's zlib-compatible deflate (the `isal` package, 3-5x zlib's speed) where it is
    installed, else the standard library's (a platform without isal wheels: same pixels, slower)."""
    try:
        from isal import isal_zlib
        return isal_zlib
    except ImportError:
        return zlib


def _deflate(data: bytes) -> bytes:
    """zlib stream of `data` at level 1 (`_deflate_module`)."""
    return _deflate_module().compress(data, 1)


def _png_fixed_filter(arr: np.ndarray, row_filter: str) -> bytes:
    """A PNG with one row filter ("sub": each byte minus the one a pixel to its left, "up": minus
    the one above) on every row, filtered with numpy, deflated by `_deflate`."""
    if row_filter not in _PNG_FILTERS:
        raise ValueError(f"row_filter {row_filter!r}: expected one of {sorted(_PNG_FILTERS)} or None")
    H, W = arr.shape[:2]
    depth = 16 if arr.dtype == np.uint16 else 8
    rows = np.ascontiguousarray(arr.astype(">u2") if depth == 16 else arr).view(np.uint8).reshape(H, -1)
    bpp = rows.shape[1] // W   # bytes per pixel
    out = np.empty((H, rows.shape[1] + 1), np.uint8)
    out[:, 0] = _PNG_FILTERS[row_filter]
    body = out[:, 1:]
    if row_filter == "sub":
        body[:, :bpp] = rows[:, :bpp]
        np.subtract(rows[:, bpp:], rows[:, :-bpp], out=body[:, bpp:])   # modulo 256, as PNG's filters
    else:
        body[0] = rows[0]
        np.subtract(rows[1:], rows[:-1], out=body[1:])

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", W, H, depth, 2 if arr.ndim == 3 else 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", _deflate(out.tobytes())) + chunk(b"IEND", b"")


def atomic_save_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    return atomic_write_bytes(path, encode_png(image))
