"""Object segmentation without colour (paper section III-C): depth differencing, arm removal, DBSCAN.

Two entry points:
  * ``segment_by_difference``: reference depth D0 vs depth D1 after the arms moved (initialisation);
  * ``segment_against_background``: per-frame tracking against a static background depth model.
Both return a voxel-down-sampled world-frame object cloud.

One module (~640 lines) on purpose: both entry points and the growth and refinement steps share the
same small helpers (pixel masks, the support plane, DBSCAN on voxels) and the ``Segmentation`` result.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from tracking.colour import BACKGROUND
from tracking.geometry import depth_to_points, pixel_mask, project_points
from tracking.kernels import dbscan, near_any, voxel_centroids, zbuffer_triangles
from tracking.params import TrackingParams


@dataclass(frozen=True)
class Segmentation:
    """Segmented object cloud.

    points: (N, 3) float64, metres, world frame, voxel-down-sampled object points.
    n_foreground: number of lifted foreground pixels before clustering.
    n_clusters: DBSCAN clusters found (noise excluded).
    grown: whether the object was grown over the changed pixels (``segment_by_difference(grow=True)``);
    ``refine_object_cloud`` then grows it again at full resolution.
    """

    points: np.ndarray
    n_foreground: int
    n_clusters: int
    grown: bool = False


def valid_depth(depth: np.ndarray, params: TrackingParams) -> np.ndarray:
    """(H, W) bool: depth (m) inside the valid range."""
    return (depth >= params.depth_min_m) & (depth <= params.depth_max_m)


def depth_noise(z: np.ndarray, params: TrackingParams, k: float = 1.0) -> np.ndarray:
    """k times the depth sensor's noise sigma(z) = ``diff_noise_coeff`` z**2 (m) at depths z (any shape, m), in z's
    float dtype: the one noise model the change threshold, the table's plane and its height test share."""
    z = np.asarray(z)
    return np.asarray(k * params.diff_noise_coeff, z.dtype) * z * z


def change_threshold(depth: np.ndarray, params: TrackingParams) -> np.ndarray:
    """(H, W) float32 noise-aware change threshold (m) at reference depth ``depth`` (m)."""
    return np.maximum(np.float32(params.diff_abs_m), np.float32(params.diff_sigma_k) * depth_noise(depth, params))


def _rays_needed(
    u: np.ndarray, v: np.ndarray, triangles: np.ndarray, r0: int, c0: int, shape: tuple[int, int], stride: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Which rays of a grid can hit a mesh whose vertices all lie in front of the camera.

    u, v: (V,) float pixel coordinates of the vertices; triangles (F, 3) int; the grid's ray (i, j) passes
    through pixel (c0 + j * stride, r0 + i * stride), shape = (rows, cols). A ray can hit a triangle only
    where its pixel lies inside the triangle's projection, so inside its bounding box (padded by a pixel
    against rounding). Returns the (rows, cols) bool rays inside some triangle's box and the (F,) bool
    triangles whose box meets the grid (the others no ray of the grid can hit).
    """
    nr, nc = shape
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    ua, ub, uc, va, vb, vc = u[a], u[b], u[c], v[a], v[b], v[c]  # per corner: min/max over axis 1 is slow
    jlo = np.ceil((np.minimum(np.minimum(ua, ub), uc) - 1.0 - c0) / stride)
    jhi = np.floor((np.maximum(np.maximum(ua, ub), uc) + 1.0 - c0) / stride)
    ilo = np.ceil((np.minimum(np.minimum(va, vb), vc) - 1.0 - r0) / stride)
    ihi = np.floor((np.maximum(np.maximum(va, vb), vc) + 1.0 - r0) / stride)
    hit = (jhi >= 0) & (jlo <= nc - 1) & (ihi >= 0) & (ilo <= nr - 1)
    jlo, jhi = np.clip(jlo[hit], 0, nc - 1).astype(np.int64), np.clip(jhi[hit], 0, nc - 1).astype(np.int64) + 1
    ilo, ihi = np.clip(ilo[hit], 0, nr - 1).astype(np.int64), np.clip(ihi[hit], 0, nr - 1).astype(np.int64) + 1
    # +1 / -1 at each box's corners, summed up into the number of boxes over each ray
    corners = np.concatenate([ilo * (nc + 1) + jlo, ihi * (nc + 1) + jhi, ilo * (nc + 1) + jhi, ihi * (nc + 1) + jlo])
    sign = np.repeat(np.array([1.0, -1.0]), 2 * len(jlo))
    cover = np.bincount(corners, sign, (nr + 1) * (nc + 1)).reshape(nr + 1, nc + 1)
    return np.cumsum(np.cumsum(cover, axis=0), axis=1)[:nr, :nc] > 0.5, hit


@lru_cache(maxsize=4)
def _pixel_rays(K_bytes: bytes, T_bytes: bytes, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel's viewing ray of a camera (K (3, 3), T_world_cam (4, 4) as float64 bytes) with an (H, W)
    image: unit world-frame directions (H, W, 3) float32 and their camera z components (H, W) float64
    (hit distance times it is the z-depth). Cached: the camera of a sequence is fixed, and building them
    for the arms' box every frame cost as much as casting. Read-only arrays."""
    K = np.frombuffer(K_bytes, np.float64).reshape(3, 3)
    R = np.frombuffer(T_bytes, np.float64).reshape(4, 4)[:3, :3]
    cc, rr = np.meshgrid(np.arange(W), np.arange(H))
    dc = np.stack(
        [(cc - K[0, 2]) / K[0, 0], (rr - K[1, 2]) / K[1, 1], np.ones_like(cc, dtype=np.float64)], axis=-1
    ).reshape(-1, 3)
    dc /= np.linalg.norm(dc, axis=1, keepdims=True)
    dirs = (dc @ R.T).astype(np.float32).reshape(H, W, 3)
    dirs_z = dc[:, 2].reshape(H, W)
    dirs.flags.writeable = False
    dirs_z.flags.writeable = False
    return dirs, dirs_z


def render_arm_depth(
    vertices: np.ndarray,
    triangles: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    shape: tuple[int, int],
    stride: int = 2,
) -> np.ndarray:
    """Raycast world-frame meshes into a camera depth image.

    vertices: (V, 3) float, metres, world frame; triangles: (F, 3) int. shape: (H, W).
    Rays are cast every ``stride`` pixels inside the meshes' projected bounding box and upsampled; with the
    whole mesh in front of the camera only the rays inside some triangle's projected box are cast, against
    the triangles the box grid can reach (the others miss: the same image, a smaller BVH to build).
    Returns (H, W) float32 camera z-depth in metres, +inf where no mesh is hit.
    """
    H, W = shape
    out = np.full((H, W), np.inf, np.float32)
    if len(vertices) == 0 or len(triangles) == 0:
        return out
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    vc = (vertices - t) @ R
    front = vc[:, 2] > 1e-3
    if not front.any():
        return out
    if front.all():
        u = K[0, 0] * vc[:, 0] / vc[:, 2] + K[0, 2]
        v = K[1, 1] * vc[:, 1] / vc[:, 2] + K[1, 2]
        c0, c1 = int(np.clip(np.floor(u.min()), 0, W)), int(np.clip(np.ceil(u.max()) + 1, 0, W))
        r0, r1 = int(np.clip(np.floor(v.min()), 0, H)), int(np.clip(np.ceil(v.max()) + 1, 0, H))
    else:
        c0, c1, r0, r1 = 0, W, 0, H
    if c1 <= c0 or r1 <= r0:
        return out
    rows = np.arange(r0, r1, stride)
    cols = np.arange(c0, c1, stride)
    dirs, dirs_z = _pixel_rays(K.tobytes(), T_world_cam.tobytes(), H, W)
    dirs, dirs_z = dirs[r0:r1:stride, c0:c1:stride], dirs_z[r0:r1:stride, c0:c1:stride]
    need = None
    if front.all():
        need, reach = _rays_needed(u, v, np.asarray(triangles), r0, c0, dirs_z.shape, stride)
        if not need.any():
            return out
        dirs, dirs_z, triangles = dirs[need], dirs_z[need], np.asarray(triangles)[reach]
    import open3d as o3d  # here: ~1 s to import, and only a mesh crossing the camera plane is raycast

    rays = np.empty((dirs_z.size, 6), np.float32)
    rays[:, :3] = t
    rays[:, 3:] = dirs.reshape(-1, 3)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(triangles, np.uint32)),
    )
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    if need is None:
        z = (t_hit * dirs_z.ravel()).astype(np.float32).reshape(len(rows), len(cols))
    else:
        z = np.full((len(rows), len(cols)), np.inf, np.float32)
        z[need] = (t_hit * dirs_z).astype(np.float32)
    block = np.repeat(np.repeat(z, stride, axis=0), stride, axis=1)[: r1 - r0, : c1 - c0]
    out[r0:r1, c0:c1] = block
    return out


def rasterise_depth(
    vertices: np.ndarray,
    triangles: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    shape: tuple[int, int],
    stride: int = 1,
    cullable: np.ndarray | None = None,
) -> np.ndarray:
    """``render_arm_depth``'s image drawn with a z-buffer instead of raycast: no BVH to build every frame.

    vertices: (V, 3) float, metres, world frame; triangles: (F, 3) int; shape: (H, W). The same grid (every
    ``stride``-th pixel in the meshes' projected box, upsampled): each triangle is scanned row by row over the
    grid pixels whose centre its projection covers (both faces), at the camera z-depth where that pixel's ray
    meets its plane (kept within the triangle's depth range: an edge-on sliver's plane is ill-conditioned).
    cullable: (F,) bool triangles skipped when they face away from the camera (``tdcommon.meshes.closed_outward``:
    on a closed outward mesh such a face is behind one that faces the camera; about half the work).
    The scan runs compiled (``tracking.kernels.zbuffer_triangles``). A mesh with a vertex behind the camera is
    raycast (``render_arm_depth``).
    Returns (H, W) float32 camera z-depth in metres, +inf where no mesh is hit.
    """
    H, W = shape
    out = np.full((H, W), np.inf, np.float32)
    if len(vertices) == 0 or len(triangles) == 0:
        return out
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    vc = (np.asarray(vertices, np.float64) - t) @ R
    if not (vc[:, 2] > 1e-3).all():
        return render_arm_depth(vertices, triangles, K, T_world_cam, shape, stride)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * vc[:, 0] / vc[:, 2] + cx
    v = fy * vc[:, 1] / vc[:, 2] + cy
    c0, c1 = int(np.clip(np.floor(u.min()), 0, W)), int(np.clip(np.ceil(u.max()) + 1, 0, W))
    r0, r1 = int(np.clip(np.floor(v.min()), 0, H)), int(np.clip(np.ceil(v.max()) + 1, 0, H))
    if c1 <= c0 or r1 <= r0:
        return out
    nr, nc = len(range(r0, r1, stride)), len(range(c0, c1, stride))
    tri = np.asarray(triangles, np.int64)
    if cullable is not None and cullable.any():  # faces turned away from the camera, behind those towards it
        q0 = vc[tri[:, 0]]
        away = np.einsum("ij,ij->i", np.cross(vc[tri[:, 1]] - q0, vc[tri[:, 2]] - q0), q0) >= 0
        tri = tri[~(away & cullable)]
    tri = np.ascontiguousarray(tri)
    grid = zbuffer_triangles(
        u, v, vc, tri, r0, nr, c0, nc, int(stride), float(fx), float(fy), float(cx), float(cy)
    )
    block = np.repeat(np.repeat(grid.reshape(nr, nc).astype(np.float32), stride, axis=0), stride, axis=1)
    out[r0:r1, c0:c1] = block[: r1 - r0, : c1 - c0]
    return out


def render_arm_mask(
    vertices: np.ndarray,
    triangles: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    shape: tuple[int, int],
    margin_px: int,
    depth: np.ndarray | None = None,
    margin_m: float = 0.02,
    stride: int = 2,
    cullable: np.ndarray | None = None,
) -> np.ndarray:
    """Image-space arm mask from rendered arm meshes.

    vertices: (V, 3) float, metres, world frame; triangles: (F, 3) int; shape: (H, W).
    The rendered silhouette is grown by ``margin_px`` (nearest arm depth propagated). Without
    ``depth`` the grown silhouette is returned; with measured depth (H, W) float metres a pixel is
    arm when it is inside the grown silhouette and its measured depth is missing, within
    ``margin_m`` of, or behind the rendered arm (an object in front of the arm survives).
    The silhouette and depth are ``rasterise_depth``'s (``render_arm_depth``'s image without its BVH; cullable:
    its (F,) bool back faces that may be skipped). Returns (H, W) bool.
    """
    arm = rasterise_depth(vertices, triangles, K, T_world_cam, shape, stride, cullable)
    if margin_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
        arm = cv2.erode(arm, k)
    sil = np.isfinite(arm)
    if depth is None:
        return sil
    return sil & ((depth <= 0) | (depth >= arm - np.float32(margin_m)))


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """points: (N, 3) float64, m -> (M, 3) float64 voxel centroids, m, in the voxels' (x, y, z) order.

    open3d's ``voxel_down_sample`` grid (voxels floor((p - min + voxel_m / 2) / voxel_m)) and centroids (each
    voxel's points summed in their order), bit for bit (``tracking.kernels.voxel_centroids``): importing open3d
    is ~1 s of a ``trackdeform track`` command's start-up.
    """
    if len(points) == 0:
        return np.zeros((0, 3))
    points = np.ascontiguousarray(points, np.float64)
    return voxel_centroids(points, float(voxel_m), points.min(axis=0) - 0.5 * voxel_m)[0]


def dbscan_labels(points: np.ndarray, eps_m: float, min_points: int) -> np.ndarray:
    """points: (N, 3) float64, m -> (N,) int64 DBSCAN labels 0..k-1, -1 = noise.

    A point is core when at least ``min_points`` points (itself included) lie within ``eps_m``;
    clusters are the connected components of core points linked within eps_m, and a non-core
    point within eps_m of a core point joins the cluster of the nearest one. Compiled
    (``tracking.kernels.dbscan``: neighbours in a grid of eps_m cells, union-find), ~5x a KD-tree pair query
    and scipy's connected components and ~15x open3d's DBSCAN here.
    """
    return dbscan(np.ascontiguousarray(points, np.float64), float(eps_m), int(min_points))


def voxel_groups(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Group points (N, 3) m by voxel of size voxel_m -> (centroids (M, 3) m, voxel of each point (N,) int64)
    (``tracking.kernels.voxel_centroids``)."""
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return voxel_centroids(np.ascontiguousarray(points, np.float64), float(voxel_m), np.zeros(3))


def coarse_dbscan_labels(points: np.ndarray, params: TrackingParams) -> np.ndarray:
    """DBSCAN labels (N,) int64 of points (N, 3) m computed on the centroids of a ``dbscan_voxel_m``
    grid, each point taking its voxel's label."""
    if len(points) == 0 or params.dbscan_voxel_m <= params.voxel_m:
        return dbscan_labels(points, params.dbscan_eps_m, params.dbscan_min_points)
    cen, inv = voxel_groups(points, params.dbscan_voxel_m)
    return dbscan_labels(cen, params.dbscan_eps_m, params.dbscan_min_points)[inv]


def select_largest_clusters(points: np.ndarray, labels: np.ndarray, params: TrackingParams) -> np.ndarray:
    """Largest cluster plus clusters of comparable size close to it (an object split by a gripper).

    points: (N, 3) float64, m; labels: (N,) int64. Returns (M, 3) float64 object points.
    """
    ok = labels >= 0
    if not ok.any():
        return np.zeros((0, 3))
    sizes = np.bincount(labels[ok])
    big = int(np.argmax(sizes))
    if sizes[big] < params.min_cluster_points:
        return np.zeros((0, 3))
    keep_label = np.zeros(len(sizes), bool)
    keep_label[big] = True
    cand = ok & (sizes[np.maximum(labels, 0)] >= params.cluster_keep_fraction * sizes[big]) & (labels != big)
    if cand.any():
        d, _ = cKDTree(points[labels == big]).query(points[cand], distance_upper_bound=params.cluster_keep_gap_m)
        near = np.isfinite(d)
        keep_label[np.unique(labels[cand][near])] = True
    return points[ok & keep_label[np.maximum(labels, 0)]]


def _within_box(points: np.ndarray, ref: np.ndarray, pad_m: float) -> np.ndarray:
    """(N,) bool: points (N, 3) m inside the axis-aligned box of ref (R, 3) m grown by ``pad_m`` (m) on each side,
    a cheap necessary condition for lying within pad_m of some ref point (the box is grown by a further
    millionth of pad_m so that rounding never drops such a point)."""
    if len(ref) == 0:
        return np.zeros(len(points), bool)
    pad = pad_m * (1.0 + 1e-6)
    lo, hi = ref.min(axis=0) - pad, ref.max(axis=0) + pad
    x, y, z = points.T  # per coordinate: a comparison of the (N, 3) array reduced over its rows is slower
    return (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2])


def _near(points: np.ndarray, ref: np.ndarray, r_m: float) -> np.ndarray:
    """(N,) bool: points (N, 3) m closer than r_m (m) to some ref (R, 3) m (``tracking.kernels.near_any``)."""
    return near_any(np.ascontiguousarray(points, np.float64), np.ascontiguousarray(ref, np.float64), float(r_m))


def _near_points(points: np.ndarray, ref: np.ndarray, r_m: float) -> np.ndarray:
    """(N,) bool: points (N, 3) m within r_m (m) of some ref (R, 3) m; only those inside ref's box grown by r_m
    are tested."""
    near = _within_box(points, ref, r_m)
    box = np.flatnonzero(near)
    if len(box):
        near[box] = _near(points[box], ref, r_m)
    return near


def _clusters_near(
    points: np.ndarray, labels: np.ndarray, wanted: np.ndarray, ref: np.ndarray, r_m: float
) -> np.ndarray:
    """(L,) bool: which of the ``wanted`` (L,) bool clusters have a point within r_m (m) of some ref (R, 3) m.

    points: (N, 3) m; labels: (N,) int64 cluster (-1: noise), L = len(wanted). Only points inside ref's box
    grown by r_m can be near.
    """
    near = np.zeros(len(wanted), bool)
    if not wanted.any():
        return near
    idx = np.flatnonzero((labels >= 0) & wanted[np.maximum(labels, 0)] & _within_box(points, ref, r_m))
    if len(idx):
        near[labels[idx[_near(points[idx], ref, r_m)]]] = True
    return near


def _in_cones(points: np.ndarray, tips: np.ndarray, reach_m: float, cone_cos: float) -> np.ndarray:
    """(N,) bool: points (N, 3) m within reach_m of some tip (T, 6) m and inside its cone (``tip_continuations``)."""
    out = np.zeros(len(points), bool)
    for t in tips:
        rel = points - t[:3]
        dist = np.linalg.norm(rel, axis=1)
        out |= (dist > 0) & (dist <= reach_m) & (rel @ t[3:] >= cone_cos * dist)
    return out


def chained_to(points: np.ndarray, seeds: np.ndarray, step_m: float) -> np.ndarray:
    """(N,) bool: points (N, 3) m chained to some seed in steps of at most step_m (m), in any direction, within the
    seed's reach. seeds: (S, 4) m, each one's position (3,) and reach (``tracker.held_seeds``)."""
    seeds = np.asarray(seeds, np.float64).reshape(-1, 4)
    out = np.zeros(len(points), bool)
    if not len(points) or not len(seeds):
        return out
    d = np.linalg.norm(points[:, None] - seeds[None, :, :3], axis=2)  # (N, S)
    cand = np.flatnonzero((d <= seeds[None, :, 3]).any(axis=1))
    if not len(cand) or d[cand].min() > step_m:  # nothing within a step of any seed
        return out
    S = len(seeds)
    nodes = np.vstack([seeds[:, :3], points[cand]])  # nodes 0..S-1: the seeds
    pairs = cKDTree(nodes).query_pairs(step_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(len(nodes),) * 2)
    comp = connected_components(graph, directed=False)[1]
    out[cand[np.isin(comp[S:], comp[:S])]] = True
    return out


def tip_continuations(points: np.ndarray, tips: np.ndarray, reach_m: float, step_m: float, cone_cos: float
                      ) -> np.ndarray:
    """(N,) bool: points (N, 3) m that continue a 1D object's free tips: within reach_m (m) of a tip, inside the
    cone of cosine cone_cos around its outward direction, and chained to it in steps of at most step_m (m).

    tips: (T, 6) m, each tip's position (3,) and unit outward direction (3,) (``tracker.free_tips``). A tube
    pointing towards or away from the camera lifts to a few points one or two decimated pixels wide, too sparse
    for DBSCAN; the cone keeps the table's noise and the rest of the object beside the tip out."""
    out = np.zeros(len(points), bool)
    for t in np.asarray(tips, np.float64).reshape(-1, 6):  # one or two tips an object
        cone = np.flatnonzero(_in_cones(points, t[None], reach_m, cone_cos))
        out[cone[chained_to(points[cone], np.append(t[:3], reach_m)[None], step_m)]] = True
    return out


def select_clusters_near(
    points: np.ndarray, labels: np.ndarray, keypoints: np.ndarray, params: TrackingParams,
    support: tuple[np.ndarray, float] | None = None, samples: np.ndarray | None = None, flat: bool = True,
    colour: Callable[[np.ndarray], np.ndarray] | None = None, tips: np.ndarray | None = None,
    held: np.ndarray | None = None, cam: np.ndarray | None = None,
) -> np.ndarray:
    """Clusters with a point within ``track_gate_m`` of the previous keypoints (N, 3) -> (M, 3) float64, m.

    samples: (S, 3) m points along the previous object (``object_samples``; default the keypoints).
    Where the kept clusters leave the previous object uncovered (no point within ``dbscan_eps_m`` of it), the
    points DBSCAN left out (noise, clusters under ``min_cluster_points``) within ``track_attach_m`` of it are
    kept too: a tube steep to the image plane lifts to points several pixel footprints apart along it, too
    sparse for DBSCAN. Next to a covered part such points are the sensor's flying pixels, and stay out; so
    do those less than ``table_floor`` above the ``support`` plane (normal (3,), offset m: the table, whose
    noise an object lying on it would otherwise gather frame after frame; cam (3,) m world, the camera, for the
    noise's depth; without it ``attach_min_height_m``). The points of the kept clusters near the table (within
    that of it either way) stay out too: the table's noise
    (a shadow's, where stereo matching is poor) joins the cluster of a part hanging or lying above it and
    extends its tips, and a rope or branch lying there shows its top, a diameter above the table. An object
    that can lie ``flat`` on the table (a cloth, a millimetre or two thick) keeps those within
    ``track_attach_m`` of the previous object: it stays within that of where it lay. An object that cannot (a
    rope, a branched rope) keeps of its clusters only the points within ``track_gate_m`` of the previous object:
    a cluster of the table's stereo noise beside a part lying low joins through a point near it and reaches
    10-17 cm beyond, where it drew a tip's keypoint off the object (a cloth's sheet is kept whole).
    colour: points (K, 3) m -> (K,) int8 ``tracking.colour.classify`` (this frame's): for an object that cannot
    lie flat, the left-out points lower than ``colour_band_m`` above the table whose colour is the table's stay
    out too (the table's stereo noise beside a part lying low reaches as high as that part's own sparse points;
    colour tells them apart where the table's colour is not the object's).
    tips: (T, 6) m the free tips of an object that cannot lie flat (``tracker.free_tips``): the left-out points
    that continue them are kept too (``tip_continuations`` with ``tip_reach_m``, ``tip_step_m``, ``tip_cone_cos``;
    those low above the table by colour, as above).
    held: (H, 4) m a flat object's held corners (``tracker.held_seeds``: position, the sheet's reach from it): with
    ``held_chain`` the left-out points chained to them in steps of at most ``tip_step_m`` within that reach are
    kept, in any direction (``chained_to``: a side hanging edge-on from the hand)."""
    ok = labels >= 0
    if len(keypoints) == 0 or len(points) == 0:
        return np.zeros((0, 3))
    big = (np.bincount(labels[ok]) if ok.any() else np.zeros(0, np.int64)) >= params.min_cluster_points
    near = _clusters_near(points, labels, big, keypoints, params.track_gate_m)
    keep = np.zeros(len(points), bool)
    keep[ok] = near[labels[ok]]
    ref = keypoints if samples is None else samples
    if not flat and keep.any():  # a cluster reaching far beyond the previous object is partly something else
        kk = np.flatnonzero(keep)
        keep[kk[~_near_points(points[kk], ref, params.track_gate_m)]] = False
    height = None if support is None else points @ support[0] - support[1]  # m above the table
    if height is not None:
        floor = (params.attach_min_height_m if cam is None
                 else table_floor(np.linalg.norm(points - cam, axis=1), params))
        low = np.flatnonzero(keep & (np.abs(height) < floor))
        if len(low) and flat:
            low = low[~_near(points[low], ref, params.track_attach_m)]
        keep[low] = False
    loose = ~keep
    loose[ok] &= ~big[labels[ok]]
    if height is not None:
        loose &= height >= floor  # as points_above_support
    if params.track_attach_m <= 0 or not loose.any():
        return points[keep]
    attach = params.track_attach_m
    # the left-out points near the object at all, and the parts of the object near them: only these parts'
    # coverage by the kept clusters (the kept points beside them) can decide anything
    def off_table(idx: np.ndarray) -> np.ndarray:
        """idx without the points lower than colour_band_m above the table whose colour is the table's."""
        if colour is None or height is None or not len(idx):
            return idx
        band = height[idx] < params.colour_band_m
        if not band.any():
            return idx
        return np.delete(idx, np.flatnonzero(band)[colour(points[idx[band]]) == BACKGROUND])

    cand = np.flatnonzero(loose)
    cand = cand[_near_points(points[cand], ref, attach)]
    if not flat:
        cand = off_table(cand)
    if held is not None and len(held) and flat and params.held_chain:
        pool = np.flatnonzero(loose)
        keep[pool[chained_to(points[pool], held, params.tip_step_m)]] = True
    if tips is not None and len(tips) and not flat and params.tip_reach_m > 0:
        tips = np.asarray(tips, np.float64).reshape(-1, 6)
        pool = np.flatnonzero(loose)
        # the cone's points, none of the table's noise for a chain to pass through
        pool = off_table(pool[_in_cones(points[pool], tips, params.tip_reach_m, params.tip_cone_cos)])
        if len(pool):
            keep[pool[tip_continuations(points[pool], tips, params.tip_reach_m, params.tip_step_m,
                                        params.tip_cone_cos)]] = True
    if len(cand) == 0:
        return points[keep]
    ref = ref[_near(ref, points[cand], attach)]
    kept = points[keep & _within_box(points, ref, params.dbscan_eps_m)]
    if len(kept):
        ref = ref[~_near(ref, kept, params.dbscan_eps_m)]
    if len(ref):
        keep[cand[_near(points[cand], ref, attach)]] = True
    return points[keep]


def _cluster(
    depth: np.ndarray,
    fg: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    prev_keypoints: np.ndarray | None,
    support: tuple[np.ndarray, float] | None = None,
    samples: np.ndarray | None = None,
    flat: bool = True,
    colour: Callable[[np.ndarray], np.ndarray] | None = None,
    tips: np.ndarray | None = None,
    held: np.ndarray | None = None,
) -> Segmentation:
    """Lift foreground (H, W) bool pixels, voxelise, DBSCAN and select the object clusters
    (``select_clusters_near`` with prev_keypoints, the table plane ``support``, ``samples``, ``flat``,
    ``colour``, ``tips`` and ``held``, else the largest)."""
    s = max(1, params.lift_stride)
    sub = np.zeros_like(fg)
    sub[::s, ::s] = fg[::s, ::s]
    pts, _ = depth_to_points(depth, K, T_world_cam, sub)
    vox = voxel_downsample(pts, params.voxel_m)
    labels = coarse_dbscan_labels(vox, params)
    n_clusters = int(labels.max()) + 1 if len(labels) else 0
    if prev_keypoints is None:
        obj = select_largest_clusters(vox, labels, params)
    else:
        obj = select_clusters_near(vox, labels, prev_keypoints, params, support, samples, flat, colour, tips, held,
                                   T_world_cam[:3, 3])
    return Segmentation(obj, len(pts), n_clusters)


def difference_masks(
    depth_ref: np.ndarray, depth1: np.ndarray, params: TrackingParams
) -> tuple[np.ndarray, np.ndarray]:
    """Signed depth change between reference depth(s) and depth1, metres.

    depth_ref: (H, W) or (R, H, W) float; depth1: (H, W) float. Returns (appeared, vanished), each
    (H, W) bool: appeared = in front of some reference surface (the object in frame 1), vanished =
    behind some reference surface (where the object stood in that reference).
    The change threshold is sqrt(2) * max(abs, k * sigma(z)): both frames are noisy.
    """
    refs = depth_ref[None] if depth_ref.ndim == 2 else depth_ref
    ok1 = valid_depth(depth1, params)
    appeared = np.zeros(depth1.shape, bool)
    vanished = np.zeros(depth1.shape, bool)
    for d0 in refs:
        both = ok1 & valid_depth(d0, params)
        thr = np.float32(np.sqrt(2.0)) * change_threshold(np.minimum(d0, depth1), params)
        diff = depth1 - d0
        appeared |= both & (diff < -thr)
        vanished |= both & (diff > thr)
    return appeared, vanished


def far_where_no_return(refs: np.ndarray, K: np.ndarray, params: TrackingParams) -> np.ndarray:
    """References (R, H, W) m with the scene's empty space set to ``depth_max_m``.

    A pixel without a reading in any reference looks at nothing within the sensor's range (an
    open room beyond a table seen from the side) when it belongs to a no-return region wider than
    ``no_return_open_m`` at 1 m (an opening with that kernel on the camera matrix K (3, 3) of this
    image): the object appearing there is in front of it, as it is in front of a far wall. Thinner
    holes (stereo shadow bands beside an edge, dropout) stay unknown (0). Returns a new array,
    or refs itself when nothing is filled.
    """
    if params.no_return_open_m <= 0:
        return refs
    stack = np.asarray(refs, np.float32).reshape(-1, *np.shape(refs)[-2:])
    none = ~((stack > 0) & (stack <= np.float32(params.depth_max_m))).any(axis=0)
    r = int(round(0.5 * params.no_return_open_m * float(K[0, 0])))
    if r < 1 or not none.any():
        return refs
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    far = cv2.morphologyEx(none.astype(np.uint8), cv2.MORPH_OPEN, kernel)
    # a structure thinner than that with empty space on both sides (a rope hanging still in every
    # reference) has empty space behind it too
    far = cv2.morphologyEx(far, cv2.MORPH_CLOSE, kernel).astype(bool)
    if not far.any():
        return refs
    out = stack.copy()
    out[:, far] = np.float32(params.depth_max_m)
    return out.reshape(np.shape(refs))


def grow_depth_region(
    depth: np.ndarray, seeds: np.ndarray, candidate: np.ndarray, step_m: float, thin: bool = False
) -> np.ndarray:
    """Pixels of ``candidate`` (H, W) bool connected to ``seeds`` (H, W) bool through a depth-continuous surface.

    depth: (H, W) float m. Two 4-neighbours are continuous when their depths differ by at most
    ``step_m`` m; a pixel with a neighbour nearer than that (the far side of an occluding edge) is
    cut, so a surface never connects to what lies behind its outline. Connected components of the
    remaining candidates (4-connectivity) touching a seed are returned, (H, W) bool.

    thin: the region is a structure one or two pixels wide (a tube on a decimated image): a diagonal
    staircase whose pixels touch only at corners, broken wherever one reading drops out. Diagonal
    neighbours then count too (8-connectivity; they are sqrt(2) pixels apart, so their step limit is
    sqrt(2) * step_m), and a missing pixel enclosed by candidates (a 3x3 closing) links the neighbours
    within the step of the nearest reading around it (not the surface behind a tube).
    """
    z = np.where(depth > 0, depth, np.float32(1e3)).astype(np.float32)  # missing: far, never continuous
    far = np.zeros(depth.shape, bool)
    step = np.float32(step_m)
    dv = z[1:, :] - z[:-1, :]  # > 0: the lower pixel is farther
    dh = z[:, 1:] - z[:, :-1]
    far[1:, :] |= dv > step
    far[:-1, :] |= -dv > step
    far[:, 1:] |= dh > step
    far[:, :-1] |= -dh > step
    cand = candidate & ~far & (depth > 0)
    if thin:
        return _grow_thin(z, seeds, cand, step)
    n, lab = cv2.connectedComponents(cand.astype(np.uint8), connectivity=4)
    keep = np.zeros(n, bool)
    keep[lab[seeds & cand]] = True
    keep[0] = False
    return keep[lab]


def table_floor(z: np.ndarray, params: TrackingParams) -> np.ndarray:
    """How high (m) above the table a point at depth z (any shape, m from the camera) must stand to be told from
    it: ``attach_min_height_m``, or ``support_sigma_k`` times the depth noise (``diff_noise_coeff`` z**2) where
    that is wider (a table ~2 m from a stereo camera reads ~8 mm RMS, and its noise stood 5 mm above it as a
    branch's tip continuing to the table)."""
    return np.maximum(np.float32(params.attach_min_height_m), depth_noise(z, params, params.support_sigma_k))


def points_above_support(
    points: np.ndarray, support: tuple[np.ndarray, float], params: TrackingParams, cam: np.ndarray
) -> np.ndarray:
    """(N,) bool: points (N, 3) m world standing at least ``table_floor`` above the support plane (unit normal
    (3,), offset m, camera side positive: ``support_plane``), seen from the camera at cam (3,) m world;
    ``above_support`` is the same test on a depth image."""
    return points @ support[0] - support[1] >= table_floor(np.linalg.norm(points - cam, axis=1), params)


def above_support(
    depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, support: tuple[np.ndarray, float] | None,
    params: TrackingParams,
) -> np.ndarray:
    """(H, W) bool: pixels of depth (H, W) m whose 3D point stands at least ``table_floor`` above the support
    plane (unit normal (3,) world, offset m, camera side positive: ``support_plane``); all False without one."""
    if support is None:
        return np.zeros(depth.shape, bool)
    n, o = support
    a = T_world_cam[:3, :3].T @ n  # the normal in the camera frame
    H, W = depth.shape
    u = ((np.arange(W, dtype=np.float32) - np.float32(K[0, 2])) / np.float32(K[0, 0])) * np.float32(a[0])
    v = ((np.arange(H, dtype=np.float32) - np.float32(K[1, 2])) / np.float32(K[1, 1])) * np.float32(a[1])
    height = depth * (v[:, None] + u[None, :] + np.float32(a[2])) + np.float32(T_world_cam[:3, 3] @ n - o)
    return (depth > 0) & (height >= table_floor(depth, params))


def _grow_thin(z: np.ndarray, seeds: np.ndarray, cand: np.ndarray, step: np.float32) -> np.ndarray:
    """``grow_depth_region(thin=True)`` after the 4-neighbour cut: z (H, W) float32 m (missing 1e3), cand
    (H, W) bool the remaining candidates. Pixels are linked to their 8 neighbours within the step (sqrt(2) x
    for diagonals); a missing pixel enclosed by candidates links as if it read the nearest reading around it."""
    H, W = z.shape
    missing = z >= np.float32(1e3)
    zf = np.where(missing, cv2.erode(z, np.ones((3, 3), np.uint8)), z)
    closed = cv2.morphologyEx(cand.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)
    links = cand | (closed & missing & (zf < np.float32(1e3)))
    idx = np.full((H, W), -1, np.int64)
    n = int(links.sum())
    if n == 0:
        return links
    idx[links] = np.arange(n)
    diag = np.float32(np.sqrt(2.0)) * step
    src, dst = [], []
    for dr, dc, lim in ((0, 1, step), (1, 0, step), (1, 1, diag), (1, -1, diag)):
        r0, r1 = slice(0, H - dr), slice(dr, H)
        c0, c1 = (slice(0, W - dc), slice(dc, W)) if dc >= 0 else (slice(-dc, W), slice(0, W + dc))
        ok = links[r0, c0] & links[r1, c1] & (np.abs(zf[r0, c0] - zf[r1, c1]) <= lim)
        src.append(idx[r0, c0][ok])
        dst.append(idx[r1, c1][ok])
    s, d = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(len(s), np.int8), (s, d)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    keep = np.zeros(int(comp.max()) + 1, bool)
    keep[comp[idx[seeds & cand]]] = True
    out = np.zeros((H, W), bool)
    out[links] = keep[comp]
    return out & cand


def segment_by_difference(
    depth_ref: np.ndarray,
    depth1: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    arm_mask: np.ndarray | None = None,
    grow: bool = False,
    support: tuple[np.ndarray, float] | None = None,
) -> Segmentation:
    """Initial segmentation: the object in depth1 (H, W) float m against reference depth(s) m.

    depth_ref: (H, W) reference D0, or (R, H, W) several references with the object elsewhere (e.g.
    D0 and D2 around D1): a pixel counts if it is in front of any of them. arm_mask: optional (H, W)
    bool arm pixels of frame 1 (``render_arm_mask``). Keeps the largest DBSCAN cluster (plus
    comparable clusters split from it by a gripper).

    grow (with ``params.grow_step_m`` > 0): an object moving away from the camera lies behind the
    references where it overlaps its old positions (a cloth pulled back: most of it), so the object
    is grown from its "appeared" pixels over the changed pixels (in front of or behind some
    reference) reachable through a depth-continuous surface (``grow_depth_region``); revealed
    background behind the object's outline is cut off by the depth step there. An object resting
    on a surface would leak into the surface revealed where it stood: growth suits an object
    held in the air (a cloth lifted by its corners), not a rope on a table.
    support: the reference's table plane (``support_plane``): growth also crosses the pixels that did
    not change but stand ``attach_min_height_m`` above it (the part of a hanging cloth that did not
    move yet: its lower hem, a strip that differencing misses and whose loss folds the grid's free
    side); the table itself, which a cloth may touch, is never grown into.
    """
    appeared, vanished = difference_masks(depth_ref, depth1, params)
    if arm_mask is not None:
        appeared &= ~arm_mask
    seg = _cluster(depth1, appeared, K, T_world_cam, params, None)
    if not grow or params.grow_step_m <= 0 or len(seg.points) == 0:
        return seg
    seeds = pixel_mask(seg.points, K, T_world_cam, depth1.shape)[0] & appeared
    candidate = appeared | vanished | above_support(depth1, K, T_world_cam, support, params)
    if arm_mask is not None:
        candidate &= ~arm_mask
    grown = grow_depth_region(depth1, seeds, candidate, params.grow_step_m)
    return replace(_cluster(depth1, grown | (appeared & seeds), K, T_world_cam, params, None), grown=True)


def support_plane(
    depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, params: TrackingParams, n_points: int = 4000,
    n_hypotheses: int = 200,
) -> tuple[np.ndarray, float] | None:
    """The scene's dominant plane (the table) in a depth image (H, W) m by RANSAC, refined by least squares.

    Returns (unit normal (3,) world, offset m) with x @ normal = offset on the plane and the camera
    on its positive side, or None when under ``attach_plane_min_fraction`` of the sampled pixels lie
    within ``attach_plane_tol_m`` of the best plane, nor within ``support_sigma_k`` times their
    depth noise (``diff_noise_coeff`` z**2) where that is wider: a table ~1.9 m from a stereo camera
    reads ~4-6 mm RMS, and under a third of the image then lies within 4 mm of it. Sampling is seeded
    (``params.seed``).
    """
    pts, px = depth_to_points(depth, K, T_world_cam, valid_depth(depth, params))
    if len(pts) < 50:
        return None
    rng = np.random.default_rng(params.seed)
    pick = rng.choice(len(pts), min(n_points, len(pts)), replace=False)
    P = pts[pick]
    tri = P[rng.integers(0, len(P), (n_hypotheses, 3))]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(nrm, axis=1)
    good = ln > 1e-9
    if not good.any():
        return None
    nrm = nrm[good] / ln[good, None]
    off = np.einsum("hi,hi->h", nrm, tri[good, 0])
    res = np.abs(P @ nrm.T - off)  # (N, hypotheses) m
    z = depth[px[pick, 0], px[pick, 1]].astype(np.float64)
    fixed = np.full(len(P), params.attach_plane_tol_m)
    for tol in (fixed, np.maximum(fixed, depth_noise(z, params, params.support_sigma_k))):
        inside = res <= tol[:, None]  # (N, hypotheses)
        inl = inside[:, int(np.argmax(inside.sum(axis=0)))]
        if inl.mean() >= params.attach_plane_min_fraction:
            break
    else:
        return None
    c = P[inl].mean(axis=0)
    n = np.linalg.svd(P[inl] - c, full_matrices=False)[2][2]
    o = float(c @ n)
    if T_world_cam[:3, 3] @ n < o:
        n, o = -n, -o
    return n, o


def component_spreads(points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Per label, the square roots of the point covariance's eigenvalues, ascending: (L, 3) m.

    points: (N, 3) m; labels: (N,) int >= 0, L = labels.max() + 1 (empty labels give zeros). All
    components at once from per-label sums (no loop over components).
    """
    n = np.bincount(labels).astype(np.float64)
    L = len(n)
    w = np.maximum(n, 1.0)
    mean = np.stack([np.bincount(labels, points[:, i], L) for i in range(3)], axis=1) / w[:, None]
    q = points - mean[labels]
    outer = q[:, :, None] * q[:, None, :]  # (N, 3, 3)
    cov = np.stack([np.bincount(labels, outer[:, i, j], L) for i in range(3) for j in range(3)], axis=1)
    ev = np.linalg.eigvalsh(cov.reshape(L, 3, 3) / w[:, None, None])
    return np.sqrt(np.maximum(ev, 0.0))


def grow_attached_tubes(
    depth1: np.ndarray,
    seg: Segmentation,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    arm_mask: np.ndarray | None = None,
    support: tuple[np.ndarray, float] | None = None,
    min_part_px: int = 3,
) -> Segmentation:
    """A 1D object's difference segmentation completed with its parts that did not move.

    depth1: (H, W) float m; seg: ``segment_by_difference`` of it. An end that barely moved between
    the references and depth1 (a free branch dragged along the table) changes its depth by less
    than the noise threshold and is missing from the difference cloud, by an amount that varies
    with the noise (0-15 mm short over camera seeds). Pixels within ``attach_reach_m`` of the cloud
    (3D), standing at least ``attach_min_height_m`` above the ``support`` plane (normal (3,), offset
    m, camera side positive: ``support_plane`` of the reference, the table; a rope 14 mm thick
    meets the table without a depth step, so continuity alone cannot separate them) and reachable
    from the object's pixels over a depth-continuous surface (``grow_depth_region``, step
    ``attach_step_m`` or ``attach_step_px`` pixel footprints at the cloud's median depth, the
    larger) are added, when each added connected part is thin (lateral spread, the square
    root of its second PCA eigenvalue, at most ``attach_max_spread_m``) and of at least ``min_part_px``
    pixels: the rest of a tube, not a patch of surface or a speck of noise. Repeated growth towards a free
    end takes single pixels (1): a tube steep to the image plane gains a row of one or two pixels a step.
    Returns a new Segmentation (the input when nothing is added or the reach is 0).
    """
    reach = params.attach_reach_m
    if reach <= 0 or len(seg.points) == 0:
        return seg
    H, W = depth1.shape
    seeds, zmed = pixel_mask(seg.points, K, T_world_cam, (H, W))
    # the object's pixels: the projected voxels dilated to the voxel's footprint
    px_m = zmed / float(K[0, 0])
    vox_px = max(1, int(np.ceil(params.voxel_m / px_m)))
    obj = cv2.dilate(seeds.astype(np.uint8), np.ones((vox_px, vox_px), np.uint8)).astype(bool)
    r_px = int(np.ceil(reach / px_m))
    near = cv2.dilate(obj.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r_px + 1,) * 2))
    zone = near.astype(bool) & valid_depth(depth1, params) & ~obj
    if arm_mask is not None:
        zone &= ~arm_mask
    zp, zpix = depth_to_points(depth1, K, T_world_cam, zone)
    tree = cKDTree(seg.points)
    d, _ = tree.query(zp, distance_upper_bound=reach)
    ok = np.isfinite(d)
    if support is not None:
        ok &= points_above_support(zp, support, params, T_world_cam[:3, 3])
    zpix = zpix[ok]
    if len(zpix) == 0:
        return seg
    cand = np.zeros((H, W), bool)
    cand[zpix[:, 0], zpix[:, 1]] = True
    # a tube inclined to the image plane steps by its slope times the pixel footprint between neighbours,
    # give or take the noise of the two readings
    noise = np.sqrt(2.0) * float(change_threshold(np.float32(zmed), params))
    step = max(params.attach_step_m, params.attach_step_px * px_m) + noise
    grown = grow_depth_region(depth1, obj, obj | cand, step, thin=True) & cand
    if not grown.any():
        return seg
    _, lab = cv2.connectedComponents(grown.astype(np.uint8), connectivity=8)
    pts, pix = depth_to_points(depth1, K, T_world_cam, grown)
    comp = lab[pix[:, 0], pix[:, 1]]
    thin = (component_spreads(pts, comp)[:, 1] <= params.attach_max_spread_m) & (np.bincount(comp) >= min_part_px)
    accepted = thin[comp]
    if not accepted.any():
        return seg
    extra = voxel_downsample(pts[accepted], params.voxel_m)
    d, _ = tree.query(extra, distance_upper_bound=0.5 * params.voxel_m)
    extra = extra[~np.isfinite(d)]  # voxels the difference cloud already has stay as they were
    return Segmentation(np.concatenate([seg.points, extra]), seg.n_foreground + int(accepted.sum()), seg.n_clusters)


def complete_thin_parts(
    depth: np.ndarray,
    seg: Segmentation,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    arm_mask: np.ndarray | None = None,
    support: tuple[np.ndarray, float] | None = None,
    iterations: int | None = None,
    away: tuple[np.ndarray, float] | None = None,
) -> Segmentation:
    """A 1D object's tracking segmentation of depth (H, W) m grown over its thin parts (``grow_attached_tubes``,
    up to ``iterations`` times (default ``track_attach_iterations``), each within ``attach_reach_m`` of what it
    has and taking parts of a single pixel: a tube steep to the image plane gains a row of one or two pixels a
    step). away: (points (G, 3) m, distance m): what grows within that distance of them is left out (a gripper
    holding the object is no part of it; ``LivePipeline.reach_grippers`` grows the still free ends so).

    Where the object stood in the references, the background holds the object itself: a branch swinging back
    to where it hung reads within the change threshold of that background, or behind it, and is missing from
    the foreground (its lower third, 5-10 cm, for a dozen frames at a time). It is still a thin tube
    depth-continuous with the part that is seen. Each growth runs on the crop of the image it can reach (the
    cloud's pixels and ``attach_reach_m`` around them). Returns the input when nothing is added."""
    H, W = depth.shape
    for _ in range(max(0, params.track_attach_iterations if iterations is None else iterations)):
        uv, z = project_points(seg.points, K, T_world_cam)
        front = z > 1e-6
        if not front.any():
            break
        px_m = float(np.median(z[front])) / float(K[0, 0])
        pad = int(np.ceil(params.attach_reach_m / px_m)) + int(np.ceil(params.voxel_m / px_m)) + 2
        lo = np.maximum(np.floor(uv[front].min(axis=0)).astype(int) - pad, 0)
        hi = np.minimum(np.ceil(uv[front].max(axis=0)).astype(int) + pad + 1, [W, H])
        if (hi <= lo).any():
            break
        crop = np.s_[lo[1]:hi[1], lo[0]:hi[0]]
        Kc = K.astype(np.float64).copy()
        Kc[0, 2] -= lo[0]
        Kc[1, 2] -= lo[1]
        arm = None if arm_mask is None else arm_mask[crop]
        grown = grow_attached_tubes(depth[crop], seg, Kc, T_world_cam, params, arm, support, min_part_px=1)
        new = grown.points[len(seg.points):]
        if away is not None and len(new):
            new = new[(np.linalg.norm(new[:, None, :] - away[0][None, :, :], axis=2) > away[1]).all(axis=1)]
        if len(new) == 0:
            break
        seg = replace(grown, points=np.concatenate([seg.points, new]))
    return seg


def refine_object_cloud(
    depth: np.ndarray,
    cloud: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    arm_mask: np.ndarray | None = None,
    refs: np.ndarray | None = None,
    support: tuple[np.ndarray, float] | None = None,
) -> np.ndarray:
    """An object's cloud (N, 3) m segmented on a decimated depth, re-lifted from the full-resolution
    depth (H, W) m (camera matrix K (3, 3) of that resolution) and voxelised again, (M, 3) m.

    On a decimated image a rope is 3 pixels wide: every voxel holds one reading, so the cloud's
    points sit on the decimated pixel rays and its skeleton jumps by a whole pixel (5 mm) between
    captures. Every full-resolution pixel within a voxel's footprint of the cloud's projection and
    within ``voxel_m`` of it in 3D is lifted (not in ``arm_mask``, (H, W) bool or decimated, resized)
    and voxel-averaged: ~10 readings a voxel, so its centroid is steady to the noise's tenth.

    refs: (R, h, w) m the reference depths (any resolution, resized nearest) of a grown segmentation
    (``Segmentation.grown``): the growth over the pixels changed against them is redone at full
    resolution. A surface seen almost edge-on (a hanging cloth's top hem) steps by more than
    ``grow_step_m`` between decimated pixels, and a decimated pixel on its edge may sample the
    background: the decimated growth loses it in some captures and not others (20 mm of the
    cloth's top edge, 4 mm spread of its keypoints); full-resolution neighbours are a quarter as far apart.

    support: the table plane (``support_plane``): with refs, the regrowth also crosses the unchanged
    pixels above it (``segment_by_difference``); without, a 1D object's thin parts standing above it
    are grown at full resolution too (``grow_attached_tubes``). The last centimetre of a branch hanging
    just above the table is within a decimated pixel's noise of it and was lost in some captures
    (its tip 1-8 mm short over camera seeds).
    """
    if len(cloud) == 0:
        return cloud
    H, W = depth.shape
    on, zmed = pixel_mask(cloud, K, T_world_cam, (H, W))
    r = max(1, int(np.ceil(params.voxel_m * float(K[0, 0]) / zmed)))
    mask = cv2.dilate(on.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)).astype(bool)
    valid = valid_depth(depth, params)
    arm = None if arm_mask is None else _full_size(arm_mask, (H, W))
    if arm is not None:
        valid &= ~arm
    pts, pix = depth_to_points(depth, K, T_world_cam, mask & valid)
    d, _ = cKDTree(cloud).query(pts, distance_upper_bound=params.voxel_m)
    near = np.isfinite(d)
    pts = pts[near]
    if refs is not None and params.grow_step_m > 0 and len(pts):
        seeds = np.zeros((H, W), bool)
        seeds[pix[near, 0], pix[near, 1]] = True
        above = above_support(depth, K, T_world_cam, support, params) if support else None
        extra, _ = depth_to_points(depth, K, T_world_cam, _regrow(depth, seeds, refs, valid, params, above) & ~seeds)
        pts = np.concatenate([pts, extra])
    if not len(pts):
        return cloud
    out = voxel_downsample(pts, params.voxel_m)
    if support is not None and refs is None:
        out = grow_attached_tubes(depth, Segmentation(out, len(pts), 1), K, T_world_cam, params, arm, support).points
    return out


def _regrow(
    depth: np.ndarray, seeds: np.ndarray, refs: np.ndarray, valid: np.ndarray, params: TrackingParams,
    above: np.ndarray | None = None,
) -> np.ndarray:
    """Pixels (H, W) bool of a full-resolution depth (H, W) m changed against the references refs
    (R, h, w) m (resized nearest), or in ``above`` (H, W) bool (above the table), and reachable from
    seeds (H, W) bool through depth steps of at most ``grow_step_m``; only ``valid`` (H, W) bool pixels
    are candidates."""
    H, W = depth.shape
    refs = np.asarray(refs, np.float32).reshape(-1, *np.shape(refs)[-2:])
    up = np.stack([cv2.resize(ref, (W, H), interpolation=cv2.INTER_NEAREST) for ref in refs])
    appeared, vanished = difference_masks(up, depth, params)
    changed = appeared | vanished if above is None else appeared | vanished | above
    return grow_depth_region(depth, seeds, (changed & valid) | seeds, params.grow_step_m)


def _full_size(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A (h, w) bool mask resized (nearest) to shape (H, W)."""
    if mask.shape == shape:
        return mask.astype(bool)
    return cv2.resize(mask.astype(np.uint8), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST).astype(bool)


def background_from_depths(depths: np.ndarray) -> np.ndarray:
    """Static background (H, W) float32 metres: per-pixel median of (K, H, W) depths ignoring zeros."""
    d = np.asarray(depths, np.float32)
    if d.ndim == 2:
        return d.copy()
    d = np.where(d > 0, d, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(d, axis=0)
    return np.nan_to_num(med, nan=0.0).astype(np.float32)


def behind_near_object(
    depth: np.ndarray,
    background: np.ndarray,
    params: TrackingParams,
    object_points: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    arm_mask: np.ndarray | None = None,
    thr: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool: valid pixels significantly behind the background (m), or without a background
    (0: unknown, e.g. where the object stood still in every reference), whose 3D point lies within
    ``background_object_gap_m`` of the tracked object (points (M, 3) m world, e.g. its densified
    keypoint edges): the object moved away from the camera behind a background that still holds
    it from the reference frames, or is where nothing else was ever seen. Such pixels are object,
    not revealed background. thr: ``change_threshold(background)`` when the caller has it."""
    out = valid_depth(depth, params)
    out &= (background <= 0) | (depth - background > (change_threshold(background, params) if thr is None else thr))
    if arm_mask is not None:
        out &= ~arm_mask
    if len(object_points) == 0 or not out.any():
        return out & False
    pts, rc = depth_to_points(depth, K, T_world_cam, out)
    near = _near_points(pts, object_points, params.background_object_gap_m)
    out[:] = False
    out[rc[near, 0], rc[near, 1]] = True
    return out


def behind_continuing(
    depth: np.ndarray,
    background: np.ndarray,
    params: TrackingParams,
    seeds: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    arm_mask: np.ndarray | None,
    support: tuple[np.ndarray, float] | None,
    thr: np.ndarray,
) -> np.ndarray:
    """(H, W) bool: valid pixels significantly behind the background (H, W) m that a depth-continuous surface
    standing above the table joins to the object's pixels ``seeds`` (H, W) bool (``grow_depth_region``,
    ``grow_step_m``; the table plane ``support``, ``attach_min_height_m``; arm pixels left out).

    The object moved behind where the references held something else (a hand, or the object itself): a surface
    continuing the object's own is the object, not revealed background, however far the tracked keypoints lag
    behind it (``behind_near_object`` asks for them within ``background_object_gap_m``, so a part the keypoints
    had lost became background and stayed out of the cloud). thr: ``change_threshold(background)``."""
    ok = valid_depth(depth, params) & (background > 0)
    if arm_mask is not None:
        ok &= ~arm_mask
    if support is not None:
        ok &= above_support(depth, K, T_world_cam, support, params)
    behind = ok & (depth - background > thr)
    if not behind.any():
        return behind
    region = behind | (ok & (background - depth > thr))  # what lies behind the background, and in front of it
    return grow_depth_region(depth, seeds & region, region, params.grow_step_m) & behind


def update_background(
    background: np.ndarray,
    depth: np.ndarray,
    params: TrackingParams,
    arm_mask: np.ndarray | None = None,
    prev_depth: np.ndarray | None = None,
    keep: np.ndarray | None = None,
    nearest: bool = True,
    thr: np.ndarray | None = None,
) -> np.ndarray:
    """Background (H, W) float32 m updated with newly revealed farther surfaces of depth (H, W) m.

    Where the measured depth is significantly behind the background, whatever stood there (the
    object in the reference frames) has moved away: the farther surface becomes the background.
    With ``prev_depth`` (P, H, W) m, the previous frames (oldest first; (H, W): one), a pixel more than
    ``background_jump_k`` change thresholds behind (a surface revealed) must be behind in the newest
    previous frame too; one less far behind must be behind in all of them and takes the nearest of
    these readings (``nearest``; else the current one). Noisy or flying readings then cannot push the
    background back (they would ratchet it farther frame after frame and the foreground would fill
    with noise: a stereo sensor noisier than ``diff_noise_coeff`` crosses the change threshold on a
    few % of the pixels in a frame, in two frames running on ~0.1 %, in three on ~0.01 %, and
    seldom by twice the threshold).
    keep: (H, W) bool pixels not to update (``behind_near_object``: the object, not background). A
    pixel without a background (0) takes the depth it has in all these frames (``keep`` aside).
    thr: ``change_threshold(background)`` when the caller has it.
    """
    ok = valid_depth(depth, params)
    if arm_mask is not None:
        ok &= ~arm_mask
    if keep is not None:
        ok &= ~keep
    bg_ok = background > 0
    thr = change_threshold(background, params) if thr is None else thr
    revealed = ok & bg_ok & (depth - background > thr)
    unknown = ok & ~bg_ok
    out = background.copy()
    if prev_depth is None:
        out[revealed | unknown] = depth[revealed | unknown]
        return out
    prevs = np.asarray(prev_depth, np.float32).reshape(-1, *depth.shape)
    jump = revealed & (depth - background > np.float32(params.background_jump_k) * thr)
    jump &= prevs[-1] - background > thr
    near = depth
    for prev in prevs:
        revealed &= prev - background > thr
        unknown &= valid_depth(prev, params)
        near = np.minimum(near, prev) if nearest else near
    revealed &= ~jump
    out[jump] = depth[jump]
    out[revealed] = near[revealed]
    out[unknown] = depth[unknown]
    return out


def unchanged_object_pixels(
    depth: np.ndarray, background: np.ndarray, cloud: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
    params: TrackingParams, by_background: bool = False,
) -> np.ndarray:
    """(H, W) bool: pixels of the object cloud (N, 3) m world in depth (H, W) m (within a voxel's footprint of
    its projection and ``voxel_m`` of it in 3D) where the background (H, W) m is within the change threshold
    of the depth: the object stood there in every reference, so the background there is the object itself.

    by_background: test the background's own reading instead: a footprint pixel whose background lifts to
    within ``voxel_m`` plus the change threshold of the cloud, whatever the depth reads now. A thin tube
    hanging still is one or two pixels wide and its readings scatter by about the threshold: the depth test
    keeps the background on the object wherever this frame's reading happened to differ, and later
    readings on the near side of that background are then neither in front of nor behind it.
    """
    H, W = depth.shape
    on, zmed = pixel_mask(cloud, K, T_world_cam, (H, W))
    r = max(1, int(np.ceil(params.voxel_m * float(K[0, 0]) / zmed)))
    near = cv2.dilate(on.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2))
    cand = near.astype(bool) & (background > 0)
    thr = change_threshold(background, params)
    if by_background:
        cand &= valid_depth(background, params)
    else:
        cand &= valid_depth(depth, params) & (np.abs(depth - background) <= thr)
    out = np.zeros((H, W), bool)
    if len(cloud) == 0 or not cand.any():
        return out
    pts, rc = depth_to_points(background if by_background else depth, K, T_world_cam, cand)
    tol = params.voxel_m + (thr[rc[:, 0], rc[:, 1]] if by_background else 0.0)
    d, _ = cKDTree(cloud).query(pts, distance_upper_bound=float(np.max(tol)))
    hit = d <= tol
    out[rc[hit, 0], rc[hit, 1]] = True
    return out


def foreground_mask(
    depth: np.ndarray, background: np.ndarray, params: TrackingParams, arm_mask: np.ndarray | None = None,
    thr: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool: valid pixels significantly in front of the background (m), arm pixels removed
    (thr: ``change_threshold(background)`` when the caller has it)."""
    fg = valid_depth(depth, params) & (background > 0)
    fg &= background - depth > (change_threshold(background, params) if thr is None else thr)
    if arm_mask is not None:
        fg &= ~arm_mask
    return fg


def segment_against_background(
    depth: np.ndarray,
    background: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    arm_mask: np.ndarray | None = None,
    prev_keypoints: np.ndarray | None = None,
    extra: np.ndarray | None = None,
    support: tuple[np.ndarray, float] | None = None,
    samples: np.ndarray | None = None,
    thr: np.ndarray | None = None,
    flat: bool = True,
    colour: Callable[[np.ndarray], np.ndarray] | None = None,
    tips: np.ndarray | None = None,
    held: np.ndarray | None = None,
) -> Segmentation:
    """Per-frame segmentation: pixels in front of the background minus arms, clustered.

    depth, background: (H, W) float metres. prev_keypoints: (N, 3) m; when given, clusters near
    them are kept (all of them: an object split by a gripper stays whole), else the largest.
    extra: (H, W) bool pixels known to be object as well (``behind_near_object``). support: the table plane
    (``support_plane``), samples: (S, 3) m points along the previous object (``select_clusters_near``).
    thr: ``change_threshold(background)`` when the caller has it. flat: the object can lie flat on the table
    (``select_clusters_near``), colour: the frame's ``tracking.colour.classify`` of points (``select_clusters_near``),
    tips: the object's free tips, held: a flat object's held corners (``select_clusters_near``).
    """
    fg = foreground_mask(depth, background, params, arm_mask, thr)
    if extra is not None:
        fg |= extra
    return _cluster(depth, fg, K, T_world_cam, params, prev_keypoints, support, samples, flat, colour, tips, held)
