"""Headless stereo rendering on the CPU: moderngl with an EGL standalone context (Mesa llvmpipe).

One pass draws the opaque geometry into a BGR colour target and an auxiliary float target holding
(z depth in metres along the camera's optical axis, instance id); a second pass blends glass over it (glass
shows what lies behind it and a tint/reflection) and writes the glass's instance id into a second id target, so
a window's mask covers its panes while the depth stays that of what is behind the glass.

Camera model: pinhole, OpenCV convention (pixel (u, v) = (fx x/z + cx, fy y/z + cy), integer u at a pixel's
centre), optical frame x right, y down, z forward. Image rows come back top row first.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from importlib import resources
from typing import Any

import moderngl
import numpy as np

log = logging.getLogger(__name__)

VERTEX_FLOATS = 16  # pos 3, normal 3, tint 3, layer 1, instance 1, feature uv 2, kind 1, style 1, flags 1
FLAGS_COLUMN = 15  # bit flags, not seen by the shaders:
FLAG_DETAIL = 1  # a small detailed object (furniture, fittings, railings), drawn only within DETAIL_RANGE_M
FLAG_CLOSED = 2  # part of a closed solid wound outward (counter-clockwise seen from outside): culled from behind
DETAIL_RANGE_M = 12.0
KIND_PLAIN, KIND_DOOR, KIND_WINDOW_FRAME, KIND_GLASS = 0.0, 1.0, 2.0, 3.0
MAX_LIGHTS = 4


@dataclass(frozen=True)
class CameraModel:
    """A rectified stereo pinhole camera; the right camera is the left shifted by `baseline_m` along +x (cam)."""

    width: int = 640
    height: int = 480
    fx: float = 480.0
    fy: float = 480.0
    cx: float = 319.5
    cy: float = 239.5
    baseline_m: float = 0.12
    near_m: float = 0.05
    far_m: float = 200.0

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix, pixels."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])


@dataclass
class Lighting:
    """Per-frame light: point lights in the CAD frame (metres), RGB intensities, ambient RGB, exposure gain,
    sensor noise standard deviation (fraction of full scale) and the sky colour (RGB) seen through windows."""

    positions_cad: np.ndarray  # (L, 3)
    colours: np.ndarray  # (L, 3)
    ambient: tuple[float, float, float] = (0.35, 0.35, 0.35)
    exposure: float = 1.0
    noise_sigma: float = 0.02
    sky_rgb: tuple[float, float, float] = (0.62, 0.74, 0.9)


@dataclass
class RenderOutput:
    """image_bgr: (H, W, 3) uint8; depth_m: (H, W) float32 z along the optical axis, 0 where nothing was hit;
    instance: (H, W) int32, 0 = no door/window, k = feature k-1 of the scene's feature list."""

    image_bgr: np.ndarray
    depth_m: np.ndarray | None = None
    instance: np.ndarray | None = None


@dataclass
class ChunkIndex:
    """Triangles grouped into cells of `cell_m`, so that a frame draws only the cells in view, nearest first:
    the depth test then rejects hidden fragments before shading (a whole building drawn in any order was shaded
    20-50 times per pixel on llvmpipe).

    vertices: (3T, F) sorted by cell; first/count: (C,) vertex ranges; box_min/box_max: (C, 3) cell bounds, CAD.
    """

    vertices: np.ndarray
    first: np.ndarray
    count: np.ndarray
    box_min: np.ndarray
    box_max: np.ndarray
    huge: np.ndarray  # (C,) bool: the cell of oversized triangles (the ground, long slabs), drawn last
    detail: np.ndarray  # (C,) bool: cells of small detailed objects, drawn only within DETAIL_RANGE_M
    closed: np.ndarray  # (C,) bool: cells of closed solids' triangles, drawn with back faces culled

    @classmethod
    def build(cls, vertices: np.ndarray, cell_m: float = 5.0) -> ChunkIndex:
        tri = vertices.reshape(-1, 3, vertices.shape[1])
        centre = tri[:, :, :3].mean(axis=1)
        extent = np.ptp(tri[:, :, :3], axis=1).max(axis=1)
        flags = np.rint(tri[:, 0, FLAGS_COLUMN]).astype(np.int64)
        cell = np.column_stack([np.floor(centre / cell_m).astype(np.int64), flags & (FLAG_DETAIL | FLAG_CLOSED)])
        cell[extent > 4 * cell_m, :3] = np.iinfo(np.int32).max  # huge triangles (ground, long slabs): own cell
        _, key = np.unique(cell, axis=0, return_inverse=True)
        key = key.reshape(-1)
        order = np.argsort(key, kind="stable")
        tri, key = tri[order], key[order]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        counts = np.diff(np.r_[starts, len(key)])
        pts = tri[:, :, :3]
        box_min = np.minimum.reduceat(pts.min(axis=1), starts, axis=0)
        box_max = np.maximum.reduceat(pts.max(axis=1), starts, axis=0)
        huge = np.ptp(np.stack([box_min, box_max]), axis=0).max(axis=1) > 8 * cell_m
        cell_flags = np.rint(tri[starts, 0, FLAGS_COLUMN]).astype(np.int64)
        return cls(np.ascontiguousarray(tri.reshape(-1, vertices.shape[1])), starts * 3, counts * 3, box_min, box_max,
                   huge, (cell_flags & FLAG_DETAIL) > 0, (cell_flags & FLAG_CLOSED) > 0)

    def visible_front_to_back(self, T_cad_cam: np.ndarray, camera: CameraModel,
                              z_range_m: tuple[float, float] | None = None) -> np.ndarray:
        """(K, 3) (first vertex, vertex count, closed 0/1) of the cells whose box meets the view frustum (and the
        height range `z_range_m`, when given: the storey flown), nearest first, the oversized cell last."""
        if len(self.first) == 0:
            return np.zeros((0, 3), np.int64)
        T_cam_cad = np.linalg.inv(T_cad_cam)
        corners = np.stack([np.where(np.array([(i >> k) & 1 for k in range(3)], bool), self.box_max, self.box_min)
                            for i in range(8)], axis=1)  # (C, 8, 3)
        pc = corners @ T_cam_cad[:3, :3].T + T_cam_cad[:3, 3]
        x, y, z = pc[..., 0], pc[..., 1], pc[..., 2]
        # outside when all 8 corners lie beyond one plane: behind the camera, or past a side of the image
        tx0, tx1 = -(camera.cx + 0.5) / camera.fx, (camera.width - camera.cx - 0.5) / camera.fx
        ty0, ty1 = -(camera.cy + 0.5) / camera.fy, (camera.height - camera.cy - 0.5) / camera.fy
        out = ((z < camera.near_m).all(1) | (x < tx0 * z).all(1) | (x > tx1 * z).all(1)
               | (y < ty0 * z).all(1) | (y > ty1 * z).all(1))
        if z_range_m is not None:
            out |= ~self.huge & ((self.box_max[:, 2] < z_range_m[0]) | (self.box_min[:, 2] > z_range_m[1]))
        cam = T_cad_cam[:3, 3]
        dist = np.linalg.norm(np.clip(cam, self.box_min, self.box_max) - cam, axis=1)
        out |= self.detail & (dist > DETAIL_RANGE_M)  # a few pixels each at that range: not worth their vertices
        dist = dist + 1e6 * self.huge
        idx = np.flatnonzero(~out)
        idx = idx[np.argsort(dist[idx], kind="stable")]
        return np.column_stack([self.first[idx], self.count[idx], self.closed[idx]])


def _shader(name: str) -> str:
    return resources.files("macroloc.sim").joinpath("shaders", name).read_text()


class StereoRenderer:
    """Renders the left and right images of a stereo camera from `vertices` (N, VERTEX_FLOATS) float32, a
    triangle list in the CAD frame, and `texture_layers` (L, S, S, 3) uint8 RGB tiles of 1 m."""

    def __init__(self, vertices: np.ndarray, texture_layers: np.ndarray, camera: CameraModel) -> None:
        self.camera = camera
        self.ctx = moderngl.create_standalone_context(backend="egl")  # type: ignore[arg-type]  # stubs lag
        self.prog: Any = self.ctx.program(vertex_shader=_shader("scene.vert.glsl"),
                                          fragment_shader=_shader("scene.frag.glsl"))
        verts = np.ascontiguousarray(vertices, dtype=np.float32)
        glass = verts[:, 13] == KIND_GLASS
        self.chunks = ChunkIndex.build(verts[~glass])
        self._vbos: list[Any] = []
        self._vaos = [self._vao(self.chunks.vertices), self._vao(verts[glass])]
        # depth pre-pass: positions only, no shading; the full shader then runs once per visible pixel
        self.prog_depth: Any = self.ctx.program(vertex_shader=_shader("depth.vert.glsl"),
                                           fragment_shader="#version 330\nvoid main() {}\n")
        self._vao_depth = None
        if self._vaos[0] is not None:
            self._vao_depth = self.ctx.vertex_array(self.prog_depth, [(self._vbos[0], "3f 52x", "in_pos")])
        layers, size = texture_layers.shape[0], texture_layers.shape[1]
        self.texture = self.ctx.texture_array((size, size, layers), 3, np.ascontiguousarray(texture_layers).tobytes())
        self.texture.build_mipmaps()
        self.texture.filter = (moderngl.LINEAR_MIPMAP_NEAREST, moderngl.LINEAR)
        w, h = camera.width, camera.height
        self.colour = self.ctx.texture((w, h), 4)
        self.aux = self.ctx.texture((w, h), 2, dtype="f4")
        self.glass_id = self.ctx.texture((w, h), 2, dtype="f4")
        self.depth = self.ctx.depth_texture((w, h))
        self.fbo = self.ctx.framebuffer(color_attachments=[self.colour, self.aux], depth_attachment=self.depth)
        self.fbo_glass = self.ctx.framebuffer(color_attachments=[self.colour, self.glass_id],
                                              depth_attachment=self.depth)
        self.fbo_glass_id = self.ctx.framebuffer(color_attachments=[self.glass_id])  # clears the id target alone
        self.fbo_depth = self.ctx.framebuffer(depth_attachment=self.depth)  # the depth pre-pass
        self.fbo_colour = self.ctx.framebuffer(color_attachments=[self.colour])  # clears the colour alone (sky)
        n, f = camera.near_m, camera.far_m
        proj = (2 * camera.fx / w, 2 * camera.fy / h, 2 * (camera.cx + 0.5) / w - 1, 2 * (camera.cy + 0.5) / h - 1)
        progs: list[Any] = [self.prog, self.prog_depth]
        for prog in progs:
            prog["proj"].value = proj
            prog["nearfar"].value = (n, f)
        self._set("tex", 0)  # the texture array on unit 0
        self._indirect: Any = None
        self.depth_prepass = True
        self.cull_back_faces = True
        # rows come back top first, a vertical flip of OpenGL's window: counter-clockwise in the camera's view
        # (x right, y down) is clockwise to OpenGL
        self.ctx.front_face = "cw"
        self.ctx.cull_face = "back"
        self.z_range_m: tuple[float, float] | None = None  # heights drawn (the storey flown); None: all

    def _vao(self, verts: np.ndarray):  # noqa: ANN202 - moderngl.VertexArray | None
        if len(verts) == 0:
            return None
        vbo = self.ctx.buffer(verts.tobytes())
        vao = self.ctx.vertex_array(self.prog, [(vbo, "3f 3f 3f 1f 1f 2f 1f 1f 4x",
                                                 "in_pos", "in_normal", "in_tint", "in_layer", "in_inst",
                                                 "in_fuv", "in_kind", "in_style")])
        self._vbos.append(vbo)  # kept for the depth pre-pass
        return vao

    def render(self, T_cad_cam: np.ndarray, lighting: Lighting, frame_seed: float = 0.0,
               with_truth: bool = True) -> RenderOutput:
        """One camera at pose T_cad_cam (4x4, optical frame -> CAD). Truth = depth and instance buffers."""
        with self.ctx:  # current for this call: a process may hold several renderers (EGL contexts)
            return self._render(T_cad_cam, lighting, frame_seed, with_truth)

    def _render(self, T_cad_cam: np.ndarray, lighting: Lighting, frame_seed: float,
                with_truth: bool) -> RenderOutput:
        T_cam_cad = np.linalg.inv(np.asarray(T_cad_cam, dtype=np.float64))
        self._set_uniforms(T_cam_cad, np.asarray(T_cad_cam)[:3, 3], lighting, frame_seed)
        sky = lighting.sky_rgb
        self.texture.use(0)
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)  # depth 0 and instance 0 where nothing is hit
        self.fbo_colour.clear(sky[2] * lighting.exposure, sky[1] * lighting.exposure, sky[0] * lighting.exposure,
                              1.0)  # BGR order, like the image
        self.fbo.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        self._set("glass_pass", 0)
        if self._vaos[0] is not None:
            ranges = self.chunks.visible_front_to_back(T_cad_cam, self.camera, self.z_range_m)
            if self.depth_prepass and self._vao_depth is not None:
                self.fbo_depth.use()
                self._draw_culled(ranges, self._vao_depth)
                self.fbo.use()
                self.ctx.depth_func = "<="
            self._draw_culled(ranges, self._vaos[0])
            self.ctx.depth_func = "<"
        if self._vaos[1] is not None:
            self.fbo_glass.use()
            if with_truth:
                self.fbo_glass_id.clear()
                self.fbo_glass.use()
            self.ctx.enable(moderngl.BLEND)
            self.ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
            self._set("glass_pass", 1)
            self._vaos[1].render(moderngl.TRIANGLES)
            self.ctx.disable(moderngl.BLEND)
        w, h = self.camera.width, self.camera.height
        image = np.frombuffer(self.colour.read(alignment=1), np.uint8).reshape(h, w, 4)[:, :, :3]
        if not with_truth:
            return RenderOutput(image)
        aux = np.frombuffer(self.aux.read(), np.float32).reshape(h, w, 2)
        instance = np.rint(aux[:, :, 1]).astype(np.int32)
        if self._vaos[1] is not None:
            glass = np.rint(np.frombuffer(self.glass_id.read(), np.float32).reshape(h, w, 2)[:, :, 1]).astype(np.int32)
            instance = np.where(glass > 0, glass, instance)
        return RenderOutput(image, aux[:, :, 0].copy(), instance)

    def _draw_culled(self, ranges: np.ndarray, vao) -> None:  # noqa: ANN001 - moderngl.VertexArray
        """The closed solids' cells with back faces culled (they are hidden behind the solid's own front), then
        the double-sided rest; each group nearest first."""
        closed = ranges[:, 2] > 0
        if self.cull_back_faces:
            self.ctx.enable(moderngl.CULL_FACE)
            self._draw_indirect(ranges[closed], vao)
            self.ctx.disable(moderngl.CULL_FACE)
            self._draw_indirect(ranges[~closed], vao)
        else:
            self._draw_indirect(ranges, vao)

    def _draw_indirect(self, ranges: np.ndarray, vao) -> None:  # noqa: ANN001 - moderngl.VertexArray
        """One glMultiDrawArraysIndirect call for the (first, count) vertex ranges, in their order."""
        if len(ranges) == 0:
            return
        # moderngl strides indirect commands by 5 uint32 (the indexed layout) also for arrays:
        # count, instance count, first, base instance, (unused)
        cmds = np.zeros((len(ranges), 5), np.uint32)
        cmds[:, 0], cmds[:, 1], cmds[:, 2] = ranges[:, 1], 1, ranges[:, 0]
        if self._indirect is None or self._indirect.size < cmds.nbytes:
            self._indirect = self.ctx.buffer(reserve=max(cmds.nbytes, 4096), dynamic=True)
        self._indirect.write(cmds.tobytes())
        vao.render_indirect(self._indirect, moderngl.TRIANGLES, count=len(cmds))

    def render_stereo(self, T_cad_camleft: np.ndarray, lighting: Lighting,
                      frame_seed: float = 0.0) -> tuple[RenderOutput, np.ndarray]:
        """(left with depth and instances, right BGR image); right = left shifted by the baseline along +x."""
        left = self.render(T_cad_camleft, lighting, frame_seed, with_truth=True)
        T_left_right = np.eye(4)
        T_left_right[0, 3] = self.camera.baseline_m
        right = self.render(np.asarray(T_cad_camleft) @ T_left_right, lighting, frame_seed + 0.5, with_truth=False)
        return left, right.image_bgr

    def _set_uniforms(self, T_cam_cad: np.ndarray, cam_pos: np.ndarray, lighting: Lighting, seed: float) -> None:
        self._write("T_cam_cad", T_cam_cad.T.astype(np.float32).tobytes())  # GLSL matrices are column-major
        self.prog_depth["T_cam_cad"].write(T_cam_cad.T.astype(np.float32).tobytes())
        self._set("cam_pos", tuple(float(v) for v in cam_pos))
        k = min(MAX_LIGHTS, len(lighting.positions_cad))
        pos = np.zeros((MAX_LIGHTS, 3), np.float32)
        col = np.zeros((MAX_LIGHTS, 3), np.float32)
        if k:
            order = np.argsort(np.linalg.norm(lighting.positions_cad - cam_pos, axis=1))[:k]
            pos[:k], col[:k] = lighting.positions_cad[order], lighting.colours[order]
        self._write("light_pos", pos.tobytes())
        self._write("light_col", col.tobytes())
        self._set("n_lights", k)
        self._set("ambient", tuple(float(v) for v in lighting.ambient))
        self._set("exposure", float(lighting.exposure))
        self._set("noise_sigma", float(lighting.noise_sigma))
        self._set("sky_rgb", tuple(float(v) for v in lighting.sky_rgb))
        self._set("frame_seed", float(seed % 1000.0))

    def _set(self, name: str, value: object) -> None:
        """Set a uniform of the scene shader; one the GLSL compiler optimised away is skipped."""
        if name in self.prog:
            self.prog[name].value = value

    def _write(self, name: str, data: bytes) -> None:
        if name in self.prog:
            self.prog[name].write(data)

    def release(self) -> None:
        self.ctx.release()
