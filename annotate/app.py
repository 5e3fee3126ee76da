"""The annotation tool's gradio app (gradio 6): the page's components and the wiring of each
page event to annotate.editor.Tool, which does the work. The page itself (viewer, keys, how a
click travels) is annotate.page; serving it is annotate.server.

Offline by design: analytics off, a built-in theme with system fonts, no CDN assets.
"""
import contextlib
import json
import os

os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")

from . import draw as D
from . import schema as S
from .editor import Tool
from .page import MODE_HELP, SHORTCUTS, VIEWER_HTML
from .session import FILTERS, MODES, Session
from .store import Project, StoreError

# --- the gradio UI ------------------------------------------------------------------------------
#: gradio's delete_cache: every minute, remove the files this app put in gradio's cache (uploads,
#: accepted or refused) once they are 5 minutes old
DELETE_CACHE = (60, 300)
#: every server event of the app runs one at a time, in the order it arrived
CONCURRENCY = dict(concurrency_limit=1, concurrency_id="annotate")


def build_app(project: Project, predictor=None, user: str | None = None, gap_split=None):
    """The gradio app over a Tool; `gap_split` (annotate.geometry.GapSplit): how proposals and `W`
    cut at the photo's gaps (default: its defaults)."""
    import time

    import gradio as gr

    tool = Tool(project, predictor, user)
    if gap_split is not None:
        tool.gap_split = gap_split
    presets = [p["name"] for p in project.settings["presets"]]

    with gr.Blocks(title="RackLay annotate", delete_cache=DELETE_CACHE) as demo:
        state = gr.State(None)
        header = gr.Markdown(elem_id="header")
        with gr.Row():
            filter_dd = gr.Dropdown(choices=list(FILTERS), value="all", label="list", elem_id="filter", scale=1,
                                    min_width=110)
            # filled by on_load for a logged-in session: the page served before login must not list the photos;
            # wide enough for a camera's file name and its status at 1280-1440 px
            image_dd = gr.Dropdown(choices=[], label="photo (status)", elem_id="image-select", scale=6, min_width=300)
            gr.Button("◀ prev (p)", elem_id="btn-prev", size="sm", scale=0, min_width=90)
            gr.Button("next ▶ (n)", elem_id="btn-next", size="sm", scale=0, min_width=90)
            gr.Button("next unfinished (u)", elem_id="btn-next-todo", size="sm", scale=0, min_width=90)
            status_dd = gr.Dropdown(choices=list(S.STATUSES), label="annotation status", elem_id="status", scale=2,
                                    min_width=130)
            gr.Button("mark done (d)", elem_id="btn-done", size="sm", scale=0, min_width=90)
        with gr.Row(elem_classes="mode-row"):
            for i, m in enumerate(MODES):
                gr.Button(f"{i + 1} {m}", elem_id=f"mode-{m}", size="sm")
        gr.HTML('<div id="mode-help" class="rl-text"></div>')
        with gr.Row():
            with gr.Column(scale=3):
                gr.HTML(VIEWER_HTML)
                gr.HTML('<div id="message" class="rl-text"></div>')
            with gr.Column(scale=2):
                gr.Markdown("**Live layouts** — per shelf (S1 = lowest): top view above, front view below; "
                            "orange = box, blue = free shelf space")
                gr.HTML('<img id="rl-preview" alt="layouts" hidden><div id="summary" class="rl-text"></div>')
        with gr.Row():
            with gr.Column():
                gr.Markdown("**Rack**")
                preset_dd = gr.Dropdown(choices=presets, label="preset", elem_id="preset")
                with gr.Row():
                    gr.Number(label="width m", elem_id="rack-width", elem_classes="rl-field", minimum=0)
                    gr.Number(label="height m", elem_id="rack-height", elem_classes="rl-field", minimum=0)
                    gr.Number(label="depth m", elem_id="rack-depth", elem_classes="rl-field", minimum=0)
                gr.Button("confirm size (c)", elem_id="btn-confirm-size", size="sm")
                with gr.Row():
                    gr.Number(label="reference width m", elem_id="ref-width", elem_classes="rl-field", minimum=0)
                    gr.Number(label="reference height m", elem_id="ref-height", elem_classes="rl-field", minimum=0)
                    gr.Button("rack size from selected box (g)", elem_id="btn-size-from-box", size="sm")
            with gr.Column():
                gr.Markdown("**Selection**")
                gr.HTML('<div id="selection" class="rl-text"></div>')
                with gr.Row():
                    gr.Number(label="box depth m (empty: shelf depth; or mode 7)", elem_id="box-depth",
                              elem_classes="rl-field", minimum=0)
                    gr.Number(label="front offset m (or mode 8)", elem_id="box-offset", elem_classes="rl-field", minimum=0)
                with gr.Row():
                    gr.Number(label="split into N equal boxes (w)", elem_id="split-n", elem_classes="rl-field",
                              minimum=2, precision=0)
                    gr.Button("split the row (w)", elem_id="btn-split-row", size="sm")
                    gr.Button("split at the photo's gaps (W)", elem_id="btn-split-gaps", size="sm")
                with gr.Row():
                    gr.Button("on board / floats (f)", elem_id="btn-on-board", size="sm")
                    gr.Button("delete (Del)", elem_id="btn-delete", size="sm")
                    gr.Button("accept (a)", elem_id="btn-accept", size="sm")
                    gr.Button("reject (r)", elem_id="btn-reject", size="sm")
                    gr.Button("accept all (A)", elem_id="btn-accept-all", size="sm")
            with gr.Column():
                gr.Markdown("**Edit & view**")
                with gr.Row():
                    gr.Button("undo (z)", elem_id="btn-undo", size="sm")
                    gr.Button("redo (y)", elem_id="btn-redo", size="sm")
                    gr.Button("save (s)", elem_id="btn-save", size="sm")
                    gr.Button("cancel box (Esc)", elem_id="btn-cancel", size="sm")
                with gr.Row():
                    gr.Button("zoom + ", elem_id="btn-zoom-in", size="sm")
                    gr.Button("zoom −", elem_id="btn-zoom-out", size="sm")
                    gr.Button("fit", elem_id="btn-zoom-reset", size="sm")
                upload = gr.File(label="add photos (PNG/JPEG)", file_count="multiple", file_types=[".png", ".jpg", ".jpeg"],
                                 elem_id="upload")
        with gr.Accordion("Keyboard shortcuts", open=True):
            gr.Markdown("\n".join(["| key | action |", "|---|---|"] + [f"| {k} | {v} |" for k, v in SHORTCUTS]),
                        elem_id="shortcuts")
        # the page's channel to the server (hidden): a batch of actions in, the view's data out
        actions_tb = gr.Textbox(elem_id="rl-actions", elem_classes="rl-hidden", container=False)
        send = gr.Button("send", elem_id="rl-send", elem_classes="rl-hidden")
        view_data = gr.HTML(elem_id="rl-view-data", elem_classes="rl-hidden")
        photo_data = gr.HTML(elem_id="rl-photo-data", elem_classes="rl-hidden")
        preview_data = gr.HTML(elem_id="rl-preview-data", elem_classes="rl-hidden")

        outputs = [state, header, image_dd, status_dd, preset_dd, view_data, photo_data]

        def render(st: Session, t0=None):
            """Every output, drawn from one frame (one scene); an output unchanged since this
            session's last answer is not sent again."""
            f = tool.frame(st)
            sel_txt, bd, bo = D.selection(f)
            a = st.ann or {}
            rack = a.get("rack") or {}
            stats = f.statuses
            choices = [(f"{n} · {stats.get(n, '?')}", n) for n in tool.listed(st, stats)]
            name = st.name
            photo_key = f"{name}:{project.image_path(name).stat().st_mtime_ns}" if st.ann is not None else ""
            view = {"ack": st.ack, "name": name, "image_size": a.get("image_size"), "mode": st.mode,
                    "pixel_aspect": S.pixel_aspect(project.settings),
                    "overlay": D.overlay(f), "sel": st.sel,
                    "fields": {"width": rack.get("width"), "height": rack.get("height"), "depth": rack.get("depth"),
                               "box_depth": bd, "box_offset": bo, "ref_width": st.ref[0], "ref_height": st.ref[1],
                               "split_n": st.split_n},
                    "text": {"message": D.md_html(st.msg), "summary": D.md_html(D.summary(f)),
                             "selection": D.md_html(sel_txt),
                             "mode-help": D.md_html(f"**{st.mode}**: {MODE_HELP.get(st.mode, '')}")}}
            vals = {"header": D.header(f), "image_dd": (tuple(choices), name), "status": a.get("status"),
                    "preset": rack.get("preset"), "photo": photo_key}
            last = st.sent
            out = [st]
            for k in ("header", "image_dd", "status", "preset"):
                if last.get(k, object()) == vals[k]:
                    out.append(gr.skip())
                    continue
                last[k] = vals[k]
                out.append(gr.update(choices=list(vals[k][0]), value=vals[k][1]) if k == "image_dd" else vals[k])
            view["ms"] = None if t0 is None else round((time.perf_counter() - t0) * 1000, 1)
            out.append(D.pre(json.dumps(view)))
            if last.get("photo") == photo_key:
                out.append(gr.skip())
            else:
                last["photo"] = photo_key
                out.append(D.pre(tool.photo_b64(name) if photo_key else "", data_key=photo_key))
            return out

        def on_preview(st: Session | None):
            """The layouts preview, right after each answer (so the click's outline is on screen
            first): sent only when it changed."""
            if st is None:
                return gr.skip()
            url = D.preview_url(tool.frame(st)) or ""
            if st.sent.get("preview") == url:
                return gr.skip()
            st.sent["preview"] = url
            return D.pre(url)

        def ensure(st, request=None):
            if st is not None:
                return st
            who = getattr(request, "username", None)
            return tool.open(project.resume_image(who), who)

        def on_load(request: gr.Request):
            # the logged-in user (--auth-file) is kept in the session state and recorded on saves
            return render(ensure(None, request))

        def on_actions(st, text, request: gr.Request):
            t0 = time.perf_counter()
            st = ensure(st, request)
            try:
                actions = json.loads(text or "[]")
            except json.JSONDecodeError:
                actions = []
                st.msg = "⚠ ignored a malformed request (not JSON)"
            return render(tool.apply(st, actions), t0)

        def on_upload(st, files, request: gr.Request):
            st = ensure(st, request)
            added, errs = [], []
            for f in files or []:
                path = f if isinstance(f, str) else getattr(f, "name", str(f))
                try:
                    with open(path, "rb") as fh:
                        data = fh.read()
                    added.append(project.add_image(os.path.basename(path), data))
                except (StoreError, OSError) as e:
                    errs.append(str(e))
                finally:
                    with contextlib.suppress(OSError):   # gradio's copy of the upload: done with it
                        os.unlink(path)
            if added and st.name is None:
                st = tool.open(added[0], st.user, st)
            st.msg = (f"added {', '.join(added)}" if added else "") + (("; ⚠ " + "; ⚠ ".join(errs)) if errs else "")
            return render(st)

        demo.load(on_load, None, outputs, **CONCURRENCY).then(on_preview, [state], [preview_data],
                                                                 show_progress="hidden", **CONCURRENCY)
        send.click(on_actions, [state, actions_tb], outputs, js="(s, a) => [s, window.rl ? window.rl.take() : '[]']",
                   trigger_mode="multiple", show_progress="hidden", queue=True, **CONCURRENCY).then(
            on_preview, [state], [preview_data], show_progress="hidden", **CONCURRENCY)
        # the dropdowns go through the page's queue too (in order with the clicks), not to the server
        for dd, kind, key in ((image_dd, "open", "name"), (filter_dd, "filter", "value"),
                              (status_dd, "status", "value"), (preset_dd, "preset", "name")):
            dd.input(None, [dd], None, js=f"(v) => {{ window.rl && window.rl.enqueue({{kind: '{kind}', {key}: v}}); return []; }}")
        upload.upload(on_upload, [state, upload], outputs, **CONCURRENCY).then(
            on_preview, [state], [preview_data], show_progress="hidden", **CONCURRENCY)
    demo.tool = tool
    return demo

