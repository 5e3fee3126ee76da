"""Serving the annotation tool: the port check, gradio's launch settings (offline), the model
that proposes boxes, a per-run temporary folder for gradio's files, and `serve`."""
import os

from .app import build_app  # sets GRADIO_ANALYTICS_ENABLED=False before gradio is imported
from .page import CSS, head
from .store import Project


def launch_kwargs(host: str = "127.0.0.1", port: int = 7860, auth=None) -> dict:
    """Everything launch() needs to run offline: built-in theme with system fonts, our css and
    keyboard script, no SSR node server, upload size limit."""
    import gradio as gr

    from .store import MAX_UPLOAD_BYTES

    theme = gr.themes.Soft(font=["ui-sans-serif", "system-ui", "sans-serif"],
                           font_mono=["ui-monospace", "monospace"])
    return dict(server_name=host, server_port=port, auth=auth, theme=theme, css=CSS, head=head(),
                ssr_mode=False, max_file_size=MAX_UPLOAD_BYTES, show_error=True, quiet=True, footer_links=[])


def load_predictor(model: str | None, backend: str = "torch", precision: str = "fp32"):
    if not model:
        return None
    from racklay.predict import Predictor

    return Predictor(model, backend=backend, precision=precision)


class PortError(ValueError):
    """The server cannot listen on the requested address and port."""


def _port_message(host: str, port: int, reason: str, hint: str = "choose another --port") -> str:
    return f"cannot serve on {host}:{port} ({reason}); {hint}"


def check_port(host: str, port: int) -> None:
    """Refuse a port that cannot be bound before the app (and a model) is loaded. Binds the way
    gradio does (SO_REUSEADDR), then lets go at once."""
    import socket

    if not 1 <= port <= 65535:
        raise PortError(f"--port: {port} is not a port number (1-65535)")
    bind_host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    try:
        infos = socket.getaddrinfo(bind_host, port, type=socket.SOCK_STREAM)
    except OSError as e:
        raise PortError(_port_message(host, port, f"unknown address: {e.strerror or type(e).__name__}",
                                      "check --host")) from None
    family, _, _, _, addr = infos[0]
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(addr)
    except OSError as e:
        import errno

        reason = (e.strerror or type(e).__name__).lower()
        if e.errno == errno.EADDRNOTAVAIL:
            raise PortError(_port_message(host, port, f"{reason}: not an address of this machine",
                                          "check --host")) from None
        raise PortError(_port_message(host, port, reason)) from None


def run_temp_dir() -> str:
    """A temp folder for this server run, holding gradio's cache (rendered photos, uploads) and the
    viewer's images; removed when the process exits (serve() makes SIGTERM a normal exit)."""
    import atexit
    import shutil
    import tempfile

    path = tempfile.mkdtemp(prefix="annotate-run-")
    os.environ["GRADIO_TEMP_DIR"] = os.path.join(path, "gradio")   # read by gradio's blocks and routes
    atexit.register(shutil.rmtree, path, True)
    return path


def _drop_temp_dir(path: str, env_before: str | None) -> None:
    """Undo run_temp_dir() when serve() fails to start."""
    import shutil

    shutil.rmtree(path, ignore_errors=True)
    if env_before is None:
        os.environ.pop("GRADIO_TEMP_DIR", None)
    else:
        os.environ["GRADIO_TEMP_DIR"] = env_before


def serve(project_dir, host: str = "127.0.0.1", port: int = 7860, model: str | None = None,
          backend: str = "torch", auth=None, block: bool = True, gap_split=None, precision: str = "fp32"):
    """Serve the tool. `auth`: None (no login) or an annotate.auth.Authenticator (several users,
    throttled failed logins; each save records the logged-in user); `gap_split`: how proposals and
    `W` cut at the photo's gaps (annotate.geometry.GapSplit; default its defaults); `precision`:
    the model's, as `racklay.predict.Predictor` takes it (the command line's default is `auto`)."""
    check_port(host, port)
    project = Project(project_dir)
    env_before = os.environ.get("GRADIO_TEMP_DIR")
    tmp = run_temp_dir()
    try:
        demo = build_app(project, load_predictor(model, backend, precision), gap_split=gap_split)   # gradio files go to $GRADIO_TEMP_DIR = tmp
        kw = launch_kwargs(host, port, auth.check if auth is not None else None)
        try:
            demo.launch(prevent_thread_lock=True, **kw)
        except OSError as e:
            if "Cannot find empty port" not in str(e):
                raise
            raise PortError(_port_message(host, port, "the port is in use")) from None
    except BaseException:
        _drop_temp_dir(tmp, env_before)
        raise
    print(f"annotate: serving {project.root} ({len(project.images())} images) at http://{host}:{port}"
          + (f", pre-labels from {os.path.basename(str(model))}" if model else ""))
    if block:
        demo.block_thread()
    return demo


