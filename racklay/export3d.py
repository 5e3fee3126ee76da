"""The 3D reconstruction of a rack (a `racklay.reasoning.RackResult`) as files people open:

- GLB (binary glTF 2.0, written here with numpy + struct): one mesh per shelf board, free-space
  volume (translucent) and box stack, coloured by material; opens in Blender, three.js
  viewers, Windows 3D Viewer, https://gltf-viewer.donmccurdy.com, etc.
- PLY (ascii, per-vertex colours): boards and box stacks as quads, for MeshLab / CloudCompare.
- PNG: a matplotlib 3D render (Poly3DCollection) beside the photo, titled with the report line.

Scene frame: x along the rack, y away from the camera, z up, metres; shelf i's board top sits at
the sum of the clear heights (and display board thicknesses) below it. glTF is y-up, so GLB
vertices are written as (x, z, -y) (a rotation: handedness is kept; the camera-facing side of
the rack faces +Z, glTF's default viewing direction).
"""
from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_write_bytes, atomic_write_text

#: display thickness of a shelf board (the layouts do not encode it)
BOARD_M = 0.04
#: a shelf with no front view is drawn with this clear height
UNKNOWN_HEIGHT_M = 0.3
#: RGBA per part kind
COLORS = {
    "board": (0.27, 0.47, 0.75, 1.0),
    "space": (0.55, 0.75, 0.95, 0.12),
    "box": (0.95, 0.58, 0.16, 1.0),
    "hidden_box": (0.80, 0.35, 0.10, 1.0),
}


@dataclass
class Part:
    name: str
    kind: str  # a key of COLORS
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


def rack_parts(result) -> list[Part]:
    """Axis-aligned cuboids (scene frame) for every shelf board, free-space volume and box stack,
    lowest shelf first."""
    parts: list[Part] = []
    base = 0.0
    depths = [s.y for s in result.shelves if s.depth_m > 0]
    default_y = depths[0] if depths else (-0.3, 0.3)
    for s in result.shelves:
        n = s.index + 1
        y = s.y if s.depth_m > 0 else default_y
        top = base + BOARD_M
        height = s.clear_height_m if s.clear_height_m > 0 else UNKNOWN_HEIGHT_M
        parts.append(Part(f"shelf{n}_board", "board", (s.x[0], y[0], base), (s.x[1], y[1], top)))
        if s.complete:
            parts.append(Part(f"shelf{n}_free_space", "space", (s.x[0], y[0], top), (s.x[1], y[1], top + height)))
        for k, b in enumerate(s.boxes):
            if b.volume_m3 <= 0:
                continue  # one-view detections have no 3D extent
            parts.append(Part(f"shelf{n}_stack{k + 1}", "hidden_box" if b.hidden else "box",
                              (b.x[0], b.y[0], top + b.z[0]), (b.x[1], b.y[1], top + b.z[1])))
        base = top + height
    return parts


# --- cuboid geometry ----------------------------------------------------------------------------
def _cuboid(lo, hi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """24 vertices (4 per face, flat normals) and 12 counter-clockwise (seen from outside)
    triangles of an axis-aligned cuboid: (positions (24,3), normals (24,3), indices (36,))."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    pos, nrm, idx = [], [], []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3  # (u, v, axis) is a right-handed cycle
        for sign in (-1, 1):
            n = np.zeros(3)
            n[axis] = sign
            corners = []
            for a, b in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.empty(3)
                p[axis] = hi[axis] if sign > 0 else lo[axis]
                p[u] = hi[u] if a else lo[u]
                p[v] = hi[v] if b else lo[v]
                corners.append(p)
            if sign < 0:
                corners = corners[::-1]  # keep counter-clockwise seen from outside
            k = len(pos)
            pos += corners
            nrm += [n] * 4
            idx += [k, k + 1, k + 2, k, k + 2, k + 3]
    return np.array(pos), np.array(nrm), np.array(idx, dtype=np.uint32)


def _to_gltf(p: np.ndarray) -> np.ndarray:
    """Scene (x, y, z-up) -> glTF (x, y-up, z towards the viewer) = (x, z, -y)."""
    return np.stack([p[:, 0], p[:, 2], -p[:, 1]], axis=1)


# --- GLB --------------------------------------------------------------------------------------
def glb_bytes(parts: list[Part], generator: str = "racklay") -> bytes:
    """A binary glTF 2.0 file: one node + mesh per part, one material per part kind."""
    kinds = [k for k in COLORS if any(p.kind == k for p in parts)]
    materials = []
    for k in kinds:
        m = {"name": k, "pbrMetallicRoughness": {"baseColorFactor": list(COLORS[k]),
                                                "metallicFactor": 0.0, "roughnessFactor": 0.9}}
        if COLORS[k][3] < 1:
            m["alphaMode"] = "BLEND"
            m["doubleSided"] = True
        materials.append(m)
    pos_blob, nrm_blob, idx_blob = bytearray(), bytearray(), bytearray()
    accessors, meshes, nodes = [], [], []
    for i, part in enumerate(parts):
        p, n, ix = _cuboid(part.lo, part.hi)
        p = _to_gltf(p).astype(np.float32)
        n = _to_gltf(n).astype(np.float32)
        ix = ix.astype(np.uint16)
        a0 = len(accessors)
        accessors += [
            {"bufferView": 0, "byteOffset": len(pos_blob), "componentType": 5126, "count": len(p),
             "type": "VEC3", "min": p.min(axis=0).tolist(), "max": p.max(axis=0).tolist()},
            {"bufferView": 1, "byteOffset": len(nrm_blob), "componentType": 5126, "count": len(n), "type": "VEC3"},
            {"bufferView": 2, "byteOffset": len(idx_blob), "componentType": 5123, "count": len(ix), "type": "SCALAR"},
        ]
        pos_blob += p.tobytes()
        nrm_blob += n.tobytes()
        idx_blob += ix.tobytes()
        meshes.append({"name": part.name, "primitives": [{
            "attributes": {"POSITION": a0, "NORMAL": a0 + 1}, "indices": a0 + 2,
            "material": kinds.index(part.kind), "mode": 4}]})
        nodes.append({"name": part.name, "mesh": i})
    views, blob = [], bytearray()
    for data, target in ((pos_blob, 34962), (nrm_blob, 34962), (idx_blob, 34963)):
        while len(blob) % 4:
            blob += b"\0"
        view = {"buffer": 0, "byteOffset": len(blob), "byteLength": len(data), "target": target}
        if target == 34962:
            view["byteStride"] = 12  # several meshes' accessors share the vertex views
        views.append(view)
        blob += data
    while len(blob) % 4:
        blob += b"\0"
    doc = {"asset": {"version": "2.0", "generator": generator}, "scene": 0,
           "scenes": [{"name": "rack", "nodes": list(range(len(nodes)))}], "nodes": nodes,
           "meshes": meshes, "materials": materials, "accessors": accessors,
           "bufferViews": views if parts else [], "buffers": [{"byteLength": len(blob)}] if parts else []}
    if not parts:  # a valid empty scene: no buffer, no empty arrays (the validator rejects them)
        for k in ("nodes", "meshes", "materials", "accessors", "bufferViews", "buffers"):
            doc.pop(k)
        doc["scenes"] = [{"name": "rack"}]
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<I4s", len(js), b"JSON") + js
    if parts:
        chunks += struct.pack("<I4s", len(blob), b"BIN\0") + bytes(blob)
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """Parse a GLB container back into (JSON document, BIN chunk). Raises ValueError when the
    container is malformed (used by the tests and handy for checking exported files)."""
    if len(data) < 20:
        raise ValueError("GLB: file too short")
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2:
        raise ValueError(f"GLB: bad header (magic {magic!r}, version {version})")
    if length != len(data):
        raise ValueError(f"GLB: header length {length} != file size {len(data)}")
    off, doc, binc = 12, None, b""
    while off < length:
        clen, ctype = struct.unpack_from("<I4s", data, off)
        if clen % 4 or off + 8 + clen > length:
            raise ValueError(f"GLB: bad chunk {ctype!r} of {clen} bytes at {off}")
        body = data[off + 8: off + 8 + clen]
        if ctype == b"JSON":
            doc = json.loads(body.decode("utf-8"))
        elif ctype == b"BIN\0":
            binc = body
        off += 8 + clen
    if doc is None:
        raise ValueError("GLB: no JSON chunk")
    return doc, binc


def glb_mesh_arrays(doc: dict, binc: bytes, mesh: int) -> tuple[np.ndarray, np.ndarray]:
    """(positions (N,3) float32, indices (M,)) of a mesh's first primitive in a parsed GLB."""
    prim = doc["meshes"][mesh]["primitives"][0]

    def acc(i):
        a = doc["accessors"][i]
        bv = doc["bufferViews"][a["bufferView"]]
        dt = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}[a["componentType"]]
        ncomp = {"SCALAR": 1, "VEC3": 3}[a["type"]]
        start = bv["byteOffset"] + a.get("byteOffset", 0)
        arr = np.frombuffer(binc, dtype=dt, count=a["count"] * ncomp, offset=start)
        return arr.reshape(-1, 3) if ncomp == 3 else arr

    return acc(prim["attributes"]["POSITION"]), acc(prim["indices"])


# --- PLY --------------------------------------------------------------------------------------
def ply_text(parts: list[Part], include_space: bool = False) -> str:
    """ASCII PLY: 8 vertices (with RGB colour) and 6 quads per cuboid."""
    verts, faces = [], []
    quads = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (1, 2, 6, 5), (0, 4, 7, 3)]
    for part in parts:
        if part.kind == "space" and not include_space:
            continue
        lo, hi = part.lo, part.hi
        rgb = tuple(int(round(c * 255)) for c in COLORS[part.kind][:3])
        k = len(verts)
        for z in (lo[2], hi[2]):
            for x, y in ((lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])):
                verts.append((x, y, z) + rgb)
        faces += [tuple(k + i for i in q) for q in quads]
    lines = ["ply", "format ascii 1.0", "comment racklay rack reconstruction (x along rack, y depth, z up, metres)",
             f"element vertex {len(verts)}", "property float x", "property float y", "property float z",
             "property uchar red", "property uchar green", "property uchar blue",
             f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [f"{x:.5f} {y:.5f} {z:.5f} {r} {g} {b}" for x, y, z, r, g, b in verts]
    lines += ["4 " + " ".join(map(str, f)) for f in faces]
    return "\n".join(lines) + "\n"


def write_glb(result, path: str | os.PathLike) -> Path:
    return atomic_write_bytes(path, glb_bytes(rack_parts(result)))


def write_ply(result, path: str | os.PathLike) -> Path:
    return atomic_write_text(path, ply_text(rack_parts(result)))


# --- PNG render -------------------------------------------------------------------------------
def render_figure(result, image: np.ndarray | None = None, out: str | os.PathLike | None = None,
                  title: str | None = None, dpi: int = 100):
    """Matplotlib figure: the photo (if given) beside a 3D render of the reconstruction, titled
    with the report line. Saved atomically to `out` when given; returns the figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from .viz import save_figure

    parts = rack_parts(result)
    fig = plt.figure(figsize=(11 if image is not None else 6.5, 5.2))
    if image is not None:
        ax0 = fig.add_subplot(1, 2, 1)
        ax0.imshow(image)
        ax0.set_axis_off()
        ax0.set_title("photo", fontsize=9)
    ax = fig.add_subplot(1, 2 if image is not None else 1, 2 if image is not None else 1, projection="3d")
    # one collection for every face, so matplotlib depth-sorts faces across parts
    quads, faces, edges = [], [], []
    for part in parts:
        p, _, ix = _cuboid(part.lo, part.hi)
        rgba = COLORS[part.kind]
        for k in range(0, 36, 6):
            quads.append(p[ix[k: k + 6][[0, 1, 2, 5]]])
            if part.kind == "space":
                faces.append((*rgba[:3], 0.03))
                edges.append((*rgba[:3], 0.35))
            else:
                faces.append(rgba)
                edges.append((0.15, 0.1, 0.05, 0.8))
    if quads:
        ax.add_collection3d(Poly3DCollection(quads, facecolors=faces, edgecolors=edges, linewidths=0.4))
    if parts:
        lo = np.min([p.lo for p in parts], axis=0)
        hi = np.max([p.hi for p in parts], axis=0)
    else:
        lo, hi = np.array([-1.0, -0.5, 0.0]), np.array([1.0, 0.5, 1.0])
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(np.maximum(hi - lo, 1e-3))
    ax.view_init(elev=18, azim=-70)
    ax.set_xlabel("x (m)", fontsize=7)
    ax.set_ylabel("y (m)", fontsize=7)
    ax.set_zlabel("z (m)", fontsize=7)
    ax.tick_params(labelsize=6)
    ax.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(3))
    ax.set_title("3D reconstruction (orange: box stacks; dark: height only bounded, shares\nall its front-view columns with another stack)", fontsize=8)
    fig.suptitle(title if title is not None else result.report(), fontsize=10)
    fig.tight_layout()
    if out is not None:
        save_figure(fig, out, dpi=dpi)
    return fig


__all__ = ["BOARD_M", "COLORS", "Part", "rack_parts", "glb_bytes", "read_glb", "glb_mesh_arrays",
           "ply_text", "write_glb", "write_ply", "render_figure"]
