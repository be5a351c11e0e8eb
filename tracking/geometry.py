"""Pinhole geometry: lift depth to world points, project world points, splat points into masks.

Camera frame is OpenCV's (x right, y down, z forward); ``T_world_cam`` (4, 4) maps camera to world.
"""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree


def csr_graph(edges: np.ndarray, n: int, weights: np.ndarray | None = None) -> csr_matrix:
    """The (n, n) CSR adjacency matrix of edges (E, 2) int (row, column) with weights (E,) (default 1.0), built
    directly, rows ordered by a stable sort (from (row, column) pairs scipy goes through COO): what scipy's
    graph routines take as it is."""
    order = np.argsort(edges[:, 0], kind="stable")
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(edges[:, 0], minlength=n), out=indptr[1:])
    w = np.ones(len(edges)) if weights is None else weights[order]
    return csr_matrix((w, edges[order, 1], indptr), shape=(n, n))


def depth_to_points(
    depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Lift depth pixels to world points.

    depth: (H, W) float, metres, 0 = missing. mask: optional (H, W) bool of pixels to lift.
    Returns points (N, 3) float64, metres, world frame, and pixels (N, 2) int64 as (row, col).
    """
    valid = depth > 0
    if mask is not None:
        valid &= mask
    idx = np.flatnonzero(valid)  # flat indices: quicker than a 2D nonzero and gather
    rows, cols = np.divmod(idx, depth.shape[1])
    z = depth.ravel()[idx].astype(np.float64)
    x = (cols - K[0, 2]) * z / K[0, 0]
    y = (rows - K[1, 2]) * z / K[1, 1]
    pc = np.stack([x, y, z], axis=1)
    pw = pc @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    return pw, np.stack([rows, cols], axis=1)


def world_to_camera(points: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """points: (N, 3) world frame, m -> (N, 3) camera frame, m."""
    R = T_world_cam[:3, :3]
    return (points - T_world_cam[:3, 3]) @ R


def project_points(points: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points to the image.

    points: (N, 3) float64, metres, world frame. Returns uv (N, 2) float64 as (col, row) pixels and
    z (N,) float64 camera depth in metres (<= 0 means behind the camera).
    """
    pc = world_to_camera(points, T_world_cam)
    z = pc[:, 2]
    zs = np.where(z > 1e-9, z, 1e-9)
    u = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    return np.stack([u, v], axis=1), z


def pixels_of(
    points: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, shape: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixel each point (N, 3) m world falls in, of an image of ``shape`` (h, w) that K (3, 3) at T_world_cam
    (4, 4) describes: row (N,) and column (N,) int64 (floored), inside (N,) bool (in front of the camera and in the
    image; the row and column of the others are out of range) and the depth z (N,) m."""
    uv, z = project_points(points, K, T_world_cam)
    h, w = shape[:2]
    c = np.floor(uv[:, 0]).astype(np.int64)
    r = np.floor(uv[:, 1]).astype(np.int64)
    return r, c, (z > 0) & (c >= 0) & (c < w) & (r >= 0) & (r < h), z


def gaps_hidden(
    a: np.ndarray, b: np.ndarray, mask: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, skip_m: float,
    samples: int = 16,
) -> np.ndarray:
    """(G,) bool: whether each straight gap from a (G, 3) m to b (G, 3) m, world frame, is out of sight behind
    mask (h, w) bool (e.g. the arm's pixels of a camera with matrix K (3, 3) at T_world_cam (4, 4)): every one of
    ``samples`` points along it farther than skip_m from a lies on a masked pixel or outside the image."""
    a = np.asarray(a, np.float64).reshape(-1, 3)
    b = np.asarray(b, np.float64).reshape(-1, 3)
    t = np.linspace(0.0, 1.0, samples)
    P = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]  # (G, S, 3)
    far = np.linalg.norm(P - a[:, None, :], axis=2) > skip_m
    r, c, inside, _ = pixels_of(P.reshape(-1, 3), K, T_world_cam, mask.shape)
    hid = ~inside
    hid[inside] = mask[r[inside], c[inside]]
    return (hid.reshape(far.shape) | ~far).all(axis=1) & far.any(axis=1)


def hidden_behind(
    points: np.ndarray, mask: np.ndarray | None, depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
    margin_m: float, reach_m: float = 0.0,
) -> np.ndarray:
    """(N,) bool: which points (N, 3) m world lie out of sight (depth (h, w) m, 0 = no reading; camera K (3, 3) at
    T_world_cam (4, 4)). With a mask (h, w) bool of what hides them (the arm's pixels): a point on a masked pixel and
    not nearer than its depth less margin_m (touching the arm, between the fingers, counts); a point well in front
    (a rope passing before the arm) is seen. Without one (mask None): a point whose pixel shows a surface more than
    margin_m in front of it (a cloth's own near layer, or the arm), or no reading; a point on the surface is seen.
    So is a point whose pixel shows open space (a surface more than margin_m behind it) unless, with reach_m > 0, a
    pixel within reach_m of it (across the image, at its depth) shows a surface more than margin_m in front of it:
    then it is out of sight behind that layer, a little beside where it was put (a cloth turned edge-on), and the
    nearest visible point, on the layer in front, is not its place. Either way a point outside the image (a held
    end above its top edge) is out of sight. Such a point has no cloud of its own."""
    r, c, inside, z = pixels_of(np.asarray(points, np.float64).reshape(-1, 3), K, T_world_cam, depth.shape)
    out = ~inside
    ri, ci = r[inside], c[inside]
    d = depth[ri, ci]
    if mask is None:
        out[inside] = (d <= 0) | (z[inside] > d + margin_m)
        free = np.flatnonzero(in_open_space(points, depth, K, T_world_cam, margin_m))
        if reach_m > 0 and len(free):
            out[free] = occluder_within(depth, r[free], c[free], z[free], K, reach_m, margin_m)
    else:
        out[inside] = mask[ri, ci] & ((d <= 0) | (z[inside] > d - margin_m))
    return out


def in_open_space(
    points: np.ndarray, depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, margin_m: float
) -> np.ndarray:
    """(N,) bool: which points (N, 3) m world lie in the open space the camera sees through (depth (h, w) m, 0 = no
    reading; K (3, 3) at T_world_cam (4, 4)): their pixel shows a surface more than margin_m behind them. Something
    there would be seen in front of that surface, so a keypoint out of sight cannot be there."""
    r, c, inside, z = pixels_of(np.asarray(points, np.float64).reshape(-1, 3), K, T_world_cam, depth.shape)
    out = np.zeros(len(r), bool)
    d = depth[r[inside], c[inside]]
    out[inside] = (d > 0) & (z[inside] < d - margin_m)
    return out


def occluder_within(
    depth: np.ndarray, r: np.ndarray, c: np.ndarray, z: np.ndarray, K: np.ndarray, reach_m: float, margin_m: float
) -> np.ndarray:
    """(n,) bool: whether a pixel of depth (h, w) m (0 = no reading; camera matrix K (3, 3)) within reach_m of pixel
    (r, c) (n,) int64, measured across the image at depth z (n,) m, shows a surface more than margin_m in front of
    z. One window of the largest radius for all, each point's own radius applied inside it."""
    h, w = depth.shape
    rad = float(K[0, 0]) * reach_m / np.maximum(z, 1e-6)  # (n,) px
    k = min(int(np.ceil(rad.max())), max(h, w))  # a point at the lens would otherwise ask for a huge window
    off = np.arange(-k, k + 1)
    dr, dc = np.meshgrid(off, off, indexing="ij")
    dr, dc = dr.ravel(), dc.ravel()
    rr, cc = r[:, None] + dr[None, :], c[:, None] + dc[None, :]  # (n, W)
    ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w) & (dr * dr + dc * dc <= (rad * rad)[:, None])
    dd = depth[np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1)]
    return (ok & (dd > 0) & (dd < (z - margin_m)[:, None])).any(axis=1)


def behind_nearest_occluder(
    points: np.ndarray, depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, mask: np.ndarray,
    reach_m: float, margin_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) m world left in the open space the camera sees through (``in_open_space``; depth (h, w) m,
    0 = no reading; K (3, 3) at T_world_cam (4, 4)) moved across the image, at their own depth, onto the nearest
    pixel of mask (h, w) bool (the arm) within reach_m, measured at that depth, whose surface lies more than
    margin_m in front of them: the camera would see them where they are, so they lie behind the nearest thing
    that hides them. Left where they are: a point on a mask pixel (in front of the arm), one with a surface at its
    own depth (within margin_m) within margin_m of it across the image (something the cloud left out is there),
    and one with no such mask pixel within reach. Returns the points (N, 3) m and which were moved (N,) bool."""
    X = np.array(points, np.float64).reshape(-1, 3)
    moved = np.zeros(len(X), bool)
    free = np.flatnonzero(in_open_space(X, depth, K, T_world_cam, margin_m))
    r, c, _, z = pixels_of(X[free], K, T_world_cam, depth.shape)
    h, w = depth.shape
    for j, rj, cj, zj in zip(free.tolist(), r.tolist(), c.tolist(), z.tolist(), strict=True):
        if mask[rj, cj]:
            continue
        rad, near = float(K[0, 0]) * reach_m / zj, float(K[0, 0]) * margin_m / zj  # px
        k = int(np.ceil(max(rad, near)))
        r0, r1, c0, c1 = max(rj - k, 0), min(rj + k + 1, h), max(cj - k, 0), min(cj + k + 1, w)
        dr, dc = np.ogrid[r0 - rj:r1 - rj, c0 - cj:c1 - cj]
        d2 = dr * dr + dc * dc  # (window) px^2
        dd = depth[r0:r1, c0:c1]
        if ((d2 <= near * near) & (dd > 0) & (np.abs(dd - zj) < margin_m)).any():
            continue
        ok = (d2 <= rad * rad) & mask[r0:r1, c0:c1] & (dd > 0) & (dd < zj - margin_m)
        if not ok.any():
            continue
        br, bc = np.unravel_index(np.argmin(np.where(ok, d2, np.inf)), ok.shape)
        u, v = c0 + bc + 0.5, r0 + br + 0.5  # the pixel's centre
        pc = np.array([(u - K[0, 2]) * zj / K[0, 0], (v - K[1, 2]) * zj / K[1, 1], zj])
        X[j] = T_world_cam[:3, :3] @ pc + T_world_cam[:3, 3]
        moved[j] = True
    return X, moved


def decimation_stride(K: np.ndarray, pixel_m: float) -> int:
    """Stride s >= 1 (px) so that every s-th pixel of a camera with matrix K (3, 3) spans about
    ``pixel_m`` metres at 1 m depth (s = round(fx * pixel_m)); 1 when pixel_m <= 0."""
    if pixel_m <= 0:
        return 1
    return max(1, int(round(0.5 * (K[0, 0] + K[1, 1]) * pixel_m)))


def decimated_intrinsics(K: np.ndarray, s: int) -> np.ndarray:
    """Camera matrix (3, 3) of the image ``img[::s, ::s]``: pixel (r, c) there is pixel (s r, s c) of K's image."""
    Kd = K.astype(np.float64).copy()
    Kd[:2, :] /= s
    return Kd


def scale_intrinsics(K: np.ndarray, s: float) -> np.ndarray:
    """Camera matrix (3, 3) of the same camera with the image resized by factor s (pixel centres kept)."""
    Ks = K.astype(np.float64).copy()
    Ks[0, 0] *= s
    Ks[1, 1] *= s
    Ks[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return Ks


def pixel_mask(
    points: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, float]:
    """The pixels (H, W) bool that points (N, 3) float64 m world fall on (rounded; those in front
    of the camera and inside the image), and the points' median depth, m (1.0 when there are none)."""
    H, W = shape
    mask = np.zeros((H, W), bool)
    uv, z = project_points(points, K, T_world_cam)
    ok = z > 1e-6
    if not ok.any():
        return mask, 1.0
    rc = np.rint(uv[ok, ::-1]).astype(np.int64)
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < H) & (rc[:, 1] >= 0) & (rc[:, 1] < W)
    mask[rc[inside, 0], rc[inside, 1]] = True
    return mask, float(np.median(z[ok]))


def splat_mask(
    points: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, shape: tuple[int, int], radius_m: float
) -> np.ndarray:
    """Binary image of points drawn as discs of world radius ``radius_m``, then closed.

    points: (N, 3) float64, metres, world frame. shape: (H, W) of the image K describes.
    Returns (H, W) bool.
    """
    mask, zmed = pixel_mask(points, K, T_world_cam, shape)
    if not mask.any():
        return mask
    f = 0.5 * (K[0, 0] + K[1, 1])
    r_px = int(np.clip(np.ceil(radius_m * f / zmed), 1, 25))
    dy, dx = np.mgrid[-r_px : r_px + 1, -r_px : r_px + 1]
    disc = ((dx**2 + dy**2) <= r_px**2 + 0.5).astype(np.uint8)
    out = cv2.dilate(mask.astype(np.uint8), disc)  # union of the discs centred on the points
    out = cv2.morphologyEx(out, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    return out.astype(bool)


def edge_samples(X: np.ndarray, edges: np.ndarray, n: int) -> np.ndarray:
    """Points (E * n, 3) m spaced evenly along each edge (E, 2) of keypoints X (N, 3) m, ends included."""
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    t = np.linspace(0.0, 1.0, max(2, n))[None, :, None]
    a, b = X[edges[:, 0]][:, None, :], X[edges[:, 1]][:, None, :]
    return (a + t * (b - a)).reshape(-1, 3)


@cache
def cell_samples(shape: tuple[int, int], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points spread over a row-major grid's cells, n + 1 to a side of each cell (corners included), as their four
    cell corners (K, 4) int64 keypoint indices and bilinear weights (K, 4): a grid X (N, 3) m has them at
    ``einsum("kj,kjc->kc", W, X[I])``. Cached per (shape, n) and read-only: one grid's are built once a clip."""
    rows, cols = shape
    idx = np.arange(rows * cols).reshape(rows, cols)
    corners = (idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:])
    t = np.linspace(0.0, 1.0, n + 1)
    u, v = (a.ravel()[:, None, None] for a in np.meshgrid(t, t, indexing="ij"))
    weights = ((1 - u) * (1 - v), (1 - u) * v, u * (1 - v), u * v)
    shape3 = (len(t) ** 2, rows - 1, cols - 1)
    I = np.stack([np.broadcast_to(c, shape3) for c in corners], -1).reshape(-1, 4)
    W = np.stack([np.broadcast_to(w, shape3) for w in weights], -1).reshape(-1, 4)
    I.flags.writeable = W.flags.writeable = False
    return I, W


def farthest_point_sampling(points: np.ndarray, n: int, seeds: np.ndarray | None = None) -> np.ndarray:
    """Indices (n,) into points (M, 3) chosen greedily farthest from the seeds (S, 3) and each other.

    The running min-distance is updated incrementally (O(n * M), no M x M matrix). Without seeds,
    sampling starts at the point farthest from the centroid (deterministic).
    """
    M = len(points)
    n = min(n, M)
    out = np.empty(n, np.int64)
    if n == 0:
        return out
    if seeds is not None and len(seeds):
        diff = points[:, None, :] - np.asarray(seeds, np.float64)[None, :, :]
        dmin = np.einsum("msk,msk->ms", diff, diff).min(axis=1)
    else:
        c = points - points.mean(axis=0)
        dmin = np.einsum("mk,mk->m", c, c)
    for i in range(n):
        j = int(np.argmax(dmin))
        out[i] = j
        d = points - points[j]
        dmin = np.minimum(dmin, np.einsum("mk,mk->m", d, d))
    return out


def object_image(
    cloud: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, pixel_m: float, radius_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Mask of the cloud in a scaled, cropped virtual image whose pixel spans about ``pixel_m`` at the object.

    cloud: (N, 3) float64 m world; K (3, 3); T_world_cam (4, 4). The image is only ever
    scaled down (factor <= 1) and cropped to the cloud's bounding box plus a margin.
    Returns (mask (h, w) bool, Kc (3, 3) camera matrix of that image, uv (N, 2) cloud pixels (col, row)
    in it, pixel size in metres at the median object depth).
    """
    uv, z = project_points(cloud, K, T_world_cam)
    zmed = float(np.median(z)) if len(z) else 1.0
    f = 0.5 * (K[0, 0] + K[1, 1])
    s = float(min(1.0, zmed / (f * pixel_m)))
    Ks = scale_intrinsics(K, s)
    uvs = (uv + 0.5) * s - 0.5
    pad = int(np.ceil(radius_m * f * s / zmed)) + 3
    c0, r0 = np.floor(uvs.min(axis=0)).astype(int) - pad if len(uvs) else (0, 0)
    c1, r1 = np.ceil(uvs.max(axis=0)).astype(int) + pad + 1 if len(uvs) else (1, 1)
    Ks[0, 2] -= c0
    Ks[1, 2] -= r0
    uvs = uvs - np.array([c0, r0])
    mask = splat_mask(cloud, Ks, T_world_cam, (int(r1 - r0), int(c1 - c0)), radius_m)
    return mask, Ks, uvs, zmed / (f * s)


def cloud_tree(cloud: np.ndarray | cKDTree) -> cKDTree:
    """The cKDTree of a cloud (M, 3) m, or the tree itself when it is one (a caller that searches a frame's
    cloud more than once builds it once)."""
    return cloud if isinstance(cloud, cKDTree) else cKDTree(np.asarray(cloud, np.float64).reshape(-1, 3))
