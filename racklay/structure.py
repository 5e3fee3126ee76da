"""The structured form of a layout: per shelf a few metric numbers (scale) and, per position along
the shelf, where its boxes are (shape). Torch, differentiable; the `struct` decoder
(racklay.model.StructDecoder) predicts it and training supervises it (`structure_loss`).

Per shelf channel and view (the layout convention of racklay.layout; grid of S pixels over
`extent` metres):

- `presence`: the channel holds a shelf.
- `length` L: the board's length along x (metres); the shelf spans x in [-L/2, L/2).
- `extent` E: front view: the drawn free space above the board, z in [0, E) (clear height plus
  WareSynth's 5 cm pad); top view: the board's depth, y in [-E/2, E/2).
- per relative position t in [0, 1) along the shelf (x = (t - 0.5) L), sampled at T bin centres:
  `box`: a box occupies that position; front view: `height`, the box top above the board as a
  fraction of E (boxes stand on the board); top view: `near`, `far`, the box's depth interval as
  fractions of E measured from the board's front edge. With a back interval (`ModelConfig.struct_back`)
  `near`, `far` are the front box's (the run of box pixels nearest the camera) and `back` (logit: a
  box stands behind it), `back_near`, `back_far` the interval of what stands behind; without one
  they span every box in the column.
- the struct decoder's structures also carry the shelf's placement in the image, where it reads
  the shelf: `centre` (image widths from the image's centre) and `half` (half-width, image
  widths), one per shelf per view. The truth's is the rack's span across the image at each level
  (`racklay.data.level_spans`: photos exported by annotate and WareSynth renders have it),
  supervised by `structure_loss`'s `placement_weight`.

Shape (the per-position fractions) does not depend on the shelf's metric size; scale is L and E.
A known dimension (a shelf length) therefore fixes the scale without touching the shape.
Measured on WareSynth renders, rasterising this form back reproduces front layouts exactly and top
layouts up to yawed corners and a box behind another in the same column (docs/results/2026-11-22-to-26-accuracy-log.md).

`rasterize` turns the form into (N, R, 3, S, S) log-probabilities with edges softened over `tau`
pixels (`tau` -> 0: exact rectangles on the convention's pixel-centre rule), so the dense losses
and every dense consumer (eval, predict, ONNX, calibrate, analyze) work on it unchanged.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .layout import BOX, NUM_CLASSES, Grid

#: positions along a shelf at which the per-position fields are sampled (bin centres (k + 0.5) / T)
DEFAULT_T = 96
#: edge softness of `rasterize` while training, in layout pixels: gradients reach the edges' positions
DEFAULT_TAU_PX = 0.5
#: edge softness for prediction: effectively hard edges, so the argmax is exact rectangles (soft edges
#: multiply at corners and can tip a corner pixel to background); class probabilities stay soft
#: through presence and box confidence
HARD_TAU_PX = 0.1
_EPS = 1e-6


def pixel_centres(S: int, extent: float, device=None) -> torch.Tensor:
    """Metric coordinate of column centres (x) and, equally, of row centres read upward (y or z of
    row S - 1 - r): racklay.layout.Grid.centers as a float32 tensor."""
    return torch.as_tensor(Grid(S, extent).centers(), dtype=torch.float32, device=device)


def sample_positions(seq: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of per-position sequences at relative positions t.
    seq (N, R, C, T) at bin centres (k + 0.5) / T; t (N, R, P) -> (N, R, C, P). Clamped at the ends."""
    N, R, C, T = seq.shape
    idx = (t * T - 0.5).clamp(0, T - 1)
    i0 = idx.floor().long().clamp(max=T - 1)
    i1 = (i0 + 1).clamp(max=T - 1)
    w = (idx - i0.to(idx.dtype)).unsqueeze(2)
    g0 = seq.gather(3, i0.unsqueeze(2).expand(N, R, C, -1))
    g1 = seq.gather(3, i1.unsqueeze(2).expand(N, R, C, -1))
    return g0 * (1 - w) + g1 * w


#: `rasterize` draws only the window where a shelf can be: beyond this many `tau` from every shelf's
#: extent a sigmoid is below 2e-9, so each class probability there is its far-field value to fp32
#: precision (background 1, shelf and box the floor `_EPS`); the rest of the grid is filled with that
_WINDOW_TAUS = 20.0


def rasterize(view: str, st: dict, S: int, extent: float, tau_px: float = DEFAULT_TAU_PX,
              window: bool = True) -> torch.Tensor:
    """A structure dict (`presence` logits (N, R); `length`, `extent` metres (N, R); `box` logits and
    `height` or `near`/`far` fractions (N, R, T)) -> (N, R, 3, S, S) log-probabilities of
    (background, shelf, box) on the layout grid of `view`.

    Only the window of rows and columns that the batch's longest and deepest shelf can reach is
    computed (a shelf is a few percent of the grid); the rest is the far-field value: the same
    numbers as drawing the whole grid (`window=False`; to ~1e-6 in log-probability, the same
    argmax). While exporting or tracing the whole grid is drawn (no data-dependent shapes)."""
    dev = st["length"].device
    c = pixel_centres(S, extent, dev)                      # column centres (x), left to right
    v = c.flip(0)                                          # row centres (y or z), top row first
    tau = tau_px * extent / S
    L, E = st["length"].float().unsqueeze(-1), st["extent"].float().unsqueeze(-1)      # (N, R, 1)
    (c0, c1), (r0, r1) = (0, S), (0, S)
    if window and not (torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()) and L.numel():
        m = _WINDOW_TAUS * tau
        half_l, e_max = float(L.detach().amax()) / 2 + m, float(E.detach().amax())
        c0, c1 = _span(c.abs() < half_l)
        r0, r1 = _span((v > -m) & (v < e_max + m) if view == "front" else v.abs() < e_max / 2 + m)
    c, v = c[c0:c1], v[r0:r1]
    pres = _sig(st["presence"].float()[..., None, None])                                # (N, R, 1, 1)
    inside = _sig(((L / 2 - c.abs()) / tau).unsqueeze(2))                               # (N, R, 1, w) columns
    t = c / L + 0.5
    if view == "front":
        fields = torch.stack([st["box"], st["height"]], 2).float()
        q, h = sample_positions(fields, t).unbind(2)
        above = _sig((v / tau)[:, None])                                                # (h, 1) above the board
        band = _sig(((E - v) / tau).unsqueeze(-1))                                      # (N, R, h, 1) rows
        box_rows = _sig(((h * E).unsqueeze(2) - v[:, None]) / tau)                      # (N, R, h, w)
    else:
        back = "back" in st
        keys = ("box", "near", "far") + (("back", "back_near", "back_far") if back else ())
        fields = sample_positions(torch.stack([st[k] for k in keys], 2).float(), t).unbind(2)
        q = fields[0]
        above = (torch.ones((), device=dev), torch.zeros((), device=dev))
        band = _sig(((E / 2 - v.abs()) / tau).unsqueeze(-1))

        def interval(near, far):                                                        # (N, R, h, w) rows
            y0, y1 = ((near - 0.5) * E).unsqueeze(2), ((far - 0.5) * E).unsqueeze(2)
            return _and(_sig((v[:, None] - y0) / tau), _sig((y1 - v[:, None]) / tau))
        box_rows = interval(*fields[1:3])
        if back:                                   # or a box behind it: (its logit) and (its interval)
            box_rows = _or(box_rows, _and(_sig(fields[3].unsqueeze(2)), interval(*fields[4:6])))
    # the board edge (front) multiplies shelf and box alike, so it never tips shelf against box
    col = _and(_and(pres, inside), above)
    qb = _and(_sig(q.unsqueeze(2)), box_rows)
    p_box = col[0] * qb[0]
    p_shelf = col[0] * band[0] * qb[1]
    p_bg = col[1] + col[0] * band[1] * qb[1]
    win = torch.stack([p_bg, p_shelf, p_box], 2).clamp_min(_EPS).log()
    if (c0, c1, r0, r1) == (0, S, 0, S):
        return win
    out = win.new_empty(*win.shape[:3], S, S)
    out[:, :, 0] = 0.0                                     # the far field: background 1, shelf and box _EPS
    out[:, :, 1:] = math.log(_EPS)
    out[..., r0:r1, c0:c1] = win
    return out


def _span(mask: torch.Tensor) -> tuple[int, int]:
    """[first, last + 1) of the True entries of a 1-D mask whose True entries are contiguous (at
    least one index, so that the window is never empty)."""
    idx = torch.nonzero(mask).flatten()
    if idx.numel() == 0:
        return 0, 1
    return int(idx[0]), int(idx[-1]) + 1


def _sig(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(p, 1 - p) of a sigmoid, each computed directly (no 1 - p cancellation: the background
    log-probability deep inside a shelf stays accurate)."""
    return torch.sigmoid(z), torch.sigmoid(-z)


def _and(a: tuple, b: tuple) -> tuple:
    """(p, 1 - p) of the product of two independent events given as (p, 1 - p)."""
    return a[0] * b[0], a[1] + a[0] * b[1]


def _or(a: tuple, b: tuple) -> tuple:
    """(p, 1 - p) of the union of two independent events given as (p, 1 - p)."""
    return a[0] + a[1] * b[0], a[1] * b[1]


def truth_structure(view: str, layouts: torch.Tensor, extent: float, T: int = DEFAULT_T, back: bool = False) -> dict:
    """The structure of ground-truth class-id layouts (N, R, S, S): `presence` (N, R) bool,
    `length`, `extent` metres (N, R), and per position, sampled at the truth's own length (so shape
    is compared with shape whatever the predicted scale): `box` (N, R, T) bool and `height` or
    `near` / `far` fractions (N, R, T). A shelf is the contiguous run its pixels span. Top view
    with `back`: `near` / `far` are the front box's (the column's run of box pixels nearest the
    camera), `back` (N, R, T) bool whether box pixels lie behind that run and `back_near` /
    `back_far` their span (0 where there are none); without it `near` / `far` span every box
    pixel of the column."""
    N, R, S, _ = layouts.shape
    res = extent / S
    fg = layouts > 0
    box = layouts == BOX
    col_fg = fg.any(2)                                     # (N, R, S) over rows
    present = col_fg.any(-1)
    length = col_fg.sum(-1).float() * res
    ext = fg.any(3).sum(-1).float() * res
    t = (torch.arange(T, device=layouts.device, dtype=torch.float32) + 0.5) / T
    x = (t - 0.5) * length.unsqueeze(-1)                   # (N, R, T) metres
    cols = (x / res + S / 2).floor().long().clamp(0, S - 1)
    box_col = box.any(2).gather(2, cols)
    out = {"presence": present, "length": length, "extent": ext, "box": box_col}
    safe_e = ext.clamp_min(res).unsqueeze(-1)
    if view == "front":
        heights = box.sum(2).float() * res                # boxes stand on the board: their top
        out["height"] = (heights.gather(2, cols) / safe_e).clamp(0, 1)
    else:
        rows = torch.arange(S, device=layouts.device)[None, None, :, None]            # row index, per column
        big = torch.full_like(box, S, dtype=torch.long)

        def last_row(m):                           # per column, the last row where m holds (-S where none)
            return torch.where(m, rows, -big).amax(2)

        r_first = torch.where(box, rows, big).amin(2)                                   # far edge row
        r_last = last_row(box)                                                          # near edge row
        half = ext.unsqueeze(-1) / 2

        def frac(r):                               # a row edge (S / 2 - r pixels from the map centre) -> fraction of E
            return (((S / 2 - r.float()) * res).gather(2, cols) + half) / safe_e

        out["near"] = frac(r_last + 1).clamp(0, 1)
        if back:                                   # the near run starts at the last box row whose row above is no box
            above_box = torch.cat([torch.zeros_like(box[:, :, :1]), box[:, :, :-1]], 2)
            r_run = last_row(box & ~above_box)
            behind = box & (rows < r_run.unsqueeze(2))
            b_last = last_row(behind)
            has = behind.any(2)
            out["far"] = frac(r_run).clamp(0, 1)
            out["back"] = has.gather(2, cols)
            out["back_near"] = (frac(b_last + 1) * out["back"]).clamp(0, 1)
            out["back_far"] = (frac(r_first) * out["back"]).clamp(0, 1)
        else:
            out["far"] = frac(r_first).clamp(0, 1)
    return out


def gap_positions(box: torch.Tensor) -> torch.Tensor:
    """(..., T) bool box-or-not per position -> (..., T) bool: the gaps between boxes (positions
    without a box that have a box on either side along the shelf)."""
    left = box.int().cummax(-1).values.bool()
    right = box.flip(-1).int().cummax(-1).values.flip(-1).bool()
    return ~box & left & right


#: the gap output's loss weights a true gap position this many times a non-gap one (gaps are
#: ~4 of 96 positions on a shelf with two loads)
GAP_POS_WEIGHT = 5.0


#: the half-width a struct decoder may give a shelf in the image, in image widths (a shelf across
#: 4 % of the image to one 8 times as wide as the image)
MIN_HALF_WIDTH, MAX_HALF_WIDTH = 0.02, 4.0


def image_span(st: dict) -> torch.Tensor:
    """Where a struct decoder places each shelf across the image, from its placement ("centre",
    "half") -> (..., 2) left and right ends in image widths (0 the left edge, 1 the right; beyond
    [0, 1] where the shelf leaves the frame): the form of the labelled spans (`racklay.data.level_spans`)."""
    c, h = 0.5 + st["centre"].float(), st["half"].float()
    return torch.stack([c - h, c + h], -1)


def placement_loss(st: dict, spans: torch.Tensor, present: torch.Tensor) -> torch.Tensor | None:
    """L1 of a struct decoder's placement (`centre`, log `half`) against the labelled span of each
    shelf in the image (`spans` (N, R, 2): left and right end in image widths, NaN where no span is
    known), over the shelves `present` (N, R) that have a span; None when none has."""
    spans = spans.to(st["centre"].device, torch.float32)
    ok = torch.isfinite(spans).all(-1) & present
    if not ok.any():
        return None
    centre = spans.mean(-1) - 0.5
    half = ((spans[..., 1] - spans[..., 0]) / 2).clamp(MIN_HALF_WIDTH, MAX_HALF_WIDTH)
    return ((st["centre"].float() - centre).abs()[ok].mean()
            + (st["half"].float().log() - half.log()).abs()[ok].mean())


def structure_loss(view: str, st: dict, layouts: torch.Tensor, extent: float, gap_weight: float = 1.0,
                   gap_loss_weight: float = 1.0, spans: torch.Tensor | None = None,
                   placement_weight: float = 0.0) -> torch.Tensor:
    """Direct supervision of a predicted structure with the truth's: BCE on shelf presence; for
    shelves that exist, L1 of log length and log extent (scale) and, per position, BCE on box and
    L1 of the box fractions where a box is (shape, sampled at the true length); with a back interval
    (`st["back"]`), BCE on it where a box is and L1 of its fractions where one stands behind. `gap_weight`
    weights the box BCE at the gaps between boxes (`gap_positions`): a gap of 10 cm is ~4 of the 96
    positions of a 2.3 m shelf, so without it bridging two boxes costs the loss next to nothing.
    A structure with a gap output (`StructDecoder(gap=True)`: "gap" and "box_raw") has its box BCE
    on the box logit before the cut and a BCE of its own on the gap logit at `gap_positions`
    (positives weighted `GAP_POS_WEIGHT`), weighted by `gap_loss_weight`; with the brightness cue
    ("gap_main" and "gap_cue", `StructDecoder(cue=True)`) each of the two gap detectors has that BCE
    of its own, so neither learns to lean on the other. With `spans` (each
    shelf's labelled span in the image, see `placement_loss`) and `placement_weight` > 0 the
    shelf's placement in the image is supervised too (a shelf read from the wrong image columns
    sees the wrong boxes, however well it reads them)."""
    T = st["box"].shape[-1]
    tr = truth_structure(view, layouts, extent, T, back="back" in st)
    pres = tr["presence"]
    loss = F.binary_cross_entropy_with_logits(st["presence"].float(), pres.float())
    if not pres.any():
        return loss
    if placement_weight and spans is not None:
        if "centre" not in st:
            raise ValueError("placement supervision needs a structure with a placement (the struct decoder's)")
        pl = placement_loss(st, spans, pres)
        if pl is not None:
            loss = loss + placement_weight * pl
    res = extent / layouts.shape[-1]
    for k in ("length", "extent"):
        loss = loss + (st[k].float()[pres].clamp_min(res).log() - tr[k][pres].clamp_min(res).log()).abs().mean()
    w = None
    if gap_weight != 1.0:
        w = 1.0 + (gap_weight - 1.0) * gap_positions(tr["box"][pres]).float()
    box = st["box_raw"] if "gap" in st else st["box"]
    loss = loss + F.binary_cross_entropy_with_logits(box.float()[pres], tr["box"][pres].float(), weight=w)
    if "gap" in st:
        gaps = gap_positions(tr["box"][pres]).float()
        pos_weight = torch.tensor(GAP_POS_WEIGHT, device=st["gap"].device)
        for k in ("gap_main", "gap_cue") if "gap_cue" in st else ("gap",):   # two experts: each by its own BCE
            loss = loss + gap_loss_weight * F.binary_cross_entropy_with_logits(st[k].float()[pres], gaps,
                                                                               pos_weight=pos_weight)
    has_box = tr["box"] & pres.unsqueeze(-1)
    if has_box.any():
        for k in (("height",) if view == "front" else ("near", "far")):
            loss = loss + (st[k].float()[has_box] - tr[k][has_box]).abs().mean()
        if "back" in st:                           # whether a box stands behind the front one, and where
            loss = loss + F.binary_cross_entropy_with_logits(st["back"].float()[has_box], tr["back"][has_box].float())
            has_back = has_box & tr["back"]
            if has_back.any():
                for k in ("back_near", "back_far"):
                    loss = loss + (st[k].float()[has_back] - tr[k][has_back]).abs().mean()
    return loss


#: structure fields a distilled student matches (`distill_structure_loss`); each view has those it predicts
DISTILL_FIELDS = ("presence", "length", "extent", "centre", "half", "box_raw", "box", "gap", "height", "near", "far",
                  "back", "back_near", "back_far")


def distill_structure_loss(view: str, st: dict, teacher: dict, gap_weight: float = 1.0) -> torch.Tensor:
    """How far a predicted structure is from a teacher's (`racklay.distill`): BCE of the presence
    logit on the teacher's presence probability; for each shelf weighted by that probability, L1 of
    log length, log extent, log half-width and of the placement centre; per position, BCE of the box
    logit (before the gap cut, where there is a gap output) and of the gap logit on the teacher's
    probabilities, and L1 of the box fractions (height, or near and far; with a back interval its
    logit's BCE and its fractions too) where the teacher sees a
    box. Soft targets: the loss does not reach 0 where the teacher is unsure. `gap_weight` weights
    the gap BCE at each position by 1 + (gap_weight - 1) x the teacher's gap probability: gaps are a
    few positions of a shelf, and a student fitted on the mean learns to miss them."""
    p = torch.sigmoid(teacher["presence"].float())
    loss = F.binary_cross_entropy_with_logits(st["presence"].float(), p)
    w = p.clamp_min(1e-3)
    for k in ("length", "extent", "half"):
        loss = loss + ((st[k].float().log() - teacher[k].float().log()).abs() * w).sum() / w.sum()
    loss = loss + ((st["centre"].float() - teacher["centre"].float()).abs() * w).sum() / w.sum()
    box = "box_raw" if "gap" in teacher else "box"
    wpos = w.unsqueeze(-1).expand_as(teacher[box])
    for k in (box, "gap") if "gap" in teacher else (box,):
        target = torch.sigmoid(teacher[k].float())
        bce = F.binary_cross_entropy_with_logits(st[k].float(), target, reduction="none")
        wk = wpos * (1 + (gap_weight - 1) * target) if k == "gap" else wpos
        loss = loss + (bce * wk).sum() / wpos.sum()
    wb = wpos * torch.sigmoid(teacher[box].float())
    for k in ("height",) if view == "front" else ("near", "far"):
        loss = loss + ((st[k].float() - teacher[k].float()).abs() * wb).sum() / wb.sum().clamp_min(1e-3)
    if "back" in teacher:                          # a box behind the front one: where the teacher sees a box
        if "back" not in st:
            raise ValueError("the teacher has a back interval (struct_back) and the student none: give the "
                             "student --struct-back")
        target = torch.sigmoid(teacher["back"].float())
        loss = loss + (F.binary_cross_entropy_with_logits(st["back"].float(), target, reduction="none") * wb).sum() \
            / wb.sum().clamp_min(1e-3)
        wk = wb * target
        for k in ("back_near", "back_far"):
            loss = loss + ((st[k].float() - teacher[k].float()).abs() * wk).sum() / wk.sum().clamp_min(1e-3)
    return loss


def rescale_structure(st: dict, length: float | torch.Tensor) -> dict:
    """The same structure at a known shelf length: every present shelf's length set to `length`
    metres and its extent scaled by the same factor (one scale for the whole shelf); shape fields
    unchanged."""
    k = torch.as_tensor(length, dtype=st["length"].dtype, device=st["length"].device) / st["length"].clamp_min(_EPS)
    return {**st, "length": st["length"] * k, "extent": st["extent"] * k}


__all__ = ["DEFAULT_T", "DEFAULT_TAU_PX", "HARD_TAU_PX", "NUM_CLASSES", "pixel_centres", "sample_positions", "rasterize",
           "truth_structure", "gap_positions", "GAP_POS_WEIGHT", "MIN_HALF_WIDTH", "MAX_HALF_WIDTH", "image_span", "placement_loss", "structure_loss", "rescale_structure"]
