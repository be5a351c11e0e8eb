"""Synthetic depth scenes for tests and benchmarks: a table, tubes (ropes), sheets (cloth), boxes (arms).

Meshes come from :mod:`tdcommon.meshes`; this module places and renders them.

Meshes are raycast with open3d into a pinhole depth image, then depth noise sigma = c * z**2 and
1 mm quantisation are added. World frame: z up, table top at z = 0. Everything is seeded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from tdcommon.meshes import Mesh, box_mesh, merge_meshes, tube_mesh
from tdcommon.transforms import look_at
from tdcommon.types import CameraIntrinsics


def intrinsics(width: int, height: int, hfov_deg: float = 69.0) -> np.ndarray:
    """Square-pixel camera matrix (3, 3) for a width x height image with horizontal FOV in degrees."""
    return CameraIntrinsics.from_fov(width, height, hfov_deg).K


def default_camera(width: int = 640, height: int = 480) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), T_world_cam (4, 4)): a camera 1.06 m in front of and above the table centre."""
    return intrinsics(width, height), look_at([0.0, -0.7, 0.8], [0.0, 0.0, 0.0])


def curve_from_curvature(
    start: np.ndarray, heading: float, kappa: np.ndarray, ds: float, z: float | np.ndarray
) -> np.ndarray:
    """Planar curve by integrating curvature kappa (M,) 1/m with step ds m from start (2,) -> (M+1, 3)."""
    theta = heading + np.concatenate([[0.0], np.cumsum(kappa * ds)])
    steps = np.stack([np.cos(theta[:-1]), np.sin(theta[:-1])], axis=1) * ds
    xy = np.asarray(start, float)[None, :] + np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
    zz = np.broadcast_to(np.asarray(z, float), (len(xy),))
    return np.column_stack([xy, zz])


def rope_centreline(phase: float, length: float = 0.6, radius: float = 0.006, n: int = 241) -> np.ndarray:
    """Inextensible wavy rope lying on the table, (n, 3) m; ``phase`` (rad) bends and drifts it."""
    s = np.linspace(0.0, length, n)
    ds = s[1] - s[0]
    kappa = 6.0 * np.sin(2 * np.pi * s[:-1] / length * 1.5 + phase)
    c = curve_from_curvature(np.zeros(2), 0.3 * np.sin(phase), kappa, ds, radius)
    c[:, :2] -= c[:, :2].mean(axis=0)
    c[:, 0] += 0.05 * np.sin(phase)
    c[:, 1] += 0.03 * np.cos(phase)
    return c


def y_rope_branches(radius: float = 0.006) -> list[np.ndarray]:
    """A Y-shaped branched rope on the table: three polylines (trunk, branch, branch) from one junction."""
    j = np.array([0.0, 0.02])
    trunk = curve_from_curvature(j, np.pi + 0.1, np.full(120, 1.5), 0.25 / 120, radius)
    b1 = curve_from_curvature(j, 0.5, np.full(100, -2.0), 0.22 / 100, radius)
    b2 = curve_from_curvature(j, -0.6, np.full(100, 2.0), 0.22 / 100, radius)
    return [trunk, b1, b2]


def cloth_surface(
    rows: int = 41, cols: int = 41, size: float = 0.3, height: float = 0.12, wave: float = 0.0
) -> np.ndarray:
    """Square cloth held above the table with a gentle sag, (rows, cols, 3) m."""
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, cols), np.linspace(-0.5, 0.5, rows))
    x, y = size * u, size * v
    z = height - 0.04 * (1 - (2 * u) ** 2) * (1 - (2 * v) ** 2) + 0.015 * np.sin(3 * u + wave)
    return np.stack([x, y, z], axis=-1)


def table_mesh(half: float = 1.5) -> Mesh:
    """The table top z = 0 as two triangles, +-half m."""
    V = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
    return V, np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def render_depth(
    meshes: list[Mesh],
    K: np.ndarray,
    T_world_cam: np.ndarray,
    shape: tuple[int, int],
    noise_coeff: float = 0.0008,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Depth image (H, W) float32, metres (0 = no hit) of the meshes, with noise c*z^2 and 1 mm quantisation."""
    H, W = shape
    V, F = merge_meshes(meshes)
    cc, rr = np.meshgrid(np.arange(W), np.arange(H))
    dc = np.stack([(cc - K[0, 2]) / K[0, 0], (rr - K[1, 2]) / K[1, 1], np.ones((H, W))], -1).reshape(-1, 3)
    dc /= np.linalg.norm(dc, axis=1, keepdims=True)
    rays = np.empty((H * W, 6), np.float32)
    rays[:, :3] = T_world_cam[:3, 3]
    rays[:, 3:] = dc @ T_world_cam[:3, :3].T
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    z = (t * dc[:, 2]).reshape(H, W)
    z[~np.isfinite(z)] = 0.0
    if rng is not None and noise_coeff > 0:
        z = np.where(z > 0, z + rng.normal(0.0, 1.0, z.shape) * noise_coeff * z * z, 0.0)
    return (np.round(z * 1000.0) / 1000.0).astype(np.float32)


@dataclass(frozen=True)
class SyntheticFrame:
    """One synthetic frame: depth (H, W) float32 m, arm meshes (world), object ground truth.

    centreline: (M, 3) m dense centreline / mid-surface samples; radius: m; anchors: (A, 3) m true
    ends / junctions / corners.
    """

    depth: np.ndarray
    arm_vertices: np.ndarray
    arm_triangles: np.ndarray
    centreline: np.ndarray
    radius: float
    anchors: np.ndarray


def rope_scene(
    phase: float,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    shape: tuple[int, int],
    rng: np.random.Generator,
    with_object: bool = True,
    arm_offset: float = 0.0,
    radius: float = 0.006,
) -> SyntheticFrame:
    """A rope on the table plus a box 'arm' standing beside it; phase (rad) moves the rope."""
    c = rope_centreline(phase, radius=radius)
    arm = box_mesh((0.42 + arm_offset, 0.2, 0.2), (0.04, 0.04, 0.2))
    meshes = [table_mesh(), arm] + ([tube_mesh(c, radius)] if with_object else [])
    d = render_depth(meshes, K, T_world_cam, shape, rng=rng)
    return SyntheticFrame(d, arm[0], arm[1], c, radius, c[[0, -1]])
