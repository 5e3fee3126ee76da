"""Rendering behind a small interface. `Renderer.render(scene) -> RenderOutput` with the RGB
image and exact per-pixel maps (instance ids, camera-frame depth and normals).

Backend `GLRenderer`: moderngl on a headless EGL context (Mesa llvmpipe on CPU here; a GPU
where one exists). All solids are instanced unit cubes / cylinders: one draw call per pass.
Passes: shadow map from the main light; a depth pre-pass; the colour pass (textured Lambert +
Blinn-Phong, 1 shadowed key light + 3 fill lights + ambient), which shades each pixel once, its
nearest surface, and writes the G-buffer beside the colour (no anti-aliasing, so ids, depth and
normals are exact at pixel centres). With MSAA the G-buffer is a pass of its own and the colour
pass is multisampled and resolved.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Protocol

import numpy as np

from .scene import Scene
from .textures import TextureBank

MAX_LIGHTS = 4  # key light + 3 fill lights (array size in the shader)
NEAR, FAR = 0.05, 300.0


@dataclass
class RenderOutput:
    rgb: np.ndarray        # (H, W, 3) uint8
    instance: np.ndarray   # (H, W) uint32: object index + 1, 0 = nothing
    depth: np.ndarray      # (H, W) float32 camera-frame z in metres (0 = nothing)
    normals: np.ndarray    # (H, W, 3) uint8 camera-frame unit normals as (n + 1) / 2 * 255 (0 = nothing)


class Renderer(Protocol):
    def render(self, scene: Scene, camera=None, region=None) -> RenderOutput: ...

    def release(self) -> None: ...


# --- meshes -------------------------------------------------------------------------------
def cube_mesh():
    """24 vertices: pos(3) normal(3) uv(2) mu(3) mv(3) is_top(1); 36 indices."""
    faces = [  # normal, u axis, v axis
        ((1, 0, 0), (0, 1, 0), (0, 0, 1)), ((-1, 0, 0), (0, -1, 0), (0, 0, 1)),
        ((0, 1, 0), (-1, 0, 0), (0, 0, 1)), ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
        ((0, 0, 1), (1, 0, 0), (0, 1, 0)), ((0, 0, -1), (1, 0, 0), (0, -1, 0)),
    ]
    verts, idx = [], []
    for n, u, v in faces:
        n, u, v = (np.array(a, np.float32) for a in (n, u, v))
        base = len(verts)
        for su, sv in ((0, 0), (1, 0), (1, 1), (0, 1)):
            p = 0.5 * n + (su - 0.5) * u + (sv - 0.5) * v
            verts.append(np.concatenate([p, n, [su, 1 - sv], np.abs(u), np.abs(v), [1.0 if abs(n[2]) > 0.5 else 0.0]]))
        idx += [base, base + 1, base + 2, base, base + 2, base + 3]
    return np.array(verts, np.float32), np.array(idx, np.int32)


def cylinder_mesh(seg: int = 20):
    """Vertical cylinder inscribed in the unit cube (radius 0.5 in x and y)."""
    verts, idx = [], []
    for i in range(seg + 1):
        a = 2 * math.pi * i / seg
        c, s = math.cos(a), math.sin(a)
        for z, v in ((-0.5, 1.0), (0.5, 0.0)):
            verts.append([0.5 * c, 0.5 * s, z, c, s, 0, i / seg, v, 1, 1, 0, 0, 0, 1, 0])
    for i in range(seg):
        a, b = 2 * i, 2 * i + 2
        idx += [a, b, b + 1, a, b + 1, a + 1]
    for z, nz in ((0.5, 1.0), (-0.5, -1.0)):
        centre = len(verts)
        verts.append([0, 0, z, 0, 0, nz, 0.5, 0.5, 1, 0, 0, 0, 1, 0, 1])
        for i in range(seg + 1):
            a = 2 * math.pi * i / seg
            verts.append([0.5 * math.cos(a), 0.5 * math.sin(a), z, 0, 0, nz,
                          0.5 + 0.5 * math.cos(a), 0.5 + 0.5 * math.sin(a), 1, 0, 0, 0, 1, 0, 1])
        for i in range(seg):
            t = [centre, centre + 1 + i, centre + 2 + i]
            idx += t if nz > 0 else t[::-1]
    return np.array(verts, np.float32), np.array(idx, np.int32)


_VS_COMMON = """
#version 330
in vec3 in_pos; in vec3 in_normal; in vec2 in_uv; in vec3 in_mu; in vec3 in_mv; in float in_istop;
in vec3 i_center; in vec3 i_size; in float i_yaw; in vec3 i_tint; in vec2 i_layers; in vec4 i_mat; in float i_id;
vec3 world_pos() {
    float c = cos(i_yaw), s = sin(i_yaw);
    vec3 p = in_pos * i_size;
    return i_center + vec3(c * p.x - s * p.y, s * p.x + c * p.y, p.z);
}
vec3 world_normal() {
    float c = cos(i_yaw), s = sin(i_yaw);
    return vec3(c * in_normal.x - s * in_normal.y, s * in_normal.x + c * in_normal.y, in_normal.z);
}
"""

SHADOW_VS = _VS_COMMON + """
uniform mat4 light_vp;
void main() { gl_Position = light_vp * vec4(world_pos(), 1.0); }
"""
SHADOW_FS = """
#version 330
void main() {}
"""

CAM_VS = _VS_COMMON + """
uniform mat3 Rwc; uniform vec3 twc; uniform vec4 proj;   // (2fx/W, 2cx/W - 1, 2fy/H, 1 - 2cy/H)
uniform vec2 nf; uniform mat4 light_vp;
out vec3 v_world; out vec3 v_nworld; out vec3 v_ncam; out float v_zcam; out vec3 v_uvl; out vec3 v_tint;
out vec4 v_mat; flat out uint v_id; out vec4 v_lpos;
void main() {
    vec3 pw = world_pos();
    vec3 nw = world_normal();
    vec3 pc = Rwc * pw + twc;
    float n = nf.x, f = nf.y;
    gl_Position = vec4(proj.x * pc.x + proj.y * pc.z, -proj.z * pc.y + proj.w * pc.z,
                       (pc.z * (f + n) - 2.0 * f * n) / (f - n), pc.z);
    v_world = pw; v_nworld = nw; v_ncam = Rwc * nw; v_zcam = pc.z;
    vec2 uv = in_uv;
    if (i_mat.x > 0.0) uv *= vec2(dot(in_mu, i_size), dot(in_mv, i_size)) / i_mat.x;
    v_uvl = vec3(uv, in_istop > 0.5 ? i_layers.y : i_layers.x);
    v_tint = i_tint; v_mat = i_mat; v_id = uint(i_id + 0.5);
    v_lpos = light_vp * vec4(pw, 1.0);
}
"""

_VARYINGS_IN = """
in vec3 v_world; in vec3 v_nworld; in vec3 v_ncam; in float v_zcam; in vec3 v_uvl; in vec3 v_tint;
in vec4 v_mat; flat in uint v_id; in vec4 v_lpos;
"""
# the G-buffer's values of a fragment: instance id, camera-frame z, camera-frame normal
_GBUF_WRITE = """
void write_gbuffer() {
    f_id = v_id; f_depth = v_zcam;
    vec3 n = normalize(v_ncam);
    if (!gl_FrontFacing) n = -n;
    f_normal = vec4(n * 0.5 + 0.5, 1.0);
}
"""
GBUF_FS = """
#version 330
""" + _VARYINGS_IN + """
layout(location = 0) out uint f_id;
layout(location = 1) out float f_depth;
layout(location = 2) out vec4 f_normal;
""" + _GBUF_WRITE + """
void main() { write_gbuffer(); }
"""

_COLOR_FS_BODY = _VARYINGS_IN + """
uniform sampler2DArray tex; uniform sampler2DShadow shadow_map; uniform int use_shadow;
uniform vec3 cam_pos; uniform vec3 ambient; uniform float falloff;
#define N_FILL 3
uniform vec3 light_pos[4]; uniform vec3 light_col[4];
float shadow_factor(vec3 n, vec3 l) {
    if (use_shadow == 0) return 1.0;
    vec3 p = v_lpos.xyz / v_lpos.w * 0.5 + 0.5;
    if (p.x < 0.0 || p.x > 1.0 || p.y < 0.0 || p.y > 1.0 || p.z > 1.0) return 1.0;
    float bias = 0.0006 + 0.002 * (1.0 - max(dot(n, l), 0.0));
    float s = texture(shadow_map, vec3(p.xy, p.z - bias));  // bilinear PCF (2 x 2 compare)
    return 0.15 + 0.85 * s;
}
vec4 shade() {
    vec3 albedo = texture(tex, v_uvl).rgb * v_tint;
    vec3 n = normalize(v_nworld);
    if (!gl_FrontFacing) n = -n;
    vec3 v = normalize(cam_pos - v_world);
    vec3 col = albedo * ambient * (0.8 + 0.2 * n.z);
    // key light: Lambert + Blinn-Phong, shadowed
    {
        vec3 l = light_pos[0] - v_world;
        float d = length(l); l /= d;
        float att = 1.0 / (1.0 + (d / falloff) * (d / falloff));
        float ndl = max(dot(n, l), 0.0);
        float sh = shadow_factor(n, l);
        vec3 h = normalize(l + v);
        float spec = ndl > 0.0 ? v_mat.y * pow(max(dot(n, h), 0.0), v_mat.z) : 0.0;
        col += light_col[0] * att * sh * (albedo * ndl + spec);
    }
    // fill lights: Lambert only (fixed count; unused ones have zero colour)
    for (int i = 1; i < N_FILL + 1; ++i) {
        vec3 l = light_pos[i] - v_world;
        float d2 = dot(l, l);
        float ndl = max(dot(n, l), 0.0) * inversesqrt(d2);
        col += light_col[i] * (albedo * ndl / (1.0 + d2 / (falloff * falloff)));
    }
    col += albedo * v_mat.w;
    return vec4(clamp(col, 0.0, 1.0), 1.0);
}
"""
COLOR_FS = """
#version 330
""" + _COLOR_FS_BODY + """
out vec4 f_color;
void main() { f_color = shade(); }
"""
# the colour pass writing the G-buffer too (no MSAA): each visible pixel shaded once, depth from a pre-pass
COLOR_GBUF_FS = """
#version 330
""" + _COLOR_FS_BODY + """
layout(location = 0) out vec4 f_color;
layout(location = 1) out uint f_id;
layout(location = 2) out float f_depth;
layout(location = 3) out vec4 f_normal;
""" + _GBUF_WRITE + """
void main() { f_color = shade(); write_gbuffer(); }
"""


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    if abs(np.dot(f, up)) > 0.99:
        up = np.array([0.0, 1.0, 0.0])
    s = np.cross(f, up); s /= np.linalg.norm(s)
    u = np.cross(s, f)
    M = np.eye(4)
    M[0, :3], M[1, :3], M[2, :3] = s, u, -f
    M[:3, 3] = -M[:3, :3] @ eye
    return M


def perspective(fovy, aspect, near, far) -> np.ndarray:
    f = 1 / math.tan(fovy / 2)
    return np.array([[f / aspect, 0, 0, 0], [0, f, 0, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)], [0, 0, -1, 0]])


def frustum_slack(scene: Scene, cam) -> np.ndarray:
    """Per object, how far (metres) its bounding sphere lies outside the camera's view frustum:
    <= 0 where it reaches into the view (it may be seen), > 0 where it cannot be seen."""
    c = np.array([o.center for o in scene.objects], np.float64)
    rad = 0.5 * np.linalg.norm(np.array([o.size for o in scene.objects], np.float64), axis=1)
    pc = cam.to_cam(c)
    K = cam.K
    out = -pc[:, 2] - rad   # behind the camera
    for a, axis, sign in (((cam.width - K[0, 2]) / K[0, 0], 0, 1), (K[0, 2] / K[0, 0], 0, -1),
                          ((cam.height - K[1, 2]) / K[1, 1], 1, 1), (K[1, 2] / K[1, 1], 1, -1)):
        d = (sign * pc[:, axis] - a * pc[:, 2]) / np.sqrt(1 + a * a)
        out = np.maximum(out, d - rad)
    return out


#: objects whose bounding sphere comes within this many metres of the view frustum cast shadows
#: (farther ones can neither be seen nor shadow what is seen, given the key light sits above the
#: camera's corridor); only those reaching into the frustum are drawn by the camera's passes
SHADOW_MARGIN_M = 1.5


def instance_array(scene: Scene, bank: TextureBank, cam=None) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Per-instance attributes (N, 17) float32 for boxes and cylinders (two arrays) of the objects
    within SHADOW_MARGIN_M of the view frustum of `cam`, those that reach into it first, and how
    many of each array reach into it (what the camera's passes draw; the shadow pass draws all)."""
    cam = cam if cam is not None else scene.camera
    slack = frustum_slack(scene, cam).tolist()
    rows = ([], []), ([], [])   # (in view, shadow casters only) per shape
    for i, o in enumerate(scene.objects):
        if slack[i] > SHADOW_MARGIN_M or o.shape == "none":
            continue
        m = bank.materials[o.material]
        side = m.side[i % len(m.side)]
        top = m.top[i % len(m.top)]
        row = (*o.center, *o.size, o.yaw, *o.tint, side, top, m.uv_tile, m.specular, m.shininess, m.emissive, i + 1)
        rows[o.shape == "cylinder"][slack[i] > 0.0].append(row)
    arrays = [np.array(seen + rest, np.float32).reshape(-1, 17) for seen, rest in rows]
    return arrays[0], arrays[1], [len(seen) for seen, _ in rows]


class GLRenderer:
    """moderngl + EGL renderer. One instance per process (owns a GL context)."""

    def __init__(self, bank: TextureBank, width: int, height: int, msaa: int = 4, shadow_size: int = 512,
                 backend: str | None = "egl"):
        import moderngl

        self.moderngl = moderngl
        kw = {"backend": backend} if backend else {}
        self.ctx = ctx = moderngl.create_standalone_context(**kw)
        self.W, self.H = width, height
        self.bank = bank
        layers = bank.array()
        rgba = np.concatenate([layers, np.full(layers.shape[:3] + (1,), 255, np.uint8)], axis=-1)
        self.tex = ctx.texture_array((layers.shape[2], layers.shape[1], layers.shape[0]), 4, rgba.tobytes())
        self.tex.build_mipmaps()
        self.tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self.tex.repeat_x = self.tex.repeat_y = True
        self.shadow_prog = ctx.program(vertex_shader=SHADOW_VS, fragment_shader=SHADOW_FS)
        # the depth pre-pass: the camera passes' own vertex shader, so its depth is the one they test against
        self.depth_prog = ctx.program(vertex_shader=CAM_VS, fragment_shader=SHADOW_FS)
        self.meshes = []
        for verts, idx in (cube_mesh(), cylinder_mesh()):
            self.meshes.append((ctx.buffer(verts.tobytes()), ctx.buffer(idx.tobytes()), len(idx)))
        self.capacity = 8192
        self.inst_bufs = [ctx.buffer(reserve=self.capacity * 17 * 4) for _ in self.meshes]
        self._vao_cache = {}
        # shadow map
        self.shadow_size = shadow_size
        self.shadow_tex = ctx.depth_texture((shadow_size, shadow_size))
        self.shadow_tex.compare_func = "<="
        self.shadow_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.shadow_fbo = ctx.framebuffer(depth_attachment=self.shadow_tex)
        # G-buffer (exact, no AA)
        self.id_tex = ctx.texture((width, height), 1, dtype="u4")
        self.z_tex = ctx.texture((width, height), 1, dtype="f4")
        self.n_tex = ctx.texture((width, height), 4, dtype="f1")
        for t in (self.id_tex, self.z_tex, self.n_tex):
            t.filter = (moderngl.NEAREST, moderngl.NEAREST)
        gdepth = ctx.depth_renderbuffer((width, height))
        self.gbuf_fbo = ctx.framebuffer(color_attachments=[self.id_tex, self.z_tex, self.n_tex], depth_attachment=gdepth)
        # colour (MSAA + resolve)
        self.msaa = msaa if msaa and msaa > 1 else 0
        color_rb = ctx.renderbuffer((width, height), 4)
        self.color_out = ctx.framebuffer(color_attachments=[color_rb],
                                         depth_attachment=gdepth if not self.msaa else ctx.depth_renderbuffer((width, height)))
        if not self.msaa:
            # without MSAA: a depth pre-pass, then colour and G-buffer written by one pass that
            # shades each pixel once (its nearest surface), sharing the G-buffer's depth
            self.merged_prog = ctx.program(vertex_shader=CAM_VS, fragment_shader=COLOR_GBUF_FS)
            self.prepass_fbo = ctx.framebuffer(depth_attachment=gdepth)
            self.merged_fbo = ctx.framebuffer(color_attachments=[color_rb, self.id_tex, self.z_tex, self.n_tex],
                                              depth_attachment=gdepth)
            self.color_ms = self.color_out
        else:
            self.gbuf_prog = ctx.program(vertex_shader=CAM_VS, fragment_shader=GBUF_FS)
            self.color_prog = ctx.program(vertex_shader=CAM_VS, fragment_shader=COLOR_FS)
            self.color_ms = ctx.framebuffer(
                color_attachments=[ctx.renderbuffer((width, height), 4, samples=self.msaa)],
                depth_attachment=ctx.depth_renderbuffer((width, height), samples=self.msaa))

    def _vaos(self, prog):
        """One VAO per mesh for `prog` (cached); attributes the program does not use are skipped."""
        key = id(prog)
        if key in self._vao_cache:
            return self._vao_cache[key]
        names_v = [("in_pos", "3f"), ("in_normal", "3f"), ("in_uv", "2f"), ("in_mu", "3f"), ("in_mv", "3f"), ("in_istop", "1f")]
        names_i = [("i_center", "3f"), ("i_size", "3f"), ("i_yaw", "1f"), ("i_tint", "3f"), ("i_layers", "2f"),
                   ("i_mat", "4f"), ("i_id", "1f")]
        fv = " ".join(f if nm in prog else _skip(f) for nm, f in names_v)
        fi = " ".join(f if nm in prog else _skip(f) for nm, f in names_i) + "/i"
        vaos = []
        for (vbo, ibo, _n), ibuf in zip(self.meshes, self.inst_bufs):
            vaos.append(self.ctx.vertex_array(prog, [(vbo, fv, *[nm for nm, _ in names_v if nm in prog]),
                                                     (ibuf, fi, *[nm for nm, _ in names_i if nm in prog])],
                                              index_buffer=ibo))
        self._vao_cache[key] = vaos
        return vaos

    def _draw(self, prog, counts):
        for vao, n in zip(self._vaos(prog), counts):
            if n:
                vao.render(self.moderngl.TRIANGLES, instances=n)

    def render(self, scene: Scene, camera=None, region=None) -> RenderOutput:
        """Render `scene` through `camera` (default: scene.camera; a padded camera is used when
        the image is distorted afterwards). `region` = (x0, y0, x1, y1), image pixels (rows top
        down, x1 and y1 exclusive): only that part is drawn and returned, each of its pixels
        exactly as in the whole frame (a scissor, not another camera), at a fraction of the cost;
        None: the whole frame. Ambient occlusion looks at the whole frame, so a scene with it
        is drawn whole and then cut to the region."""
        cam = camera if camera is not None else scene.camera
        if (cam.width, cam.height) != (self.W, self.H):
            raise ValueError(f"renderer is {self.W}x{self.H}, camera is {cam.width}x{cam.height}")
        x0, y0, x1, y1 = (0, 0, self.W, self.H) if region is None else (int(v) for v in region)
        if not (0 <= x0 < x1 <= self.W and 0 <= y0 < y1 <= self.H):
            raise ValueError(f"region {region} is not inside the {self.W}x{self.H} render")
        with self.ctx:   # this renderer's GL context current (another renderer may have been made since)
            return self._render(scene, cam, (x0, y0, x1, y1))

    def _render(self, scene: Scene, cam, region: tuple[int, int, int, int]) -> RenderOutput:
        ctx, mgl = self.ctx, self.moderngl
        x0, y0, x1, y1 = region
        drawn = (0, 0, self.W, self.H) if scene.occlusion > 0 else (x0, y0, x1, y1)
        gl_box = (drawn[0], self.H - drawn[3], drawn[2] - drawn[0], drawn[3] - drawn[1])   # GL rows bottom up
        merged = not self.msaa
        fbos = (self.gbuf_fbo, self.color_ms, self.color_out) + ((self.prepass_fbo, self.merged_fbo) if merged else ())
        for fbo in fbos:
            fbo.scissor = gl_box
        boxes, cyls, in_view = instance_array(scene, self.bank, cam)
        if max(len(boxes), len(cyls)) > self.capacity:
            raise ValueError(f"scene has {len(boxes)} solids, renderer capacity is {self.capacity}")
        counts = []
        for arr, buf in zip((boxes, cyls), self.inst_bufs):
            if len(arr):
                buf.write(arr.tobytes())
            counts.append(len(arr))
        # light setup
        lights = scene.lights[:MAX_LIGHTS]
        key = np.array(lights[0].position, np.float64)
        target = np.array([0.0, 0.0, scene.shelves[len(scene.shelves) // 2].board_top])
        dist = float(np.linalg.norm(target - key))
        light_vp = (perspective(math.radians(100), 1.0, max(0.1, dist * 0.05), dist * 4 + 30) @ look_at(key, target))
        light_vp32 = light_vp.T.astype(np.float32).tobytes()
        ctx.enable(mgl.DEPTH_TEST)
        ctx.disable(mgl.CULL_FACE)
        use_shadow = int(scene.shadows)
        # 1) shadow map
        if use_shadow:
            self.shadow_fbo.use()
            self.shadow_fbo.clear(depth=1.0)
            self.shadow_prog["light_vp"].write(light_vp32)
            self._draw(self.shadow_prog, counts)
        # camera uniforms
        K = cam.K
        proj = (2 * K[0, 0] / self.W, 2 * K[0, 2] / self.W - 1, 2 * K[1, 1] / self.H, 1 - 2 * K[1, 2] / self.H)
        Rwc = cam.R.astype(np.float32)
        progs = (self.depth_prog, self.merged_prog) if merged else (self.gbuf_prog, self.color_prog, self.depth_prog)
        for prog in progs:
            prog["Rwc"].write(Rwc.T.tobytes())  # GLSL mat3 is column-major
            prog["twc"].value = tuple(float(v) for v in cam.t)
            prog["proj"].value = tuple(float(v) for v in proj)
            prog["nf"].value = (NEAR, FAR)
            if "light_vp" in prog._members:
                prog["light_vp"].write(light_vp32)
        # 2) G-buffer: with MSAA a pass of its own (exact, not anti-aliased); without, its depth
        # only (the pass below writes ids, depth and normals beside the colour)
        self.gbuf_fbo.use()
        self.gbuf_fbo.clear(0, 0, 0, 0, depth=1.0)
        if merged:
            self.prepass_fbo.use()
            self._draw(self.depth_prog, in_view)
        else:
            self._draw(self.gbuf_prog, in_view)
        # 3) colour
        p = self.merged_prog if merged else self.color_prog
        _set(p, "tex", 0)
        _set(p, "shadow_map", 1)
        _set(p, "use_shadow", use_shadow)
        _set(p, "cam_pos", tuple(float(v) for v in cam.center))
        amb = scene.ambient
        _set(p, "ambient", tuple(float(amb * c) for c in scene.ambient_color))
        _set(p, "falloff", float(scene.light_falloff))
        pos = np.zeros((MAX_LIGHTS, 3), np.float32)
        col = np.zeros((MAX_LIGHTS, 3), np.float32)
        for i, l in enumerate(lights):
            pos[i] = l.position
            col[i] = np.array(l.color) * l.intensity
        _set(p, "light_pos", data=pos.tobytes())
        _set(p, "light_col", data=col.tobytes())
        self.tex.use(0)
        self.shadow_tex.use(1)
        # The colour pass tests against finished depth and does not write it: each pixel is shaded
        # once, by its nearest surface (the last drawn of equal ones, as "<=" with writes gives).
        # Without MSAA that depth is the G-buffer's (shared): it must survive the colour clear.
        if self.msaa:  # depth pre-pass into the multisampled buffer
            self.color_ms.depth_mask = True
            self.color_ms.use()
            self.color_ms.clear(0.1, 0.1, 0.11, 1.0, depth=1.0)
            self._draw(self.depth_prog, in_view)
        self.color_ms.depth_mask = False   # (glClear leaves a masked depth buffer alone)
        self.color_ms.use()
        if merged:
            self.color_ms.clear(0.1, 0.1, 0.11, 1.0)
            self.merged_fbo.depth_mask = False
            self.merged_fbo.use()
        ctx.depth_func = "<="
        self._draw(p, in_view)
        ctx.depth_func = "<"
        if self.msaa:
            ctx.copy_framebuffer(self.color_out, self.color_ms)
        # read back the drawn part (GL rows are bottom-up)
        W, H = gl_box[2:]
        rgb = np.frombuffer(self.color_out.read(viewport=gl_box, components=3, alignment=1), np.uint8)
        ids = np.frombuffer(self.gbuf_fbo.read(viewport=gl_box, components=1, attachment=0, alignment=1, dtype="u4"), np.uint32)
        z = np.frombuffer(self.gbuf_fbo.read(viewport=gl_box, components=1, attachment=1, alignment=1, dtype="f4"), np.float32)
        nrm = np.frombuffer(self.gbuf_fbo.read(viewport=gl_box, components=4, attachment=2, alignment=1), np.uint8)
        rgb, ids, z = rgb.reshape(H, W, 3)[::-1], ids.reshape(H, W)[::-1], z.reshape(H, W)[::-1]
        nrm = nrm.reshape(H, W, 4)[::-1, :, :3]
        if scene.occlusion > 0:
            rgb = occlude(rgb, ambient_occlusion(z, nrm, K), scene.occlusion)
        cut = (slice(y0 - drawn[1], y1 - drawn[1]), slice(x0 - drawn[0], x1 - drawn[0]))
        return RenderOutput(rgb=np.ascontiguousarray(rgb[cut]), instance=np.ascontiguousarray(ids[cut]),
                            depth=np.ascontiguousarray(z[cut]), normals=np.ascontiguousarray(nrm[cut]))

    def release(self) -> None:
        self.ctx.release()


#: ambient occlusion: world radius of the sampled hemisphere (metres), samples per pixel, and the
#: side of the tile of per-pixel sample sets that the final box blur averages away
AO_RADIUS, AO_SAMPLES, AO_TILE = 0.6, 12, 4


@cache
def _ao_kernels(n: int = AO_SAMPLES, tile: int = AO_TILE) -> np.ndarray:
    """(tile, tile, n, 3) fixed sample offsets in the unit ball, one set per tile position, denser
    near the centre (so close occluders count most). A fixed seed: renders stay reproducible;
    drawn once per process (read-only)."""
    rng = np.random.default_rng(7)
    v = rng.normal(size=(tile, tile, n, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    scale = 0.1 + 0.9 * ((np.arange(n) + rng.uniform(size=(tile, tile, n))) / n) ** 2
    ker = (v * scale[..., None]).astype(np.float32)
    ker.flags.writeable = False
    return ker


def ambient_occlusion(depth: np.ndarray, normals: np.ndarray, K: np.ndarray,
                      radius: float = AO_RADIUS) -> np.ndarray:
    """Screen-space ambient occlusion from the G-buffer: (H, W) float32 in [0, 1], 1 = open.

    Per pixel, points in the hemisphere of `radius` metres around its surface point (on the side
    its normal faces) are projected into the image; a point lying behind the surface the image
    shows there is occluded, counted less the farther that surface is in front of the pixel (so a
    load 3 m in front does not darken the wall behind it). The sets of points vary over a small
    tile of pixels and a box blur of that size averages them; computed at half resolution and
    upsampled (occlusion varies slowly). Pixels that show nothing stay 1."""
    import cv2

    H, W = depth.shape
    valid = depth > 0
    h, w = -(-H // 2), -(-W // 2)
    z = np.where(valid, depth, np.float32(1e4))[::2, ::2].astype(np.float32)
    fx, fy, cx, cy = (np.float32(v) for v in (K[0, 0] / 2, K[1, 1] / 2, K[0, 2] / 2, K[1, 2] / 2))
    px = (np.arange(w, dtype=np.float32)[None, :] - cx) / fx * z                # camera-frame point
    py = (np.arange(h, dtype=np.float32)[:, None] - cy) / fy * z
    nx, ny, nz = (normals[::2, ::2, i].astype(np.float32) * np.float32(2 / 255) - 1 for i in range(3))
    face = np.sign(np.float32(1e-6) - (nx * px + ny * py + nz * z))             # turn to face the camera
    nx, ny, nz = nx * face, ny * face, nz * face
    ker = _ao_kernels()
    reps = (-(-h // AO_TILE), -(-w // AO_TILE))
    occ = np.zeros((h, w), np.float32)
    bias = np.float32(0.02 * radius) + np.float32(0.005) * z                    # + rounding on grazing planes
    zf = z.ravel()
    for k in range(ker.shape[2]):
        sx, sy, sz = (np.tile(ker[:, :, k, i], reps)[:h, :w] for i in range(3))
        side = np.float32(radius) * np.sign(sx * nx + sy * ny + sz * nz + np.float32(1e-6))  # the normal's side
        qx, qy, qz = px + side * sx, py + side * sy, np.maximum(z + side * sz, np.float32(1e-3))
        us = np.clip(np.rint(fx * qx / qz + cx), 0, w - 1).astype(np.int32)
        vs = np.clip(np.rint(fy * qy / qz + cy), 0, h - 1).astype(np.int32)
        zs = np.take(zf, vs * w + us)
        closer = np.minimum(np.float32(2 * radius) / np.maximum(np.abs(z - zs), np.float32(1e-6)), 1)  # range check
        occ += (zs < qz - bias) * closer
    ao = 1 - occ / ker.shape[2]
    ao = cv2.blur(ao, (AO_TILE, AO_TILE), borderType=cv2.BORDER_REPLICATE)    # the sample sets average out
    ao = cv2.resize(ao, (W, H), interpolation=cv2.INTER_LINEAR)
    return np.where(valid, np.clip(ao, 0, 1), 1).astype(np.float32)


def occlude(rgb: np.ndarray, ao: np.ndarray, strength: float) -> np.ndarray:
    """The image darkened by ambient occlusion `ao` at `strength`: each pixel times ao ** strength
    (0 none, 1 as computed, > 1 deeper recesses darker still, as in a dim warehouse)."""
    f = ao ** float(strength)
    return np.clip(rgb.astype(np.float32) * f[..., None] + 0.5, 0, 255).astype(np.uint8)


def _set(prog, name: str, value=None, data: bytes | None = None) -> None:
    """Set a uniform if the (compiled) program still has it."""
    if name in prog._members:
        if data is not None:
            prog[name].write(data)
        else:
            prog[name].value = value


def _skip(fmt: str) -> str:
    """Format of an attribute the program does not use: skip its bytes."""
    n = int(fmt[0])
    return f"{4 * n}x"


def make_renderer(bank: TextureBank, width: int, height: int, msaa: int = 4, backend: str = "gl") -> Renderer:
    """The renderer factory: 'gl' (moderngl/EGL). Another backend plugs in here."""
    if backend == "gl":
        return GLRenderer(bank, width, height, msaa=msaa)
    raise ValueError(f"unknown renderer backend {backend!r} (available: gl)")
