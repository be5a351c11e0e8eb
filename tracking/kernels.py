"""Compiled inner loops (numba) of the tracker: Algorithm 1's iterations, nearest-point searches, DBSCAN, voxel
grouping and the arm z-buffer.

Their numpy form was mostly call overhead over small arrays (a solver iteration is a few hundred flops per
keypoint but ~40 array calls and a KD-tree query; a cKDTree is built for a few dozen queries). These kernels do the
same arithmetic in the same order as that numpy code, so keypoints stay bit-identical unless a tie between equally
distant points is broken differently. Neighbour searches use slabs of x or grid cells ordered by counting / radix
sorts, linear in the points. Compiled once per machine (``cache=True`` keeps the machine code beside this file, or
in ``NUMBA_CACHE_DIR``); ``warm_up`` loads them all.
"""

from __future__ import annotations

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)


@_jit
def _sq_dist(x0: float, x1: float, x2: float, pts: np.ndarray, j: int) -> float:
    """Squared distance from (x0, x1, x2) to pts[j] (pts: (M, 3))."""
    d0, d1, d2 = x0 - pts[j, 0], x1 - pts[j, 1], x2 - pts[j, 2]
    return d0 * d0 + d1 * d1 + d2 * d2


@_jit
def _insert(d2: float, j: int, best_d: np.ndarray, best_i: np.ndarray, found: int, k: int) -> int:
    """Insert cloud point j at squared distance d2 into the sorted (nearest first) top-k lists; -> new count."""
    if found == k and d2 >= best_d[k - 1]:
        return found
    pos = found if found < k else k - 1
    while pos > 0 and best_d[pos - 1] > d2:
        if pos < k:
            best_d[pos] = best_d[pos - 1]
            best_i[pos] = best_i[pos - 1]
        pos -= 1
    best_d[pos] = d2
    best_i[pos] = j
    return found + 1 if found < k else k


@_jit
def _x_buckets(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray]:
    """Cloud points pts (M, 3) m counting-sorted into M // 4 + 1 equal slabs of x: (the points in slab order
    (M, 3), the slabs' starts (B + 1,) into them, the first slab's lower x, the slab width (m), the index in pts
    of each (M,)). Linear time: a comparison sort of a few thousand points costs more than the solve."""
    M = pts.shape[0]
    B = M // 4 + 1
    lo, hi = pts[:, 0].min(), pts[:, 0].max()
    w = max((hi - lo) / B, 1e-9) * (1.0 + 1e-12)  # the largest x falls into the last slab
    slab = np.empty(M, np.int64)
    start = np.zeros(B + 1, np.int64)
    for j in range(M):
        slab[j] = min(int((pts[j, 0] - lo) / w), B - 1)
        start[slab[j] + 1] += 1
    for b in range(B):
        start[b + 1] += start[b]
    fill = start[:-1].copy()
    out = np.empty((M, 3))
    index = np.empty(M, np.int64)
    for j in range(M):
        out[fill[slab[j]]] = pts[j]
        index[fill[slab[j]]] = j
        fill[slab[j]] += 1
    return out, start, lo, w, index


@_jit
def _slab_range(x0: float, r: float, lo: float, w: float, B: int) -> tuple[int, int]:
    """First and last of the B slabs (``_x_buckets``: lower x lo, width w) that hold x within r of x0."""
    b0 = min(max(int(np.floor((x0 - r - lo) / w)), 0), B - 1)
    b1 = min(max(int(np.floor((x0 + r - lo) / w)), 0), B - 1)
    return b0, b1


@_jit
def _knn_slabs(
    x0: float, x1: float, x2: float, pts: np.ndarray, start: np.ndarray, lo: float, w: float, k: int,
    best_d: np.ndarray, best_i: np.ndarray, bound2: float = np.inf,
) -> int:
    """The k nearest points to (x0, x1, x2) of pts, start, lo, w (``_x_buckets``) into best_d (squared
    distances) and best_i, nearest first: the slabs are visited outwards from x0's, each side until its x gap
    alone exceeds the k-th distance, or reaches sqrt(bound2) (then only the nearest within it are complete).
    Returns how many were found (k unless pts has fewer)."""
    B = start.shape[0] - 1
    home = min(max(int(np.floor((x0 - lo) / w)), 0), B - 1)
    found = 0
    for j in range(start[home], start[home + 1]):
        found = _insert(_sq_dist(x0, x1, x2, pts, j), j, best_d, best_i, found, k)
    right, left = home + 1, home - 1  # each side's next slab, -1 / B once that side is done
    while right < B or left >= 0:
        if right < B:
            g = lo + right * w - x0  # x gap to the slab
            if g > 0 and ((found == k and g * g > best_d[k - 1]) or g * g >= bound2):
                right = B
            else:
                for j in range(start[right], start[right + 1]):
                    found = _insert(_sq_dist(x0, x1, x2, pts, j), j, best_d, best_i, found, k)
                right += 1
        if left >= 0:
            g = x0 - (lo + (left + 1) * w)
            if g > 0 and ((found == k and g * g > best_d[k - 1]) or g * g >= bound2):
                left = -1
            else:
                for j in range(start[left], start[left + 1]):
                    found = _insert(_sq_dist(x0, x1, x2, pts, j), j, best_d, best_i, found, k)
                left -= 1
    return found


@_jit
def _refresh(
    x: np.ndarray, pts: np.ndarray, start: np.ndarray, lo: float, w: float, k: int, row: int, centre: np.ndarray,
    radius: np.ndarray, cand: np.ndarray, count: np.ndarray, best_d: np.ndarray, best_i: np.ndarray,
) -> np.ndarray:
    """The k nearest cloud points to x (3,), then the candidates of keypoint ``row``: every point within twice
    the k-th distance of x (centre x). pts, start, lo, w: ``_x_buckets``; both searches visit the slabs
    outwards from x's and stop where the x gap alone exceeds the distance sought. Returns cand, reallocated
    when a row outgrows it."""
    B = start.shape[0] - 1
    x0, x1, x2 = x[0], x[1], x[2]
    _knn_slabs(x0, x1, x2, pts, start, lo, w, k, best_d, best_i)
    r = 2.0 * np.sqrt(best_d[k - 1]) + 1e-9
    r2 = r * r
    b0, b1 = _slab_range(x0, r, lo, w, B)
    n = 0
    for j in range(start[b0], start[b1 + 1]):
        if _sq_dist(x0, x1, x2, pts, j) <= r2:
            n += 1
    if n > cand.shape[1]:
        grown = np.empty((cand.shape[0], 2 * n), np.int64)
        grown[:, : cand.shape[1]] = cand
        cand = grown
    n = 0
    for j in range(start[b0], start[b1 + 1]):
        if _sq_dist(x0, x1, x2, pts, j) <= r2:
            cand[row, n] = j
            n += 1
    count[row] = n
    centre[row] = x
    radius[row] = r
    return cand


@_jit
def _extent_projector(nb: np.ndarray, out: np.ndarray) -> None:
    """Projector (3, 3) into out onto the span of the principal directions of the points nb (k, 3) whose
    variance is at least 10 % of the largest (a surface's tangent plane, a line's tangent)."""
    k = nb.shape[0]
    mean = np.zeros(3)
    for a in range(k):
        for i in range(3):
            mean[i] += nb[a, i]
    c = np.empty((k, 3))
    for a in range(k):
        for i in range(3):
            c[a, i] = nb[a, i] - mean[i] / k
    cov = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            s = 0.0
            for a in range(k):
                s += c[a, i] * c[a, j]
            cov[i, j] = s
    lam, vec = np.linalg.eigh(cov)
    for i in range(3):
        for j in range(3):
            s = 0.0
            for m in range(3):
                if lam[m] >= 0.1 * lam[2]:
                    s += vec[i, m] * vec[j, m]
            out[i, j] = s


@_jit
def _edge_sweep(
    X: np.ndarray, e_first: np.ndarray, e_second: np.ndarray, e_wi: np.ndarray, e_wj: np.ndarray, e_rest: np.ndarray,
    reverse: bool,
) -> None:
    """One Gauss-Seidel sweep of the edge projections on X (N, 3) m in place, in the edges' order or reversed."""
    E = len(e_first)
    for a in range(E):
        e = E - 1 - a if reverse else a
        i, j = e_first[e], e_second[e]
        wsum = e_wi[e] + e_wj[e]
        d0, d1, d2 = X[j, 0] - X[i, 0], X[j, 1] - X[i, 1], X[j, 2] - X[i, 2]
        L = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if wsum > 0 and L > 1e-12:
            f = (L - e_rest[e]) / (L * wsum)
            s0, s1, s2 = f * d0, f * d1, f * d2
            X[i, 0] += e_wi[e] * s0
            X[i, 1] += e_wi[e] * s1
            X[i, 2] += e_wi[e] * s2
            X[j, 0] += -e_wj[e] * s0
            X[j, 1] += -e_wj[e] * s1
            X[j, 2] += -e_wj[e] * s2


@_jit
def solve_iterations(
    X: np.ndarray,
    e_first: np.ndarray,
    e_second: np.ndarray,
    e_wi: np.ndarray,
    e_wj: np.ndarray,
    e_rest: np.ndarray,
    pts: np.ndarray,
    k: int,
    max_slide_m: float,
    soft_idx: np.ndarray,
    soft_pos: np.ndarray,
    soft_w: np.ndarray,
    hard_idx: np.ndarray,
    hard_pos: np.ndarray,
    iterations: int,
    hidden: np.ndarray,
    hidden_reach_m: float,
    bend: np.ndarray,
    bend_k: float,
    tether: np.ndarray,
    tether_m: np.ndarray,
    symmetric_last: bool,
) -> None:
    """Algorithm 1's iterations on keypoints X (N, 3) m, in place.

    Edges (E,) in colour-class order (``tracking.solver.edge_colouring``): e_first, e_second int64 endpoints, e_wi,
    e_wj their inverse masses (0: fixed), e_rest m; no edges: E = 0. pts: (M, 3) m cloud, M = 0: no cloud
    projection. Each iteration: a Gauss-Seidel sweep of the edges (with symmetric_last, the last iteration's is
    one in their order and one in reverse order from the same start, averaged: one order alone leaves the residual
    on the classes swept first, a rope's every other edge twice as far from its rest length); every keypoint to
    the cloud (k <= 1: its nearest point; else nearest point plus its offset restricted to the local extent of its
    k nearest points, clamped to max_slide_m: keypoints slide below the cloud's point spacing); soft anchors
    soft_idx (S,) moved the fraction soft_w (S,) of the way to soft_pos (S, 3); hard anchors hard_idx (H,) put on
    hard_pos (H, 3).
    A keypoint flagged in hidden (N,) bool (out of sight) is projected only when its nearest point is within
    hidden_reach_m, and before each sweep moves the fraction bend_k of the way to where its chain runs smoothest:
    the least squared second difference over its neighbours bend (N, 4) int64, two and one back and one and two on
    along its chain (-1: none; a chain end or a junction, which has no such pair, is not moved). Nor is a hidden
    keypoint projected onto a point farther than tether_m (N,) m from its fixed neighbour, hard_pos[tether] (tether
    (N,) int64 into hard_idx, -1: none).
    The k nearest cloud points are searched among a keypoint's candidates (the points within a radius of where
    they were last gathered from the whole cloud, ``_refresh``), exact while the k-th distance is within that
    radius less the keypoint's move since; otherwise gathered again.
    """
    N = X.shape[0]
    M = pts.shape[0]
    kk = min(max(k, 1), M)
    if M > 0:
        pts, slabs, lo, w, _ = _x_buckets(pts)  # a keypoint's neighbours lie in a few slabs of x
    else:
        slabs, lo, w = np.zeros(1, np.int64), 0.0, 1.0
    centre = np.zeros((N, 3))
    radius = np.full(N, -1.0)
    count = np.zeros(N, np.int64)
    cand = np.empty((N, 64), np.int64)
    members = np.full((N, kk), -1, np.int64)
    proj = np.zeros((N, 3, 3))
    best_d = np.empty(kk)
    best_i = np.empty(kk, np.int64)
    srt = np.empty(kk, np.int64)
    nb = np.empty((kk, 3))
    back = np.empty_like(X)
    for it in range(iterations):
        for n in range(bend.shape[0]):
            if not hidden[n] or bend[n, 1] < 0 or bend[n, 2] < 0:
                continue
            b0, b1, b2, b3 = bend[n, 0], bend[n, 1], bend[n, 2], bend[n, 3]
            for i in range(3):
                acc = 2.0 * (X[b1, i] + X[b2, i])  # |X[b1] - 2 X[n] + X[b2]|^2
                wt = 4.0
                if b0 >= 0:  # |X[b0] - 2 X[b1] + X[n]|^2
                    acc += 2.0 * X[b1, i] - X[b0, i]
                    wt += 1.0
                if b3 >= 0:  # |X[n] - 2 X[b2] + X[b3]|^2
                    acc += 2.0 * X[b2, i] - X[b3, i]
                    wt += 1.0
                X[n, i] += bend_k * (acc / wt - X[n, i])
        if it < iterations - 1 or not symmetric_last:
            _edge_sweep(X, e_first, e_second, e_wi, e_wj, e_rest, False)
        else:
            back[:] = X
            _edge_sweep(X, e_first, e_second, e_wi, e_wj, e_rest, False)
            _edge_sweep(back, e_first, e_second, e_wi, e_wj, e_rest, True)
            for n in range(N):
                for i in range(3):
                    X[n, i] = 0.5 * (X[n, i] + back[n, i])
        if M > 0:
            for n in range(N):
                x = X[n]
                x0, x1, x2 = x[0], x[1], x[2]
                moved = np.sqrt(_sq_dist(x0, x1, x2, centre, n))
                found = 0
                if radius[n] >= 0:
                    for c in range(count[n]):
                        j = cand[n, c]
                        found = _insert(_sq_dist(x0, x1, x2, pts, j), j, best_d, best_i, found, kk)
                if radius[n] < 0 or found < kk or np.sqrt(best_d[kk - 1]) > radius[n] - moved:
                    cand = _refresh(x, pts, slabs, lo, w, kk, n, centre, radius, cand, count, best_d, best_i)
                if hidden[n] and best_d[0] > hidden_reach_m * hidden_reach_m:
                    continue  # out of sight, and the cloud near it is another part of the object
                p = pts[best_i[0]]
                if hidden[n] and tether[n] >= 0 and _sq_dist(p[0], p[1], p[2], hard_pos, tether[n]) > tether_m[n] ** 2:
                    continue  # out of sight, and that point lies beyond its edge from its fixed neighbour
                if k <= 1:
                    X[n, 0], X[n, 1], X[n, 2] = p[0], p[1], p[2]
                    continue
                srt[:] = np.sort(best_i)
                same = True
                for a in range(kk):
                    if srt[a] != members[n, a]:
                        same = False
                if not same:
                    for a in range(kk):
                        nb[a] = pts[best_i[a]]
                    _extent_projector(nb, proj[n])
                    members[n] = srt
                r0, r1, r2 = x0 - p[0], x1 - p[1], x2 - p[2]
                P = proj[n]
                # terms 0 and 2 first, as numpy's einsum adds a length-3 product: the numpy solver's bits
                o0 = (r0 * P[0, 0] + r2 * P[0, 2]) + r1 * P[0, 1]
                o1 = (r0 * P[1, 0] + r2 * P[1, 2]) + r1 * P[1, 1]
                o2 = (r0 * P[2, 0] + r2 * P[2, 2]) + r1 * P[2, 1]
                g = max_slide_m / max(np.sqrt(o0 * o0 + o1 * o1 + o2 * o2), max(max_slide_m, 1e-12))
                X[n, 0], X[n, 1], X[n, 2] = p[0] + o0 * g, p[1] + o1 * g, p[2] + o2 * g
        for a in range(len(soft_idx)):
            n = soft_idx[a]
            for i in range(3):
                X[n, i] = X[n, i] + soft_w[a] * (soft_pos[a, i] - X[n, i])
        for a in range(len(hard_idx)):
            for i in range(3):
                X[hard_idx[a], i] = hard_pos[a, i]


@_jit
def zbuffer_triangles(
    u: np.ndarray, v: np.ndarray, vc: np.ndarray, tri: np.ndarray, r0: int, nr: int, c0: int, nc: int, stride: int,
    fx: float, fy: float, cx: float, cy: float,
) -> np.ndarray:
    """Nearest camera z-depth (nr * nc,) float64 m (+inf: none) of triangles tri (F, 3) int64 over a pixel grid.

    u, v: (V,) float64 vertex pixel coordinates; vc: (V, 3) float64 camera-frame vertices (z > 0), m. Grid pixel
    (i, j) is image pixel (r0 + i stride, c0 + j stride). Each triangle is scanned row by row over the grid
    pixels whose centre its projection covers (its corners sorted top to bottom; a row's span between the long
    edge and the short edge beside it), at the z where that pixel's ray meets the triangle's plane, clipped to
    the triangle's depth range (an edge-on sliver's plane is ill-conditioned).
    """
    grid = np.full(nr * nc, np.inf)
    for f in range(tri.shape[0]):
        a, b, c = tri[f, 0], tri[f, 1], tri[f, 2]
        if v[b] < v[a]:  # a stable sort of the three corners by v: top (a), middle (b), bottom (c)
            a, b = b, a
        if v[c] < v[b]:
            b, c = c, b
            if v[b] < v[a]:
                a, b = b, a
        vt, vm, vb = v[a], v[b], v[c]
        ilo = max(int(np.ceil((vt - r0) / stride)), 0)
        ihi = min(int(np.floor((vb - r0) / stride)), nr - 1)
        if ihi < ilo or not vb > vt:
            continue
        ut, um, ub = u[a], u[b], u[c]
        s_tb = (ub - ut) / (vb - vt)  # du / dv along the long edge and the two short ones (0 when flat)
        s_tm = (um - ut) / (vm - vt) if vm > vt else 0.0
        s_mb = (ub - um) / (vb - vm) if vb > vm else 0.0
        p0, p1, p2 = vc[a], vc[b], vc[c]
        e0, e1, e2 = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
        g0, g1, g2 = p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]
        n0, n1, n2 = e1 * g2 - e2 * g1, e2 * g0 - e0 * g2, e0 * g1 - e1 * g0
        off = n0 * p0[0] + n1 * p0[1] + n2 * p0[2]
        zmin = min(min(p0[2], p1[2]), p2[2])
        zmax = max(max(p0[2], p1[2]), p2[2])
        for i in range(ilo, ihi + 1):
            y = float(r0 + i * stride)
            x_long = ut + (y - vt) * s_tb
            x_short = ut + (y - vt) * s_tm if y < vm else um + (y - vm) * s_mb
            jlo = max(int(np.ceil((min(x_long, x_short) - c0) / stride)), 0)
            jhi = min(int(np.floor((max(x_long, x_short) - c0) / stride)), nc - 1)
            ry = n1 * ((y - cy) / fy)
            for j in range(jlo, jhi + 1):
                den = n0 * ((c0 + j * stride - cx) / fx) + ry + n2
                z = min(max(off / (den if den != 0 else 1e-300), zmin), zmax)
                k = i * nc + j
                if z < grid[k]:
                    grid[k] = z
    return grid


@_jit
def _cells(points: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, int]:
    """Points (N, 3) m, N > 0, binned into the cubic cells floor(p / size) of edge size m: (order (N,) the points
    sorted by cell, cell_key (C,) sorted keys of the occupied cells, start (C + 1,) their ranges in order, key (N,)
    each point's, Dy, Dz). A key is (x Dy + y) Dz + z of the cell's integer coordinates from the lowest occupied
    ones, padded by one cell on every side, so the key of a neighbouring cell is the key plus a constant offset;
    keys order the cells as (x, y, z) tuples do."""
    n = points.shape[0]
    c = np.empty((n, 3), np.int64)
    for a in range(n):
        for i in range(3):
            c[a, i] = int(np.floor(points[a, i] / size))
    for i in range(3):
        c[:, i] -= c[:, i].min() - 1
    Dy = c[:, 1].max() + 2
    Dz = c[:, 2].max() + 2
    key = (c[:, 0] * Dy + c[:, 1]) * Dz + c[:, 2]
    order = _argsort_keys(key)
    sk = key[order]
    m = 1
    for a in range(1, n):
        if sk[a] != sk[a - 1]:
            m += 1
    cell_key = np.empty(m, np.int64)
    start = np.empty(m + 1, np.int64)
    m = 0
    for a in range(n):
        if a == 0 or sk[a] != sk[a - 1]:
            cell_key[m] = sk[a]
            start[m] = a
            m += 1
    start[m] = n
    return order, cell_key, start, key, Dy, Dz


@_jit
def _argsort_keys(key: np.ndarray) -> np.ndarray:
    """Stable argsort (N,) int64 of non-negative int64 keys (N,): least-significant-digit radix sort, 11 bits a
    pass (two passes for keys below 2^22), linear time where a comparison sort of a few thousand keys costs
    ~0.3 ms here."""
    n = key.shape[0]
    order = np.arange(n)
    tmp = np.empty(n, np.int64)
    top = key.max() if n else 0
    shift = 0
    while shift == 0 or (shift < 63 and (top >> shift) > 0):
        count = np.zeros(2049, np.int64)
        for a in range(n):
            count[((key[order[a]] >> shift) & 2047) + 1] += 1
        for d in range(2048):
            count[d + 1] += count[d]
        for a in range(n):
            d = (key[order[a]] >> shift) & 2047
            tmp[count[d]] = order[a]
            count[d] += 1
        order, tmp = tmp, order
        shift += 11
    return order


@_jit
def voxel_centroids(points: np.ndarray, voxel_m: float, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) m, N > 0, grouped by voxel floor((p - origin) / voxel_m), origin (3,) m: (centroids (M, 3) m
    of the points themselves in the voxels' (x, y, z) order (``_cells``), the voxel of each point (N,) int64).
    Each centroid sums its points in their order, as np.bincount would."""
    order, cell_key, start, _, _, _ = _cells(points - origin, voxel_m)
    m = cell_key.shape[0]
    inv = np.empty(points.shape[0], np.int64)
    for g in range(m):
        for p in range(start[g], start[g + 1]):
            inv[order[p]] = g
    sums = np.zeros((m, 3))
    cnt = np.zeros(m)
    for a in range(points.shape[0]):
        for i in range(3):
            sums[inv[a], i] += points[a, i]
        cnt[inv[a]] += 1.0
    for g in range(m):
        for i in range(3):
            sums[g, i] /= cnt[g]
    return sums, inv


@_jit
def _find(parent: np.ndarray, a: int) -> int:
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@_jit
def _scan_pairs(
    points: np.ndarray, eps2: float, order: np.ndarray, cell_key: np.ndarray, start: np.ndarray, Dy: int, Dz: int,
    pi: np.ndarray, pj: np.ndarray, pd: np.ndarray,
) -> int:
    """The pairs of ``_pairs_within`` (points (N, 3) here sorted by cell: point p is the input's order[p]), the
    first len(pi) of them written into pi, pj, pd; -> their number."""
    C = cell_key.shape[0]
    cap = pi.shape[0]
    n = 0
    for col in range(5):  # (dx, dy) = (0, 0), (0, 1), (1, -1), (1, 0), (1, 1); dz from -1 (0 in the cell's own)
        dx = 0 if col < 2 else 1
        dy = col if col < 2 else col - 3
        base = (dx * Dy + dy) * Dz
        b = 0
        for a in range(C):
            lo = cell_key[a] + base - (1 if col > 0 else 0)
            while b < C and cell_key[b] < lo:
                b += 1
            for c in range(b, C):
                if cell_key[c] - cell_key[a] - base > 1:
                    break
                for p in range(start[a], start[a + 1]):
                    x0, x1, x2 = points[p, 0], points[p, 1], points[p, 2]
                    for q in range(p + 1 if c == a else start[c], start[c + 1]):
                        d0 = x0 - points[q, 0]
                        d1 = x1 - points[q, 1]
                        d2 = x2 - points[q, 2]
                        d = d0 * d0 + d1 * d1 + d2 * d2
                        if d <= eps2:
                            if n < cap:
                                pi[n] = order[p]
                                pj[n] = order[q]
                                pd[n] = d
                            n += 1
    return n


@_jit
def _pairs_within(
    points: np.ndarray, eps2: float, order: np.ndarray, cell_key: np.ndarray, start: np.ndarray, Dy: int, Dz: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pair of points (N, 3) m within sqrt(eps2) of each other once, from ``_cells`` of edge >= that:
    (i (P,) int64, j (P,) int64, squared distance (P,) float64). The cells beside a cell are found by walking the
    sorted keys once per forward (dx, dy) column (5 walks: the cell itself and 13 of its 26 neighbours); written
    into arrays of 16 pairs a point (scanned again into larger ones when there are more)."""
    sorted_points = points[order]
    cap = 16 * points.shape[0]
    pi, pj, pd = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap)
    n = _scan_pairs(sorted_points, eps2, order, cell_key, start, Dy, Dz, pi, pj, pd)
    if n > cap:
        pi, pj, pd = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n)
        _scan_pairs(sorted_points, eps2, order, cell_key, start, Dy, Dz, pi, pj, pd)
    return pi[:n], pj[:n], pd[:n]


@_jit
def dbscan(points: np.ndarray, eps_m: float, min_points: int) -> np.ndarray:
    """DBSCAN labels (N,) int64 of points (N, 3) m: 0..k-1 by each cluster's first core point, -1 noise.

    A point is core when at least min_points points (itself included) lie within eps_m; clusters are the
    connected components of core points linked within eps_m; a non-core point within eps_m of a core point
    takes the cluster of the nearest one (the lower index on a tie). Neighbours are searched in cells of edge eps_m.
    """
    n = points.shape[0]
    lab = np.full(n, -1, np.int64)
    if n == 0:
        return lab
    order, cell_key, start, _, Dy, Dz = _cells(points, eps_m * (1.0 + 1e-9))  # a pair eps_m apart: adjacent cells
    pi, pj, pd = _pairs_within(points, eps_m * eps_m, order, cell_key, start, Dy, Dz)
    count = np.ones(n, np.int64)  # the point itself
    for p in range(len(pi)):
        count[pi[p]] += 1
        count[pj[p]] += 1
    core = count >= min_points
    parent = np.arange(n)
    near_core = np.full(n, -1, np.int64)
    near_d2 = np.full(n, np.inf)
    for p in range(len(pi)):
        i, j, d = pi[p], pj[p], pd[p]
        if core[i] and core[j]:
            ri, rj = _find(parent, i), _find(parent, j)
            if ri != rj:
                parent[max(ri, rj)] = min(ri, rj)
        elif core[i] != core[j]:
            c, o = (i, j) if core[i] else (j, i)
            if d < near_d2[o] or (d == near_d2[o] and c < near_core[o]):
                near_core[o] = c
                near_d2[o] = d
    root_label = np.full(n, -1, np.int64)
    k = 0
    for i in range(n):
        if core[i]:
            r = _find(parent, i)
            if root_label[r] < 0:
                root_label[r] = k
                k += 1
            lab[i] = root_label[r]
    for i in range(n):
        if not core[i] and near_core[i] >= 0:
            lab[i] = lab[near_core[i]]
    return lab


@_jit
def nearest(X: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N,) m from each point X (N, 3) m to its nearest point of pts (M, 3) m, M > 0, and that point's
    index (N,) int64 (the solver's slab search: no KD-tree to build for a few hundred queries)."""
    slab_pts, start, lo, w, index = _x_buckets(pts)
    best_d = np.empty(1)
    best_i = np.empty(1, np.int64)
    dist = np.empty(X.shape[0])
    idx = np.empty(X.shape[0], np.int64)
    for n in range(X.shape[0]):
        _knn_slabs(X[n, 0], X[n, 1], X[n, 2], slab_pts, start, lo, w, 1, best_d, best_i)
        dist[n] = np.sqrt(best_d[0])
        idx[n] = index[best_i[0]]
    return dist, idx


@_jit
def lift_median(pix: np.ndarray, uv: np.ndarray, cloud: np.ndarray, radius: float, k: int) -> np.ndarray:
    """Per query pix (P, 3) (image points, z 0): the per-coordinate median (P, 3) of the cloud (N, 3) points
    whose image points uv (N, 3) (z 0) are among its k nearest and closer than radius, else of its nearest one.
    N > 0, k >= 1."""
    slab_uv, start, lo, w, index = _x_buckets(uv)
    k = min(k, uv.shape[0])
    best_d = np.empty(k)
    best_i = np.empty(k, np.int64)
    vals = np.empty(k)
    out = np.empty((pix.shape[0], 3))
    r2 = radius * radius
    for n in range(pix.shape[0]):
        found = _knn_slabs(pix[n, 0], pix[n, 1], pix[n, 2], slab_uv, start, lo, w, k, best_d, best_i, r2)
        m = 0
        while m < found and best_d[m] < r2:
            m += 1
        if m == 0:  # none within the radius: the nearest
            _knn_slabs(pix[n, 0], pix[n, 1], pix[n, 2], slab_uv, start, lo, w, 1, best_d, best_i)
            m = 1
        for c in range(3):
            for a in range(m):
                vals[a] = cloud[index[best_i[a]], c]
            v = np.sort(vals[:m])
            out[n, c] = 0.5 * (v[(m - 1) // 2] + v[m // 2])
    return out


@_jit
def near_any(points: np.ndarray, ref: np.ndarray, r_m: float) -> np.ndarray:
    """(N,) bool: points (N, 3) m closer than r_m (strictly, as a cKDTree's distance_upper_bound) to some point
    of ref (R, 3) m; each point scans the slabs of x (``_x_buckets`` of ref) within r_m of it, to the first hit."""
    n = points.shape[0]
    out = np.zeros(n, np.bool_)
    if n == 0 or ref.shape[0] == 0:
        return out
    pts, start, lo, w, _ = _x_buckets(ref)
    B = start.shape[0] - 1
    r2 = r_m * r_m
    for i in range(n):
        x0, x1, x2 = points[i, 0], points[i, 1], points[i, 2]
        if x0 + r_m < lo or x0 - r_m > lo + B * w:
            continue
        b0, b1 = _slab_range(x0, r_m, lo, w, B)
        for j in range(start[b0], start[b1 + 1]):
            if _sq_dist(x0, x1, x2, pts, j) < r2:
                out[i] = True
                break
    return out


def warm_up() -> None:
    """Compile every kernel, or load them from numba's cache (~0.3 s), on tiny inputs of the types the tracker
    passes: a process calls this at start-up so that its first tracked frame does not wait for it (compiling
    them on a new machine takes ~30 s)."""
    X = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    one = np.ones(1)
    solve_iterations(
        X.copy(), np.zeros(1, np.int64), np.ones(1, np.int64), one, one, 0.01 * one, X + 0.001, 2, 0.003,
        np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(1, np.int64), X[:1].copy(), 1,
        np.zeros(2, np.bool_), 0.01, np.full((2, 4), -1, np.int64), 0.1,
        np.array([-1, 0]), np.array([0.0, 0.02]), True,
    )
    dbscan(X, 0.015, 2)
    voxel_centroids(X, 0.009, np.zeros(3))
    near_any(X, X + 0.001, 0.01)
    nearest(X, X + 0.001)
    lift_median(X, X + 0.001, X, 1.0, 2)
    uv = np.array([10.0, 20.0, 10.0])
    zbuffer_triangles(uv, np.array([10.0, 10.0, 20.0]), X[[0, 1, 1]] + [0.0, 0.0, 1.0], np.array([[0, 1, 2]]),
                      0, 20, 0, 20, 1, 500.0, 500.0, 10.0, 10.0)


if __name__ == "__main__":  # make kernels
    import time

    t0 = time.perf_counter()
    warm_up()
    if time.perf_counter() - t0 > 2.0:
        print(f"tracking kernels compiled in {time.perf_counter() - t0:.0f} s (cached in tracking/__pycache__)")
