"""One labeller's session in the annotation tool: the photo open, its annotation, undo and redo,
the mode, the selection and what the page was last sent. annotate.editor.Tool's methods take a
Session and return it (gradio keeps one per browser tab); it is plain data, no logic."""
from __future__ import annotations

from dataclasses import dataclass, field

from .schema import Annotation

#: the labeller's modes, in the order of the mode buttons and the keys 1 … 8
MODES = ("corners", "shelves", "boxes", "select", "move", "resize", "depth", "offset")
#: what the photo list can show
FILTERS = ("all", "unfinished", "todo", "in progress", "done", "needs review", "approved", "invalid", "unreadable")


@dataclass
class Session:
    """The state of one browser tab.

    `sel` is the selected item as [kind, key]: ["corner", index], ["shelf", id], ["box", id] or
    ["proposal", id] (a list, as the page receives it). `pending` is the first corner of a
    half-drawn box (photo pixels), `grab` the point where a resize grabbed the selected box (the
    box corner nearest to it moves with the next click). `confirm` names an action waiting for
    its second key press (pressing `d` while model proposals wait asks once). `ref` is the
    reference object's size in metres [width, height] (either may be None) that sizes the rack
    from a selected box; it stays for the session's next photos. `ann` is None when no photo is
    open or its file or photo cannot be used (`error` says why). `ack` is the sequence number of the page's last applied action."""

    name: str | None = None
    ann: Annotation | None = None
    user: str | None = None
    undo: list[Annotation] = field(default_factory=list)
    redo: list[Annotation] = field(default_factory=list)
    mode: str = "corners"
    #: the mode to go back to after a depth or offset click
    mode_before: str | None = None
    sel: list | None = None
    pending: list[float] | None = None
    grab: list[float] | None = None
    confirm: str | None = None
    ref: list = field(default_factory=lambda: [None, None])
    #: how many equal boxes `w` splits the selected box into (a row of equal loads)
    split_n: int = 2
    msg: str = ""
    error: str | None = None
    filter: str = "all"
    ack: int = 0
    #: what the page already shows, per output (an unchanged one is not sent again)
    sent: dict = field(default_factory=dict)
