"""The annotation tool's page: the photo viewer (HTML, its script and CSS), the mode help, the
keyboard shortcuts and the maps from keys, buttons and number fields to actions.

How a click travels: the photo viewer is the page's own (VIEWER_JS): the photo is sent once per
photo, zoom, pan, brightness and contrast are done in the browser, and the outlines are drawn
over the photo from a list of shapes the server computes (annotate.draw.overlay). Every action
of the labeller (a click on the photo, a mode key, a button, a typed number) goes into one queue
in the page and reaches the server in order, in batches: one batch at a time, the next as soon
as the answer to the previous one is on screen, so no click is dropped however fast they come.
Each action has a sequence number; the server applies each number once (a batch re-sent after a
lost answer is not applied twice).
"""
from __future__ import annotations

import json

from .session import MODES

DISPLAY_H = 640  # the photo viewer's height, in CSS pixels (it is as wide as its column)
MODE_HELP = {
    "corners": "click the 4 corners of the rack's front face (any order); a 5th click moves the nearest corner",
    "shelves": "click once on each shelf board's front edge",
    "boxes": "click two opposite corners of a box's (or stack's) front face, or drag from one to the other",
    "select": "click a corner, shelf line, box or proposal to select it; drag it to move it (a box grabbed "
              "by a corner: resize it)",
    "move": "click where the selected item should go (a box moves its centre there), or drag to move it by the drag",
    "resize": "drag a corner of the selected box to where it should go, or click near the corner, then where it goes",
    "depth": "click the top-back edge of the selected box: its depth (then back to the previous mode)",
    "offset": "click the board where the selected box's front stands: its front offset (then back)",
}
#: key -> what it does (the page's keydown handler; never while typing in a field)
SHORTCUTS = [
    ("1 … 8", "mode: corners, shelves, boxes, select, move, resize, depth, offset"),
    ("n / →", "next photo (in the list's filter)"), ("p / ←", "previous photo"),
    ("u", "next unfinished photo"),
    ("z / Ctrl+Z", "undo"), ("y / Ctrl+Y", "redo"),
    ("Del / Backspace / x", "delete selected (a proposal: reject)"),
    ("s / Ctrl+S", "save now"),
    ("d", "mark done (refused while the photo has warnings; while model proposals wait, d again rejects them)"),
    ("c", "confirm the rack size"), ("g", "rack size from the selected box (a reference object of the typed size)"),
    ("w", "split the selected box into N equal boxes along the rack (a row of equal loads; N under Selection)"),
    ("W", "split the selected box where the photo shows gaps between its loads (a row of loads, any widths)"),
    ("f", "selected box: stands on its board / floats (on something)"),
    ("a / r", "accept / reject selected proposal"), ("A", "accept all proposals"),
    ("wheel, + / - / 0", "zoom at the cursor / reset; right-drag or Space+drag pans"),
    ("Enter", "leave a number field (its value is applied)"),
    ("Esc", "cancel a half-drawn box or a grabbed corner"),
]
#: page element id -> action; 'mode:X' and 'view:X' are handled in the page (view: no server)
BUTTONS = {f"mode-{m}": f"mode:{m}" for m in MODES}
BUTTONS.update({
    "btn-next": "next", "btn-prev": "prev", "btn-next-todo": "next_unfinished", "btn-undo": "undo",
    "btn-redo": "redo", "btn-delete": "delete", "btn-save": "save", "btn-done": "done",
    "btn-accept": "accept", "btn-reject": "reject", "btn-accept-all": "accept_all", "btn-cancel": "cancel",
    "btn-confirm-size": "confirm_size", "btn-on-board": "toggle_on_board", "btn-size-from-box": "size_from_box",
    "btn-split-row": "split_row", "btn-split-gaps": "split_at_gaps",
    "btn-zoom-in": "view:in", "btn-zoom-out": "view:out", "btn-zoom-reset": "view:reset",
})
KEYMAP = {str(i + 1): f"mode:{m}" for i, m in enumerate(MODES)}
KEYMAP.update({
    "n": "next", "ArrowRight": "next", "p": "prev", "ArrowLeft": "prev", "u": "next_unfinished",
    "z": "undo", "Ctrl+z": "undo", "y": "redo", "Ctrl+y": "redo", "Ctrl+Z": "redo",
    "Delete": "delete", "Backspace": "delete", "x": "delete", "s": "save", "Ctrl+s": "save",
    "d": "done", "c": "confirm_size", "g": "size_from_box", "w": "split_row", "W": "split_at_gaps", "f": "toggle_on_board", "a": "accept", "r": "reject", "A": "accept_all",
    "+": "view:in", "=": "view:in", "-": "view:out", "0": "view:reset", "Escape": "cancel",
})
#: number fields (elem_id -> action field); the page sends the text as typed when it changes
FIELDS = {"rack-width": "width", "rack-height": "height", "rack-depth": "depth",
          "box-depth": "box_depth", "box-offset": "box_offset", "ref-width": "ref_width", "ref-height": "ref_height",
          "split-n": "split_n"}

VIEWER_HTML = """<div id="rl-viewer">
<div id="rl-banner" hidden></div>
<div id="rl-toolbar"><span id="rl-zoom">fit</span>
 <label>brightness <input type="range" id="rl-bright" min="30" max="300" value="100"></label>
 <label>contrast <input type="range" id="rl-contrast" min="30" max="300" value="100"></label>
 <button id="rl-view-reset" type="button">reset view</button>
 <span class="rl-hint">wheel: zoom at the cursor · right-drag or Space+drag: pan · view only, nothing is saved</span></div>
<div id="rl-viewport" style="height:%dpx"><div id="rl-loading">loading the photo…</div><div id="rl-stage"><img id="rl-img" alt="" draggable="false">
<svg id="rl-svg" xmlns="http://www.w3.org/2000/svg"></svg></div></div>
</div>""" % DISPLAY_H

VIEWER_JS = r"""
(() => {
  const KEYMAP = __KEYMAP__, BUTTONS = __BUTTONS__, FIELDS = __FIELDS__;
  const rl = window.rl = {q: [], inflight: null, seq: 0, view: null, up: true, stats: [], W: 0, H: 0,
                          s: 1, fit: 1, tx: 0, ty: 0, mouse: null, photoKey: null, previewSrc: null,
                          ax: 1};   // ax: width / height of a photo pixel (the project's pixel_aspect)
  const $ = (s) => document.querySelector(s);
  // --- the action queue: one batch at a time, in order ---------------------------------------
  rl.enqueue = (a, t) => {
    a.seq = ++rl.seq; a.t = t === undefined ? performance.now() : t;
    rl.q.push(a); pump(); return a.seq;
  };
  function pump() {
    if (rl.inflight || !rl.q.length || !rl.up) return;
    const btn = $('#rl-send');
    if (!btn) { setTimeout(pump, 30); return; }
    rl.inflight = rl.q.splice(0);
    rl.sentAt = performance.now();
    btn.click();
  }
  rl.take = () => JSON.stringify((rl.inflight || []).map(({t, ...a}) => a));
  // a batch without an answer for a while: ask again (the server applies each number once)
  setInterval(() => {
    if (rl.inflight && rl.up && performance.now() - rl.sentAt > 8000) {
      rl.sentAt = performance.now(); const b = $('#rl-send'); if (b) b.click();
    }
  }, 1000);
  // --- the server's answer ------------------------------------------------------------------
  function onView() {
    const el = $('#rl-view-data pre');
    if (!el || el.textContent === rl.lastText) return;
    rl.lastText = el.textContent;
    let v; try { v = JSON.parse(el.textContent); } catch (e) { return; }
    rl.view = v;
    const ax = v.pixel_aspect || 1;
    if (v.image_size && (v.image_size[0] !== rl.W || v.image_size[1] !== rl.H || v.name !== rl.name || ax !== rl.ax)) {
      rl.W = v.image_size[0]; rl.H = v.image_size[1]; rl.name = v.name; rl.ax = ax; fitView();
    }
    draw(v);
    for (const [id, h] of Object.entries(v.text || {})) {
      const el = document.getElementById(id);
      if (el && el.innerHTML !== h) el.innerHTML = h;
    }
    for (const [id, f] of Object.entries(FIELDS)) {
      const inp = document.querySelector('#' + id + ' input');
      if (inp && document.activeElement !== inp) inp.value = (v.fields[f] === null || v.fields[f] === undefined) ? '' : v.fields[f];
    }
    for (const b of document.querySelectorAll('[id^="mode-"]')) {
      const on = b.id === 'mode-' + v.mode;
      b.classList.toggle('primary', on); b.classList.toggle('secondary', !on);
    }
    if (rl.inflight && v.ack >= rl.inflight[rl.inflight.length - 1].seq) {
      const done = rl.inflight, now = performance.now();
      rl.inflight = null;
      requestAnimationFrame(() => {
        const shown = performance.now();
        for (const a of done) rl.stats.push({kind: a.kind, queued: rl.sentAt - a.t, rtt: shown - a.t,
                                             server: v.ms, batch: done.length, answered: now - a.t});
      });
      if (rl.up) banner(null);
      pump();
    }
  }
  function onPreview() {
    const el = $('#rl-preview-data pre'), p = $('#rl-preview');
    if (!el || !p || el.textContent === rl.previewSrc) return;
    rl.previewSrc = el.textContent;
    p.src = rl.previewSrc || ''; p.hidden = !rl.previewSrc;
  }
  function onPhoto() {
    const el = $('#rl-photo-data pre');
    if (!el) return;
    const key = el.getAttribute('data-key');
    if (key === rl.photoKey) return;
    rl.photoKey = key;
    const img = $('#rl-img'), loading = $('#rl-loading');
    if (loading) {           // shown from the page's start until each new photo is decoded
      loading.hidden = !el.textContent.trim();
      img.onload = img.onerror = () => { loading.hidden = true; };
    }
    img.src = el.textContent ? 'data:image/jpeg;base64,' + el.textContent.trim() : '';
  }
  // --- drawing: the photo in a stage that is zoomed and panned by a CSS transform --------------
  function esc(s) { return String(s).replace(/[&<>"]/g, c => ({'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;'})[c]); }
  function draw(v) {
    const svg = $('#rl-svg'), img = $('#rl-img'), stage = $('#rl-stage');
    if (!svg) return;
    stage.style.width = rl.W + 'px'; stage.style.height = rl.H + 'px';
    img.style.width = rl.W + 'px'; img.style.height = rl.H + 'px';
    svg.setAttribute('width', rl.W); svg.setAttribute('height', rl.H);
    svg.setAttribute('viewBox', `-0.5 -0.5 ${rl.W} ${rl.H}`);
    const k = 1 / rl.s, out = [];
    for (const sh of v.overlay || []) {
      const w = (sh.w || 1.5) * k;
      if (sh.t === 'poly') {
        const pts = sh.pts.map(p => p[0].toFixed(2) + ',' + p[1].toFixed(2)).join(' ');
        out.push(`<${sh.closed ? 'polygon' : 'polyline'} points="${pts}" fill="none" stroke="${sh.c}" stroke-width="${w}"${sh.dash ? ` stroke-dasharray="${4 * k},${3 * k}"` : ''}/>`);
      } else if (sh.t === 'dot') {
        out.push(`<circle cx="${sh.x}" cy="${sh.y}" r="${(sh.r || 4) * k}" fill="${sh.c}" stroke="#000" stroke-width="${0.8 * k}"/>`);
      } else if (sh.t === 'cross') {
        const r = (sh.r || 6) * k;
        out.push(`<path d="M${sh.x - r},${sh.y - r}L${sh.x + r},${sh.y + r}M${sh.x - r},${sh.y + r}L${sh.x + r},${sh.y - r}" stroke="${sh.c}" stroke-width="${2 * k}"/>`);
      } else if (sh.t === 'text') {
        out.push(`<text x="${sh.x}" y="${sh.y}" fill="${sh.c}" font-size="${12 * k}" stroke="#000" stroke-width="${0.3 * k}">${esc(sh.s)}</text>`);
      }
    }
    svg.innerHTML = out.join('');
  }
  function applyTransform() {
    const stage = $('#rl-stage');
    // a squeezed photo (pixel aspect ax) is shown as taken: its pixels ax times wider than high
    if (stage) stage.style.transform = `translate(${rl.tx}px, ${rl.ty}px) scale(${rl.s * rl.ax}, ${rl.s})`;
    const z = $('#rl-zoom'); if (z) z.textContent = rl.s / rl.fit > 1.001 ? `zoom ${(rl.s / rl.fit).toFixed(1)}×` : 'fit';
    if (rl.view) draw(rl.view);
  }
  function fitView() {
    const vp = $('#rl-viewport');
    if (!vp || !rl.W) return;
    const vw = vp.clientWidth, vh = vp.clientHeight;
    rl.fit = rl.s = Math.min(vw / (rl.W * rl.ax), vh / rl.H);
    rl.tx = (vw - rl.W * rl.ax * rl.s) / 2; rl.ty = (vh - rl.H * rl.s) / 2;
    applyTransform();
  }
  rl.fitView = fitView;
  function zoomAt(cx, cy, f) {   // keeps the photo point under (cx, cy) where it is
    const ns = Math.min(Math.max(rl.s * f, rl.fit), rl.fit * 32), k = ns / rl.s;
    rl.tx = cx - (cx - rl.tx) * k; rl.ty = cy - (cy - rl.ty) * k; rl.s = ns;
    if (Math.abs(ns - rl.fit) < 1e-9) return fitView();
    applyTransform();
  }
  rl.zoomAt = zoomAt;
  // photo pixel (x right, y down; pixel centres at integers) <-> page (client) coordinates
  rl.toImage = (clientX, clientY) => {
    const r = $('#rl-viewport').getBoundingClientRect();
    return [(clientX - r.left - rl.tx) / (rl.s * rl.ax) - 0.5, (clientY - r.top - rl.ty) / rl.s - 0.5];
  };
  rl.toClient = (x, y) => {
    const r = $('#rl-viewport').getBoundingClientRect();
    return [r.left + rl.tx + (x + 0.5) * rl.s * rl.ax, r.top + rl.ty + (y + 0.5) * rl.s];
  };
  function viewAction(what) {
    const vp = $('#rl-viewport'), m = rl.mouse || [vp.clientWidth / 2, vp.clientHeight / 2];
    if (what === 'in') zoomAt(m[0], m[1], 2); else if (what === 'out') zoomAt(m[0], m[1], 0.5); else fitView();
  }
  function act(name) {
    if (name.startsWith('view:')) return viewAction(name.slice(5));
    if (name.startsWith('mode:')) return rl.enqueue({kind: 'mode', mode: name.slice(5)});
    rl.enqueue({kind: 'act', name: name});
  }
  rl.act = act;
  function banner(text) {
    const b = $('#rl-banner'); if (!b) return;
    b.hidden = !text; b.textContent = text || '';
  }
  // --- the server's heartbeat: a banner while it is away, and a fresh page when it is back ----
  let misses = 0;
  async function beat() {
    const ctl = new AbortController(), to = setTimeout(() => ctl.abort(), 6000);
    let ok = true;
    try { await fetch(location.pathname, {cache: 'no-store', signal: ctl.signal}); } catch (e) { ok = false; }
    clearTimeout(to);
    misses = ok ? 0 : misses + 1;
    if (!ok && misses < 2) return;   // one slow answer on a busy machine is not an outage
    if (!ok && rl.up) {
      rl.up = false;
      banner(`⚠ the annotation server is not reachable (since ${new Date().toLocaleTimeString()}): ` +
             'clicks are not taken until it is back; everything saved so far is safe. The page reloads by itself when it returns.');
    } else if (ok && !rl.up) {
      banner('the server is back: reloading the page…');
      setTimeout(() => location.reload(), 300);
    }
  }
  (async function loop() { await beat(); setTimeout(loop, 1500); })();
  // --- mouse and keys ----------------------------------------------------------------------------
  let drag = null, space = false;
  function onDown(e) {
    const vp = $('#rl-viewport'); if (!vp || !vp.contains(e.target)) return;
    // a number being typed is applied first (its change event queues it before this click)
    const f = document.activeElement;
    if (f && f !== document.body && f.blur) f.blur();
    e.preventDefault();
    const pan = e.button === 1 || e.button === 2 || (e.button === 0 && space);
    drag = {pan, x: e.clientX, y: e.clientY, tx: rl.tx, ty: rl.ty, t: performance.now(), button: e.button};
  }
  function onMove(e) {
    const vp = $('#rl-viewport'); if (!vp) return;
    const r = vp.getBoundingClientRect();
    if (e.clientX >= r.left && e.clientX <= r.right && e.clientY >= r.top && e.clientY <= r.bottom)
      rl.mouse = [e.clientX - r.left, e.clientY - r.top];
    if (drag && drag.pan) { rl.tx = drag.tx + e.clientX - drag.x; rl.ty = drag.ty + e.clientY - drag.y; applyTransform(); }
  }
  function inside(p) { return p[0] >= -0.5 && p[1] >= -0.5 && p[0] <= rl.W - 0.5 && p[1] <= rl.H - 0.5; }
  function onUp(e) {
    const d = drag; drag = null;
    if (!d || d.pan || e.button !== 0 || !rl.view || !rl.W) return;
    if (!rl.up) { banner($('#rl-banner').textContent || '⚠ the server is not reachable'); return; }
    const p0 = rl.toImage(d.x, d.y), p1 = rl.toImage(e.clientX, e.clientY);
    const moved = Math.hypot(e.clientX - d.x, e.clientY - d.y) > 6;
    const z = rl.s / rl.fit;
    if (moved && rl.view.mode === 'boxes' && inside(p0) && inside(p1))
      return rl.enqueue({kind: 'box', p0: p0, p1: p1, image: rl.view.name}, d.t);
    if (moved && ['select', 'move', 'resize'].includes(rl.view.mode) && inside(p0) && inside(p1))
      return rl.enqueue({kind: 'drag', p0: p0, p1: p1, z: z, image: rl.view.name}, d.t);
    if (!inside(p0)) return;
    rl.enqueue({kind: 'click', x: p0[0], y: p0[1], z: z, image: rl.view.name}, d.t);
  }
  document.addEventListener('mousedown', onDown, true);
  document.addEventListener('mousemove', onMove, true);
  document.addEventListener('mouseup', onUp, true);
  document.addEventListener('contextmenu', (e) => { const vp = $('#rl-viewport'); if (vp && vp.contains(e.target)) e.preventDefault(); }, true);
  document.addEventListener('wheel', (e) => {
    const vp = $('#rl-viewport'); if (!vp || !vp.contains(e.target)) return;
    e.preventDefault();
    const r = vp.getBoundingClientRect();
    zoomAt(e.clientX - r.left, e.clientY - r.top, Math.exp(-e.deltaY * 0.002));
  }, {capture: true, passive: false});
  window.addEventListener('resize', () => { if (rl.s === rl.fit) fitView(); });
  function typing(t) {
    const tag = ((t && t.tagName) || '').toLowerCase();
    if (tag === 'textarea' || tag === 'select' || (t && t.isContentEditable)) return true;
    return tag === 'input' && !['range', 'checkbox', 'radio', 'button'].includes((t.type || '').toLowerCase());
  }
  document.addEventListener('keydown', (e) => {
    const t = e.target;
    if (typing(t)) {
      // Enter (or Esc) leaves a number field; its value is applied as typed (the change event)
      if ((e.key === 'Enter' || e.key === 'Escape') && t.closest && t.closest('.rl-field')) { e.preventDefault(); t.blur(); }
      return;
    }
    if (e.key === ' ') { space = true; const vp = $('#rl-viewport'); if (vp && rl.mouse) e.preventDefault(); return; }
    if (e.altKey) return;
    const key = (e.ctrlKey || e.metaKey) ? 'Ctrl+' + e.key : e.key;
    const a = KEYMAP[key];
    if (!a) return;
    e.preventDefault();
    if (t && t.blur && t !== document.body) t.blur();
    act(a);
  }, true);
  document.addEventListener('keyup', (e) => { if (e.key === ' ') space = false; }, true);
  document.addEventListener('click', (e) => {
    const b = e.target.closest && e.target.closest('button');
    if (!b) return;
    if (b.id === 'rl-view-reset') { fitView(); return; }
    const a = BUTTONS[b.id];
    if (!a) return;
    e.preventDefault(); e.stopPropagation();
    act(a);
  }, true);
  document.addEventListener('change', (e) => {
    const f = e.target.closest && e.target.closest('.rl-field');
    if (!f || !FIELDS[f.id]) return;
    rl.enqueue({kind: 'field', field: FIELDS[f.id], text: e.target.value, image: rl.view && rl.view.name});
  }, true);
  document.addEventListener('input', (e) => {
    if (e.target.id !== 'rl-bright' && e.target.id !== 'rl-contrast') return;
    $('#rl-img').style.filter = `brightness(${$('#rl-bright').value}%) contrast(${$('#rl-contrast').value}%)`;
  }, true);
  document.addEventListener('pointerup', (e) => {
    if (e.target.type === 'range') e.target.blur();   // hotkeys keep working after a slider
  }, true);
  // --- wiring, once gradio has rendered the page ----------------------------------------------
  function init() {
    const vd = $('#rl-view-data'), pd = $('#rl-photo-data'), pv = $('#rl-preview-data'), vp = $('#rl-viewport');
    if (!vd || !pd || !pv || !vp) { setTimeout(init, 30); return; }
    const opts = {subtree: true, childList: true, characterData: true};
    new MutationObserver(onPhoto).observe(pd, opts);
    new MutationObserver(onPreview).observe(pv, opts);
    new MutationObserver(onView).observe(vd, opts);
    onPhoto(); onView(); onPreview();
  }
  if (document.readyState === 'loading') document.addEventListener('DOMContentLoaded', init); else init();
})();
"""


def head() -> str:
    """The page's <script>: the viewer with its key, button and field maps."""
    js = (VIEWER_JS.replace("__KEYMAP__", json.dumps(KEYMAP)).replace("__BUTTONS__", json.dumps(BUTTONS))
          .replace("__FIELDS__", json.dumps(FIELDS)))
    return f"<script>{js}</script>"


CSS = """
#header { font-size: 1.05em; }
.mode-row button { min-width: 0; }
.rl-hidden { display: none !important; }
.rl-text p { margin: 0.2em 0; }
.rl-text ul { margin: 0.2em 0 0.2em 1.2em; padding: 0; }
#rl-viewport { position: relative; overflow: hidden; background: #222; cursor: crosshair; user-select: none; }
#rl-stage { position: absolute; left: 0; top: 0; transform-origin: 0 0; }
#rl-img, #rl-svg { position: absolute; left: 0; top: 0; max-width: none; }
#rl-svg { pointer-events: none; overflow: visible; }
#rl-loading { position: absolute; inset: 0; display: flex; align-items: center; justify-content: center;
              color: #ddd; font-size: 1.1em; pointer-events: none; z-index: 2; }
#rl-loading[hidden] { display: none; }
#rl-banner { background: #b00020; color: #fff; padding: 8px 12px; font-weight: 600; border-radius: 4px; margin-bottom: 6px; }
#rl-toolbar { font-size: 0.85em; display: flex; gap: 12px; align-items: center; flex-wrap: wrap; margin-bottom: 4px; }
#rl-toolbar input[type=range] { width: 110px; vertical-align: middle; }
.rl-hint { color: #888; }
#rl-preview { max-width: 100%; }
"""
