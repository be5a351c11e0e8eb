"""Ray-cast renderer of the mock station: colour + depth with a realistic RGB-D error model.

Uses open3d's ``RaycastingScene`` (BVH ray casting on the CPU). The scene is the table (top at
z = 0), a floor and a back wall, seeded clutter boxes outside the workspace, both arms and the
object. Depth is z in the camera optical frame (x right, y down, z forward), quantised to
uint16 millimetres (``depth_scale`` = 0.001) with noise ~ z^2, dropouts at depth edges and
grazing angles and flying pixels. Everything per pixel is vectorised numpy.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from drivers.config import Pose
from drivers.types import CameraIntrinsics

INVALID_ID = int(o3d.t.geometry.RaycastingScene.INVALID_ID)
DEPTH_SCALE = 0.001  # m per depth unit
MIN_RANGE, MAX_RANGE = 0.15, 6.0  # m, the sensor's valid depth range
TABLE_COLOR = (176, 140, 98)
FLOOR_COLOR = (90, 90, 96)
WALL_COLOR = (214, 210, 200)
ARM_COLOR = (228, 228, 224)
# Box (x_min, x_max, y_min, y_max, z_min, z_max) that clutter never enters: the arms' working volume.
WORKSPACE = (-0.3, 1.0, -0.85, 0.85, -0.1, 1.3)
MOCK_CAMERA_EYE = (1.35, 0.0, 0.75)
MOCK_CAMERA_TARGET = (0.45, 0.0, 0.2)

Mesh = tuple[np.ndarray, np.ndarray]  # vertices (V, 3) float64 m, triangles (F, 3) int32


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> Pose:
    """Camera optical frame (x right, y down, z forward) at ``eye`` looking at ``target``, world frame."""
    eye_a, target_a, up_a = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target_a - eye_a
    z /= np.linalg.norm(z)
    x = np.cross(z, up_a)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye_a
    return Pose.from_matrix(T)


def mock_camera_pose() -> Pose:
    """The mock camera's pose: in front of the table at (1.35, 0, 0.75) m looking at (0.45, 0, 0.2) m."""
    return look_at(MOCK_CAMERA_EYE, MOCK_CAMERA_TARGET)


# ---------------------------------------------------------------- meshes
def box_mesh(centre: Sequence[float], half: Sequence[float], yaw: float = 0.0) -> Mesh:
    """A box with half extents ``half`` (m) rotated by ``yaw`` (rad) about z, centred at ``centre``."""
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    tri = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
        dtype=np.int32,
    )
    c, s_ = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    return (s * np.asarray(half)) @ R.T + np.asarray(centre, dtype=np.float64), tri


def merge_meshes(meshes: Sequence[Mesh]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One triangle soup from several meshes: vertices (V, 3), triangles (F, 3), source index (F,) per triangle."""
    verts, tris, src, offset = [], [], [], 0
    for k, (v, f) in enumerate(meshes):
        verts.append(v)
        tris.append(np.asarray(f, dtype=np.int32) + offset)
        src.append(np.full(len(f), k, dtype=np.int32))
        offset += len(v)
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(src)


def tube_mesh(points: np.ndarray, radius: float, sides: int = 10) -> Mesh:
    """A closed tube of ``radius`` m around the polyline ``points`` (n, 3), with end caps."""
    n = len(points)
    t = np.gradient(points, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    ref = np.where(np.abs(t[:, 2:3]) > 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]))
    a = np.cross(t, ref)
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    b = np.cross(t, a)
    ang = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = radius * (np.cos(ang)[None, :, None] * a[:, None, :] + np.sin(ang)[None, :, None] * b[:, None, :])
    verts = (points[:, None, :] + ring).reshape(-1, 3)
    k, s = np.meshgrid(np.arange(n - 1), np.arange(sides), indexing="ij")
    v00, v01 = k * sides + s, k * sides + (s + 1) % sides
    v10, v11 = v00 + sides, v01 + sides
    side = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)])
    c0, c1 = n * sides, n * sides + 1
    s1 = np.arange(sides)
    caps = np.concatenate(
        [
            np.stack([np.full(sides, c0), (s1 + 1) % sides, s1], -1),
            np.stack([np.full(sides, c1), (n - 1) * sides + s1, (n - 1) * sides + (s1 + 1) % sides], -1),
        ]
    )
    verts = np.concatenate([verts, points[[0, -1]]])
    return verts, np.concatenate([side, caps]).astype(np.int32)


def sheet_mesh(grid: np.ndarray, half_thickness: float) -> Mesh:
    """A closed sheet of thickness 2 * ``half_thickness`` m around the mid-surface ``grid`` (rows, cols, 3)."""
    rows, cols, _ = grid.shape
    du = np.gradient(grid, axis=1)
    dv = np.gradient(grid, axis=0)
    nrm = np.cross(du, dv)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=2, keepdims=True), 1e-12)
    top = (grid + half_thickness * nrm).reshape(-1, 3)
    bottom = (grid - half_thickness * nrm).reshape(-1, 3)
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    face_top = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)])
    m = rows * cols
    face_bottom = face_top[:, ::-1] + m
    loop = np.concatenate([idx[0, :], idx[1:, -1], idx[-1, -2::-1], idx[-2:0:-1, 0]])
    nxt = np.roll(loop, -1)
    rim = np.concatenate([np.stack([loop, nxt, nxt + m], -1), np.stack([loop, nxt + m, loop + m], -1)])
    return np.concatenate([top, bottom]), np.concatenate([face_top, face_bottom, rim]).astype(np.int32)


def static_scene(clutter: int, seed: int) -> tuple[list[Mesh], list[tuple[int, int, int]]]:
    """Table, floor, back wall and ``clutter`` seeded boxes outside the workspace, with their colours."""
    rng = np.random.default_rng(seed)
    meshes = [
        box_mesh((0.0, 0.0, -0.02), (1.0, 1.4, 0.02)),  # table, top at z = 0
        box_mesh((0.0, 0.0, -0.76), (4.0, 4.0, 0.01)),  # floor
        box_mesh((-1.6, 0.0, 0.5), (0.02, 4.0, 1.3)),  # back wall
    ]
    colours = [TABLE_COLOR, FLOOR_COLOR, WALL_COLOR]
    placed = 0
    while placed < clutter:
        half = rng.uniform([0.03, 0.03, 0.03], [0.15, 0.15, 0.2])
        if rng.random() < 0.6:  # behind the arms
            cx, cy = rng.uniform(-0.95, -0.35), rng.uniform(-1.25, 1.25)
        else:  # beside the workspace
            cx, cy = rng.uniform(-0.2, 0.9), rng.choice([-1.0, 1.0]) * rng.uniform(0.9, 1.3)
        r = float(np.hypot(half[0], half[1]))  # footprint radius for any yaw
        x0, x1, y0, y1, _, _ = WORKSPACE
        if x0 - r < cx < x1 + r and y0 - r < cy < y1 + r:
            continue  # would reach into the workspace
        if not (-1.0 + r < cx < 1.0 - r and -1.4 + r < cy < 1.4 - r):
            continue  # keep it on the table
        meshes.append(box_mesh((cx, cy, half[2]), half, float(rng.uniform(0, np.pi))))
        colours.append(tuple(int(c) for c in rng.integers(30, 230, 3)))
        placed += 1
    return meshes, colours


# ---------------------------------------------------------------- rendering
def _tensors(vertices: np.ndarray, triangles: np.ndarray) -> tuple[o3d.core.Tensor, o3d.core.Tensor]:
    """open3d tensors (float32 vertices, uint32 triangles) for ``RaycastingScene.add_triangles``."""
    return (
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
    )


@dataclass(frozen=True)
class RenderOutput:
    """One rendered view.

    color: (H, W, 3) uint8 RGB. depth: (H, W) uint16 mm (0 = no data), with the error model.
    depth_true: (H, W) float32 m, exact z (0 = no hit). mask: (H, W) bool object pixels, or None.
    """

    color: np.ndarray
    depth: np.ndarray
    depth_true: np.ndarray
    mask: np.ndarray | None


class SceneRenderer:
    """Renders the station from one camera: static scene built once, arms and object given per frame.

    intrinsics: the camera's pinhole model; T_world_cam: (4, 4) world <- optical frame.
    """

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        T_world_cam: np.ndarray,
        *,
        depth_noise: float = 0.0015,
        edge_dropout: float = 0.5,
        flying_pixels: float = 0.001,
        clutter: int = 6,
        seed: int = 0,
        object_color: Sequence[int] = (205, 70, 40),
    ) -> None:
        self.intrinsics = intrinsics
        self.T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        self.depth_noise = float(depth_noise)
        self.edge_dropout = float(edge_dropout)
        self.flying_pixels = float(flying_pixels)
        self.seed = int(seed)
        self.object_color = np.asarray(object_color, dtype=np.float32)
        meshes, colours = static_scene(clutter, seed)
        v, f, src = merge_meshes(meshes)
        self._static = _tensors(v, f)
        self._static_colour = np.asarray(colours, dtype=np.float32)[src]  # (F, 3) per triangle
        K = intrinsics
        u, vv = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
        d_cam = np.stack([(u - K.cx) / K.fx, (vv - K.cy) / K.fy, np.ones_like(u)], axis=-1)  # z = 1
        R, t = self.T_world_cam[:3, :3], self.T_world_cam[:3, 3]
        d_world = d_cam @ R.T
        self._dir = d_world.reshape(-1, 3).astype(np.float32)
        self._unit = (d_world / np.linalg.norm(d_world, axis=-1, keepdims=True)).reshape(-1, 3).astype(np.float32)
        rays = np.concatenate([np.broadcast_to(t, self._dir.shape).astype(np.float32), self._dir], axis=1)
        self._rays = o3d.core.Tensor(np.ascontiguousarray(rays))
        self._origin = t.astype(np.float32)
        self._light = np.array([0.35, 0.25, 1.0], dtype=np.float32)
        self._light /= np.linalg.norm(self._light)
        # Table texture per pixel, precomputed (camera and table are static): where each ray meets z = 0.
        self._n_table_triangles = 12
        with np.errstate(divide="ignore", invalid="ignore"):
            s_plane = -t[2] / d_world[..., 2]
        p = t + d_world * s_plane[..., None]
        grain = 0.92 + 0.08 * np.sin(55.0 * p[..., 0] + 4.0 * np.sin(9.0 * p[..., 1])) * np.cos(3.0 * p[..., 1])
        self._table_grain = np.nan_to_num(grain, nan=1.0).reshape(-1).astype(np.float32)
        # Pools of sensor noise, shifted randomly per frame: drawing fresh normals costs ~15 ms a frame.
        pool_rng = np.random.default_rng([self.seed, 2**31 - 1])
        self._colour_noise = pool_rng.normal(0.0, 2.0, (3, K.height, K.width, 3)).astype(np.float32)
        self._depth_noise = pool_rng.standard_normal((3, K.height, K.width)).astype(np.float32)

    def render(
        self,
        arms: Sequence[Mesh],
        obj: Mesh | None,
        *,
        frame_index: int = 0,
        with_mask: bool = False,
    ) -> RenderOutput:
        """Ray-cast one frame; ``frame_index`` seeds this frame's noise (same index, same image)."""
        H, W = self.intrinsics.height, self.intrinsics.width
        rng = np.random.default_rng([self.seed, int(frame_index)])
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(*self._static)  # geometry id 0
        palette = [self._static_colour]
        if arms:  # both arms as one geometry
            av, af, _ = merge_meshes(arms)
            scene.add_triangles(*_tensors(av, af))
            palette.append(np.broadcast_to(np.float32(ARM_COLOR), (len(af), 3)))
        obj_geom = -1
        if obj is not None:
            obj_geom = scene.add_triangles(*_tensors(*obj))
            palette.append(np.broadcast_to(self.object_color, (len(obj[1]), 3)))
        palette.append(np.zeros((1, 3), np.float32))  # misses
        offsets = np.cumsum([0] + [len(c) for c in palette[:-1]])
        hit = scene.cast_rays(self._rays, nthreads=0)
        t_hit = hit["t_hit"].numpy()
        geom = hit["geometry_ids"].numpy().astype(np.int64)
        normal = hit["primitive_normals"].numpy()
        valid = geom != INVALID_ID
        z = np.where(valid, t_hit, np.float32(0.0))  # ray directions have unit camera-z: t_hit is z

        # ---- colour: per-triangle albedo, table texture, two-sided Lambert + headlight, sensor noise.
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        tri = np.where(valid, prim + offsets[np.minimum(geom, len(offsets) - 1)], offsets[-1])
        albedo = np.take(np.concatenate(palette), tri, axis=0)
        cos_view = np.abs(np.einsum("ij,ij->i", normal, self._unit))
        shade = np.float32(0.35) + np.float32(0.45) * np.abs(normal @ self._light) + np.float32(0.25) * cos_view
        shade *= np.where(tri < self._n_table_triangles, self._table_grain, np.float32(1.0))
        color = albedo * shade[:, None]
        noise = self._noise(rng, self._colour_noise)
        color = np.clip(color.reshape(H, W, 3) + noise, 0, 255).astype(np.uint8)

        # ---- depth error model.
        z_true = z.reshape(H, W)
        zp = np.pad(z_true, 1, mode="edge")
        z_min = np.minimum(np.minimum(zp[:-2, 1:-1], zp[2:, 1:-1]), np.minimum(zp[1:-1, :-2], zp[1:-1, 2:]))
        z_max = np.maximum(np.maximum(zp[:-2, 1:-1], zp[2:, 1:-1]), np.maximum(zp[1:-1, :-2], zp[1:-1, 2:]))
        jump = np.maximum(z_max - z_true, z_true - z_min)
        edge = (jump > np.maximum(np.float32(0.015), np.float32(0.03) * z_true)) & (z_true > 0)
        grazing = (cos_view.reshape(H, W) < 0.1) & (z_true > 0)
        zn = z_true.copy()
        lost = np.zeros((H, W), dtype=bool)
        ey, ex = np.nonzero(edge)
        lost[ey, ex] = rng.random(len(ey)) < self.edge_dropout
        gy, gx = np.nonzero(grazing)
        lost[gy, gx] |= rng.random(len(gy)) < 0.8
        if len(ey) and self.flying_pixels > 0:
            p_fly = min(1.0, self.flying_pixels * H * W / len(ey))
            fly = (rng.random(len(ey)) < p_fly) & ~lost[ey, ex]
            fy, fx = ey[fly], ex[fly]
            lo = np.where(z_min[fy, fx] > 0, z_min[fy, fx], zn[fy, fx])
            hi = np.where(z_max[fy, fx] > 0, z_max[fy, fx], zn[fy, fx])
            zn[fy, fx] = lo + rng.random(len(fy)).astype(np.float32) * (hi - lo)
        zn += self._noise(rng, self._depth_noise) * (np.float32(self.depth_noise) * zn * zn)
        zn[lost | (zn < MIN_RANGE) | (zn > MAX_RANGE) | (z_true <= 0)] = 0.0
        depth = np.rint(zn * np.float32(1.0 / DEPTH_SCALE)).astype(np.uint16)
        mask = (geom == obj_geom).reshape(H, W) if with_mask else None
        return RenderOutput(color=color, depth=depth, depth_true=z_true, mask=mask)

    @staticmethod
    def _noise(rng: np.random.Generator, pool: np.ndarray) -> np.ndarray:
        """A fresh-looking noise field: one of the pool's fields, shifted by a random offset (cheap, seeded)."""
        k = int(rng.integers(len(pool)))
        dy, dx = (int(v) for v in rng.integers(0, pool.shape[1:3]))
        return np.roll(pool[k], (dy, dx), axis=(0, 1))
