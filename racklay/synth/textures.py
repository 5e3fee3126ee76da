"""Procedural textures for WareSynth: cardboard with tape and printed labels, plastic crates
with grids, concrete, painted block walls, painted steel with slots, chipboard, pallet wood.
Nothing is downloaded. Two families: "warehouse" (the synthetic recipes) and "proxy" (the
proxy-real domain: its own colours and patterns). A folder of the user's own images can be
added as extra carton side textures.

The bank is a list of 256 x 256 RGB layers (one GL texture array) plus, per material, its
layer indices and shading parameters. It depends only on (family, seed, texture_dir).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .recipe import texture_files
from .scene import CATEGORY_NAMES

TEX = 256


@dataclass
class Material:
    side: list            # layer indices (variants) for side faces
    top: list             # layer indices for top/bottom faces
    uv_tile: float = 0.0  # 0: each face maps the whole texture; > 0: world tiling, metres per repeat
    specular: float = 0.05
    shininess: float = 16.0
    emissive: float = 0.0


@dataclass
class TextureBank:
    family: str
    layers: list = field(default_factory=list)      # (TEX, TEX, 3) uint8
    materials: dict = field(default_factory=dict)   # name -> Material

    def add(self, img: np.ndarray) -> int:
        self.layers.append(np.ascontiguousarray(img[:, :, :3].astype(np.uint8)))
        return len(self.layers) - 1

    def array(self) -> np.ndarray:
        return np.stack(self.layers)


def _noise(rng, size=TEX, octaves=(4, 8, 16, 32, 64), falloff=0.55) -> np.ndarray:
    """Fractal value noise in [0, 1], tileable enough for our use."""
    import cv2

    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in octaves:
        g = rng.random((o, o)).astype(np.float32)
        g = np.pad(g, 1, mode="wrap")
        up = cv2.resize(g, (size + 2 * size // o, size + 2 * size // o), interpolation=cv2.INTER_CUBIC)
        off = size // o
        out += amp * up[off:off + size, off:off + size]
        total += amp
        amp *= falloff
    out /= total
    return np.clip((out - out.min()) / max(out.max() - out.min(), 1e-6), 0, 1)


def _rgb(color, shape=(TEX, TEX)):
    return np.ones(shape + (3,), np.float32) * np.array(color, np.float32)


def _to_u8(img):
    return np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)


def _text(rng, n=6):
    alphabet = "ABCDEFGHJKLMNPQRSTUVWXYZ0123456789"
    return "".join(alphabet[i] for i in rng.integers(0, len(alphabet), n))


def _ink(img, ink, draw):
    """Draw with OpenCV on a uint8 mask (`draw(mask)` paints 255) and blend `ink` into `img`."""
    mask = np.zeros(img.shape[:2], np.uint8)
    draw(mask)
    a = (mask.astype(np.float32) / 255)[..., None]
    img[:] = img * (1 - a) + np.array(ink, np.float32) * a


def _label(rng, img, x0, y0, w, h, ink=(0.05, 0.05, 0.05), paper=(0.95, 0.95, 0.92), style="warehouse"):
    import cv2

    img[y0:y0 + h, x0:x0 + w] = paper
    # barcode
    bx, by, bw, bh = x0 + 4, y0 + h // 2, w - 8, h // 2 - 4
    x = bx
    while x < bx + bw - 2:
        t = int(rng.integers(1, 4))
        if rng.random() < 0.55:
            img[by:by + bh, x:min(x + t, bx + bw)] = ink
        x += t
    font = cv2.FONT_HERSHEY_SIMPLEX if style == "warehouse" else cv2.FONT_HERSHEY_DUPLEX
    for k in range(2):
        txt = _text(rng, int(rng.integers(4, 9)))
        _ink(img, ink, lambda m: cv2.putText(m, txt, (x0 + 4, y0 + 12 + 11 * k), font, 0.33, 255, 1, cv2.LINE_AA))


def carton(rng, base, tape, family, variant) -> tuple[np.ndarray, np.ndarray]:
    """(side, top) textures of a cardboard carton."""
    import cv2

    n = _noise(rng)
    fibre = _noise(rng, octaves=(64, 128), falloff=0.7)
    shade = 0.88 + 0.16 * n[..., None] + 0.05 * (fibre[..., None] - 0.5)
    side = _rgb(base) * shade
    top = _rgb(base) * (0.9 + 0.12 * _noise(rng)[..., None])
    # corrugation stripes (faint, vertical on the side)
    stripes = 0.97 + 0.03 * np.sin(np.arange(TEX) / 2.0)[None, :, None]
    side *= stripes
    # tape: over the top's centre seam and down the side's top edge
    tw = int(rng.integers(28, 44))
    c = TEX // 2
    tape_c = np.array(tape, np.float32)
    top[:, c - tw // 2:c + tw // 2] = tape_c * (0.95 + 0.08 * _noise(rng)[:, c - tw // 2:c + tw // 2, None])
    top[c - 1:c + 1, :] *= 0.6  # flap seam
    side[:int(TEX * 0.18), c - tw // 2:c + tw // 2] = tape_c * 0.97
    # printed marks
    ink = (0.12, 0.1, 0.08) if family == "warehouse" else (0.05, 0.15, 0.45)
    if variant % 2 == 0:
        _label(rng, side, int(rng.integers(20, 120)), int(rng.integers(90, 150)), 110, 70,
               style=family)
    else:
        # "this side up" arrows and a logo-ish box
        txt = _text(rng, 3)

        def marks(m):
            for k in range(2):
                cv2.arrowedLine(m, (40 + 60 * k, 200), (40 + 60 * k, 140), 255, 5, tipLength=0.4)
            cv2.rectangle(m, (150, 120), (230, 200), 255, 3)
            cv2.putText(m, txt, (160, 172), cv2.FONT_HERSHEY_SIMPLEX, 0.8, 255, 2, cv2.LINE_AA)
        _ink(side, ink, marks)
    edge = np.ones((TEX, TEX, 1), np.float32)
    edge[:3], edge[-3:], edge[:, :3], edge[:, -3:] = 0.75, 0.75, 0.75, 0.75
    return _to_u8(side * edge), _to_u8(top * edge)


def crate(rng, color, family) -> tuple[np.ndarray, np.ndarray]:
    """(side, top) textures of a plastic crate: grid of vents on the sides, dark open top."""
    base = _rgb(color) * (0.92 + 0.1 * _noise(rng, octaves=(8, 16))[..., None])
    side = base.copy()
    cols, rows = (6, 3) if family == "warehouse" else (8, 4)
    m = 22
    cw, rh = (TEX - 2 * m) // cols, (TEX - 3 * m) // rows
    for i in range(cols):
        for j in range(rows):
            x0, y0 = m + i * cw + 4, 2 * m + j * rh + 4
            side[y0:y0 + rh - 8, x0:x0 + cw - 8] *= 0.35
    side[:m] *= 1.1  # rim
    top = _rgb(color) * 0.35
    top[:14], top[-14:], top[:, :14], top[:, -14:] = (np.array(color, np.float32) * 1.05,) * 4
    for k in range(1, 4):
        top[:, k * TEX // 4 - 2:k * TEX // 4 + 2] = np.array(color, np.float32) * 0.6
    return _to_u8(side), _to_u8(top)


def concrete(rng, family):
    import cv2

    n = _noise(rng)
    fine = _noise(rng, octaves=(64, 128), falloff=0.8)
    if family == "warehouse":
        img = _rgb((0.55, 0.55, 0.53)) * (0.8 + 0.3 * n[..., None] + 0.08 * (fine[..., None] - 0.5))
        pts = []
        for _ in range(3):  # cracks
            p = rng.integers(0, TEX, 2)
            for _ in range(12):
                q = p + rng.integers(-20, 21, 2)
                pts.append((tuple(int(v) for v in p), tuple(int(v) for v in q)))
                p = q
        _ink(img, (0.35, 0.35, 0.34), lambda m: [cv2.line(m, a, b, 255, 1) for a, b in pts])
    else:  # epoxy floor with a yellow safety line
        img = _rgb((0.42, 0.5, 0.45)) * (0.9 + 0.15 * n[..., None])
        img[:, 110:130] = (0.9, 0.75, 0.1)
    return _to_u8(img)


def block_wall(rng, family):
    img = _rgb((0.9, 0.9, 0.88)) * (0.9 + 0.12 * _noise(rng)[..., None])
    if family == "warehouse":  # painted cinder blocks: mortar lines
        for y in range(0, TEX, 32):
            img[y:y + 2] *= 0.7
            off = 0 if (y // 32) % 2 == 0 else 32
            for x in range(off, TEX, 64):
                img[y:y + 32, x:x + 2] *= 0.7
    else:  # corrugated metal sheet
        img *= (0.8 + 0.2 * np.abs(np.sin(np.arange(TEX) * np.pi / 16)))[None, :, None]
    return _to_u8(img)


def steel(rng, family, slots=True):
    img = _rgb((0.92, 0.92, 0.92)) * (0.93 + 0.07 * _noise(rng, octaves=(16, 32, 64))[..., None])
    if slots:  # teardrop-like slots of pallet-rack uprights
        for y in range(8, TEX, 32):
            img[y:y + 16, TEX // 2 - 5:TEX // 2 + 5] *= 0.15
    return _to_u8(img)


def slotted_angle(rng):
    """Slotted-angle steel: columns of long slots and round holes, one column per flange face at
    the material's tiling (a 4 cm flange shows half the layer's width)."""
    import cv2

    img = _rgb((0.92, 0.92, 0.92)) * (0.93 + 0.07 * _noise(rng, octaves=(16, 32, 64))[..., None])
    for cx in (TEX // 4, 3 * TEX // 4):
        for y in range(0, TEX, 128):
            img[y + 14:y + 74, cx - 10:cx + 10] *= 0.12                       # a slot
            _ink(img, (0.1, 0.1, 0.1), lambda m: cv2.circle(m, (cx, y + 100), 10, 255, -1, cv2.LINE_AA))   # a hole
    return _to_u8(img)


def chipboard(rng, family):
    if family == "warehouse":
        n = _noise(rng, octaves=(32, 64, 128), falloff=0.9)
        img = _rgb((0.72, 0.6, 0.42)) * (0.75 + 0.4 * n[..., None])
    else:  # galvanised wire decking
        img = _rgb((0.7, 0.72, 0.74)) * (0.9 + 0.1 * _noise(rng)[..., None])
        img[::16] *= 0.4
        img[:, ::16] *= 0.4
    return _to_u8(img)


def wood_planks(rng):
    img = _rgb((0.68, 0.52, 0.33)) * (0.8 + 0.3 * _noise(rng, octaves=(4, 64), falloff=0.6)[..., None])
    for x in range(0, TEX, 52):
        img[:, x:x + 10] *= 0.35
    return _to_u8(img)


def wire_deck(rng):
    """Galvanised wire-mesh decking on pallet-rack beams."""
    img = _rgb((0.16, 0.16, 0.17)) * (0.8 + 0.2 * _noise(rng)[..., None])
    for k in range(0, TEX, 12):
        img[k:k + 2] = (0.72, 0.73, 0.75)
    for k in range(0, TEX, 48):
        img[:, k:k + 3] = (0.62, 0.63, 0.66)
    return _to_u8(img)


#: paper and band colours of rack location labels: white, yellow, white with a blue band
_BEAM_LABELS = (((0.95, 0.95, 0.92), None), ((0.97, 0.84, 0.16), None), ((0.95, 0.95, 0.92), (0.15, 0.3, 0.7)))


def beam_label(rng, paper, band=None):
    """A rack location label as stuck on a beam's front: a big location code over a barcode,
    drawn at the label's own aspect (about 2.5 : 1) and squeezed into the square layer that the
    label's front face stretches back."""
    import cv2

    w, h = 640, 256
    img = _rgb(paper, (h, w)) * (0.95 + 0.05 * cv2.resize(_noise(rng), (w, h))[..., None])
    top = 0
    if band is not None:
        img[:48] = band
        top = 48
    code = f"{_text(rng, 1)}{int(rng.integers(1, 40)):02d}-{int(rng.integers(1, 60)):02d}-{int(rng.integers(1, 6))}"
    _ink(img, (0.05, 0.05, 0.05), lambda m: cv2.putText(m, code, (24, top + 100), cv2.FONT_HERSHEY_SIMPLEX, 2.6,
                                                           255, 7, cv2.LINE_AA))
    x = 40
    while x < w - 40:   # barcode
        t = int(rng.integers(3, 10))
        if rng.random() < 0.55:
            img[top + 130:h - 24, x:x + t] = 0.05
        x += t
    return _to_u8(cv2.resize(img, (TEX, TEX), interpolation=cv2.INTER_AREA))


def stretch_wrap(rng):
    """A pallet load under stretch film: cartons seen through milky, streaked plastic."""
    n = _noise(rng, octaves=(4, 8, 64), falloff=0.7)
    img = _rgb((0.72, 0.6, 0.45)) * (0.85 + 0.2 * n[..., None])
    for y in range(0, TEX, 64):        # carton joints behind the film
        img[y:y + 2] *= 0.6
    for x in range(0, TEX, 85):
        img[:, x:x + 2] *= 0.6
    streaks = 0.5 + 0.5 * np.sin(np.arange(TEX) * 2 * np.pi / TEX * 7 + rng.uniform(0, 6))[:, None]
    film = 0.45 + 0.3 * streaks * (0.7 + 0.3 * _noise(rng, octaves=(8, 32)))
    img = img * (1 - film[..., None]) + film[..., None] * 0.95
    return _to_u8(img)


def plain(rng, level=0.92):
    return _to_u8(_rgb((level,) * 3) * (0.96 + 0.04 * _noise(rng, octaves=(16, 32))[..., None]))


# carton base colours and tape colours per category, per family
_CARTON_COLORS = {
    "warehouse": [((0.70, 0.53, 0.34), (0.78, 0.62, 0.40)), ((0.76, 0.6, 0.4), (0.85, 0.8, 0.7)),
                  ((0.62, 0.46, 0.29), (0.75, 0.6, 0.38)), ((0.84, 0.82, 0.76), (0.7, 0.55, 0.35)),
                  ((0.72, 0.56, 0.38), (0.2, 0.35, 0.7)), ((0.66, 0.5, 0.33), (0.85, 0.85, 0.82))],
    "proxy": [((0.8, 0.68, 0.45), (0.9, 0.9, 0.9)), ((0.55, 0.4, 0.28), (0.85, 0.25, 0.2)),
              ((0.9, 0.9, 0.88), (0.95, 0.75, 0.2)), ((0.6, 0.55, 0.5), (0.3, 0.3, 0.3)),
              ((0.85, 0.72, 0.5), (0.2, 0.6, 0.3)), ((0.45, 0.35, 0.25), (0.8, 0.7, 0.5))],
}
_CRATE_COLORS = {"warehouse": [(0.12, 0.32, 0.75), (0.78, 0.12, 0.1)],
                 "proxy": [(0.15, 0.55, 0.25), (0.95, 0.75, 0.1)]}

_BANK_CACHE: dict = {}


def load_user_textures(folder: str) -> list[np.ndarray]:
    """Images in `folder` (sorted by name), resized to 256 x 256 RGB. Unreadable files are an
    error naming the file."""
    import cv2

    from ..data import read_image

    return [cv2.resize(read_image(p), (TEX, TEX), interpolation=cv2.INTER_AREA) for p in texture_files(folder)]


def build_bank(family: str = "warehouse", seed: int = 0, texture_dir: str = "") -> TextureBank:
    """All textures of a family; cached per process."""
    key = (family, seed, texture_dir)
    if key in _BANK_CACHE:
        return _BANK_CACHE[key]
    rng = np.random.default_rng(np.random.SeedSequence([seed & 0xFFFFFFFF, 0x7E47, 1 if family == "proxy" else 0]))
    bank = TextureBank(family)
    user = load_user_textures(texture_dir) if texture_dir else []
    user_layers = [bank.add(u) for u in user]
    for ci, (base, tape) in enumerate(_CARTON_COLORS[family]):
        sides, tops = [], []
        for v in range(2):
            s, t = carton(rng, base, tape, family, v + ci)
            sides.append(bank.add(s))
            tops.append(bank.add(t))
        bank.materials[CATEGORY_NAMES[ci]] = Material(sides + user_layers, tops, specular=0.03, shininess=8)
    for k, col in enumerate(_CRATE_COLORS[family]):
        s, t = crate(rng, col, family)
        bank.materials[CATEGORY_NAMES[6 + k]] = Material([bank.add(s)], [bank.add(t)], specular=0.35, shininess=32)
    c = bank.add(concrete(rng, family))
    bank.materials["concrete"] = Material([c], [c], uv_tile=2.5, specular=0.08, shininess=12)
    w = bank.add(block_wall(rng, family))
    bank.materials["wall"] = Material([w], [w], uv_tile=2.0)
    bank.materials["ceiling"] = Material([w], [w], uv_tile=3.0)
    st = bank.add(steel(rng, family))
    bank.materials["steel"] = Material([st], [st], uv_tile=0.5, specular=0.3, shininess=24)
    pa = bank.add(plain(rng))
    bank.materials["beam"] = Material([pa], [pa], specular=0.35, shininess=24)
    bank.materials["paint"] = Material([pa], [pa], specular=0.25, shininess=20)
    bank.materials["lamp"] = Material([pa], [pa], emissive=1.0)
    b = bank.add(chipboard(rng, family))
    bank.materials["board"] = Material([b], [b], uv_tile=1.0, specular=0.05 if family == "warehouse" else 0.3)
    pw = bank.add(wood_planks(rng))
    bank.materials["pallet"] = Material([pw], [pw], uv_tile=1.2)
    # pallet racking (added last: the layers above keep their indices and pixels)
    dk = bank.add(wire_deck(rng))
    bank.materials["deck"] = Material([dk], [dk], uv_tile=0.5, specular=0.3, shininess=24)
    wr = bank.add(stretch_wrap(rng))
    bank.materials["wrap"] = Material([wr], [wr], uv_tile=1.0, specular=0.45, shininess=40)
    # wire shelving: chrome or epoxy-coated wire (its colour is the object's tint)
    ch = bank.add(steel(rng, family, slots=False))
    bank.materials["chrome"] = Material([ch], [ch], uv_tile=0.5, specular=0.7, shininess=64)
    # rack location labels (recipe key beam_labels)
    bl = [bank.add(beam_label(rng, paper, band)) for paper, band in _BEAM_LABELS]
    bank.materials["beam_label"] = Material(bl, bl, specular=0.15, shininess=16)
    # slotted-angle shelving posts
    sa = bank.add(slotted_angle(rng))
    bank.materials["slotted"] = Material([sa], [sa], uv_tile=0.08, specular=0.3, shininess=24)
    _BANK_CACHE[key] = bank
    return bank
