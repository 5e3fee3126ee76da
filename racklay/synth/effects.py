"""Camera effects applied after rendering (the proxy-real domain; off in the synthetic
recipes): mild radial lens distortion, blur, vignetting, exposure and white-balance shifts,
sensor noise and a JPEG round trip. Only the image (and the per-pixel maps that must stay
aligned with it) change; the layouts are metric and never distorted."""
from __future__ import annotations

from functools import cache

import numpy as np

#: barrel distortion never stretches the image corner's pinhole radius more than this (see k1_limit)
MAX_CORNER_STRETCH = 1.25


def k1_limit(K: np.ndarray, width: int, height: int) -> float:
    """The most negative k1 a camera gets: barrel distortion stretches the pinhole radius of the
    image's farthest corner at most MAX_CORNER_STRETCH times. Stronger k1 with a wide lens folds
    the image (x_d = x_u (1 + k1 r_u^2) has no inverse past r_u = 1 / sqrt(-3 k1): the corners
    become garbage) and needs a render many times the image's size."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xd, yd = max(cx, width - cx) / fx, max(cy, height - cy) / fy
    s = MAX_CORNER_STRETCH
    return float((1 / s - 1) / (s * s * (xd * xd + yd * yd)))


def undistort_normalised(xd, yd, k1: float):
    """Pinhole (undistorted) normalised coordinates of distorted ones (arrays or floats), by
    fixed-point iteration: 8 steps, then on until it has converged (k1 within k1_limit)."""
    xu, yu = xd, yd
    for it in range(200):
        f = 1 + k1 * (xu * xu + yu * yu)
        nx, ny = xd / f, yd / f
        done = it >= 7 and np.max(np.abs(nx - xu)) < 1e-9 and np.max(np.abs(ny - yu)) < 1e-9
        xu, yu = nx, ny
        if done:
            break
    return xu, yu


def distortion_maps(K: np.ndarray, k1: float, width: int, height: int,
                    offset: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps that turn an undistorted (pinhole) render into the image of a camera with
    radial distortion x_d = x_u (1 + k1 r_u^2) (normalised coordinates, OpenCV's model with
    only k1). For every distorted output pixel the undistorted source is found by fixed-point
    iteration (undistort_normalised). `offset` = (px, py): the render has px / py extra pixels on each side."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    c0, r0 = (width // 2, height // 2) if (2 * cx, 2 * cy) == (width, height) else (0, 0)
    # centred principal point: the map is odd in x and in y, so one quadrant is solved and
    # mirrored (bit for bit what solving every pixel gives, at a quarter of the cost)
    u, v = np.meshgrid(np.arange(c0, width, dtype=np.float64) + 0.5, np.arange(r0, height, dtype=np.float64) + 0.5)
    xd, yd = (u - cx) / fx, (v - cy) / fy
    xu, yu = undistort_normalised(xd, yd, k1)
    if c0 or r0:
        cols, rows = np.arange(width), np.arange(height)
        ci, ri = np.where(cols >= c0, cols, width - 1 - cols) - c0, np.where(rows >= r0, rows, height - 1 - rows) - r0
        xu = xu[np.ix_(ri, ci)] * np.where(cols >= c0, 1.0, -1.0)
        yu = yu[np.ix_(ri, ci)] * np.where(rows >= r0, 1.0, -1.0)[:, None]
    # remap uses pixel-index coordinates (pixel i's centre is at i)
    return ((xu * fx + cx + offset[0] - 0.5).astype(np.float32),
            (yu * fy + cy + offset[1] - 0.5).astype(np.float32))


def distort_points(K: np.ndarray, k1: float, uv: np.ndarray) -> np.ndarray:
    """Pinhole pixel coordinates (..., 2) -> distorted pixel coordinates (same model)."""
    if not k1:
        return uv
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x, y = (uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy
    f = 1 + k1 * (x * x + y * y)
    return np.stack([x * f * fx + cx, y * f * fy + cy], axis=-1)


def apply_distortion(maps, rgb, nearest: list[np.ndarray]):
    import cv2

    mx, my = maps
    out_rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out = []
    for a in nearest:
        if a.dtype == np.uint32:  # remap has no uint32 path: split into two uint16 halves
            lo = cv2.remap((a & 0xFFFF).astype(np.uint16), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
            hi = cv2.remap((a >> 16).astype(np.uint16), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
            out.append(lo.astype(np.uint32) | (hi.astype(np.uint32) << 16))
        else:
            out.append(cv2.remap(a, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE))
    return out_rgb, out


def edge_antialias(rgb: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """Cheap anti-aliasing from the exact instance map: pixels on an object boundary get a 3x3
    average. Used when MSAA is off (antialias: 1)."""
    import cv2

    e = np.zeros(instance.shape, bool)
    np.not_equal(instance[:, 1:], instance[:, :-1], out=e[:, 1:])
    e[1:, :] |= instance[1:, :] != instance[:-1, :]
    e[:, :-1] |= e[:, 1:]   # (numpy buffers overlapping operands)
    e[:-1, :] |= e[1:, :]
    mean = rgb.astype(np.uint16)
    mean += cv2.blur(rgb, (3, 3))
    mean >>= 1
    out = rgb.copy()
    np.copyto(out, mean, where=e[..., None], casting="unsafe")
    return out


@cache
def _vignette_falloff(H: int, W: int) -> np.ndarray:
    """(H, W) float32 radial falloff in [0, 1] (0 at the centre, 1 at the corners) that
    `vignetting` scales; one per image size (read-only)."""
    yy, xx = np.meshgrid(np.linspace(-1, 1, H, dtype=np.float32), np.linspace(-1, 1, W, dtype=np.float32), indexing="ij")
    r = np.clip((xx * xx + yy * yy) / 2, 0, 1) ** 1.5
    r.flags.writeable = False
    return r


#: standard-normal values drawn once per process (fixed seed), from which each image's sensor
#: noise is read at an offset its seed draws: drawing 400 k Gaussian values per image cost ~7 ms,
#: a fifth of a render's ground-truth stage on a Zen 3 core
NOISE_BANK_SIZE = 1 << 22


@cache
def _noise_bank() -> np.ndarray:
    bank = np.random.default_rng(0x5E45).standard_normal(NOISE_BANK_SIZE, dtype=np.float32)
    bank.flags.writeable = False
    return bank


def gaussian_noise(shape: tuple[int, ...], seed: int) -> np.ndarray:
    """(shape) float32 standard-normal noise, a function of `seed` alone: a window of the bank
    at an offset the seed draws (each image's values are independent draws; two images' windows
    may overlap at different offsets), or drawn afresh when the shape exceeds the bank."""
    rng = np.random.default_rng(seed)
    size = int(np.prod(shape))
    bank = _noise_bank()
    if size > bank.size:
        return rng.standard_normal(shape, dtype=np.float32)
    start = int(rng.integers(0, bank.size - size + 1))
    return bank[start:start + size].reshape(shape).copy()


def photometric(rgb: np.ndarray, fx: dict) -> np.ndarray:
    """Blur, vignetting, exposure, white balance, noise, JPEG (each skipped when neutral)."""
    import cv2

    img = rgb
    if fx.get("blur_sigma", 0) > 0.05:
        img = cv2.GaussianBlur(img, (0, 0), fx["blur_sigma"])
    gain = np.array(fx.get("white_balance", [1, 1, 1]), np.float32) * float(fx.get("exposure", 1.0))
    vig = float(fx.get("vignetting", 0))
    noise = float(fx.get("noise_std", 0))
    if vig > 0 or noise > 0 or np.any(np.abs(gain - 1) > 1e-6):
        H, W = img.shape[:2]
        f = img.astype(np.float32)
        rows = f.reshape(H, W * 3)
        rows *= np.tile(gain, W)   # the gain per channel, along whole rows (a 3-long inner loop is slow)
        if vig > 0:
            f *= (1 - vig * _vignette_falloff(H, W))[..., None]
        if noise > 0:
            n = gaussian_noise(f.shape, fx.get("noise_seed", 0))
            n *= np.float32(noise) * np.sqrt(np.clip(f, 8, 255) / 128)
            f += n
        f += 0.5
        img = np.clip(f, 0, 255, out=f).astype(np.uint8)
    q = int(fx.get("jpeg_quality", 0))
    if q > 0:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, q])
        img = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return img
