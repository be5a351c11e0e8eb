"""Algorithm 1: Gauss-Seidel iterative projection (edge lengths, point cloud, anchors).

Edges are greedily coloured so that no two edges of a colour class share a vertex; projecting a
whole class at once is then exactly the sequential Gauss-Seidel sweep over that class.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tracking.params import TrackingParams

EdgeClassPlan = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]
"""One colour class of ``edge_plan``: (ends, w, wsum, movable, rest)."""


def edge_colouring(edges: np.ndarray, n_vertices: int) -> list[np.ndarray]:
    """Greedy edge colouring of edges (E, 2) int -> list of index arrays into edges, one per colour.

    No two edges in a class share a vertex (at most 2 * max_degree - 1 classes).
    """
    used: list[set[int]] = [set() for _ in range(n_vertices)]
    colour = np.empty(len(edges), np.int64)
    for e, (i, j) in enumerate(np.asarray(edges, np.int64)):
        taken = used[i] | used[j]
        c = 0
        while c in taken:
            c += 1
        colour[e] = c
        used[i].add(c)
        used[j].add(c)
    if len(edges) == 0:
        return []
    return [np.nonzero(colour == c)[0] for c in range(int(colour.max()) + 1)]


def edge_plan(
    edges: np.ndarray, rest: np.ndarray, inv_mass: np.ndarray, classes: list[np.ndarray]
) -> list[EdgeClassPlan]:
    """What ``project_edges`` needs of each colour class and does not change between sweeps: per class of C
    edges (ends (2C,) int64: the first endpoints then the second ones, w (2, C, 1) their inverse masses, the
    second ones negated, wsum (C,), movable (C,) bool wsum > 0 or None when every edge of the class has a free
    endpoint, rest (C,) m), so a sweep indexes only the keypoints, once."""
    plan = []
    for cls in classes:
        i, j = edges[cls, 0], edges[cls, 1]
        wi, wj = inv_mass[i], inv_mass[j]
        wsum = wi + wj
        movable = wsum > 0
        plan.append(
            (
                np.concatenate([i, j]),
                np.stack([wi, -wj])[:, :, None],
                wsum,
                None if movable.all() else movable,
                rest[cls],
            )
        )
    return plan


def project_edges(
    X: np.ndarray,
    edges: np.ndarray,
    rest: np.ndarray,
    inv_mass: np.ndarray,
    classes: list[np.ndarray],
    plan: list[EdgeClassPlan] | None = None,
) -> None:
    """One Gauss-Seidel sweep of edge-length projection, in place.

    X: (N, 3) float64 m; edges: (E, 2) int; rest: (E,) m; inv_mass: (N,) 1 free, 0 fixed (anchor).
    Each edge moves its free endpoints along the edge to length ``rest``, split by inverse mass
    (half each when both are free, as projective dynamics eq. 8). plan: ``edge_plan`` of these
    arguments when the caller sweeps many times (then edges, rest, inv_mass and classes are not read).
    """
    for ends, w, wsum, movable, r in plan if plan is not None else edge_plan(edges, rest, inv_mass, classes):
        C = len(r)
        P = X[ends]  # a class's edges share no keypoint: its first endpoints, then its second ones
        d = P[C:] - P[:C]
        L = np.sqrt(np.add.reduce(d * d, axis=1))  # np.linalg.norm(d, axis=1), without its checks
        if movable is None and np.minimum.reduce(L) > 1e-12:
            s = ((L - r) / (L * wsum))[:, None] * d
        else:  # an edge too short to have a direction or with both endpoints fixed stays
            ok = L > 1e-12 if movable is None else movable & (L > 1e-12)
            s = np.where(ok, (L - r) / np.where(ok, L * wsum, 1.0), 0.0)[:, None] * d
        X[ends] = P + (w * s).reshape(2 * C, 3)  # first endpoints + wi s, second ones - wj s


def extent_projectors(nb: np.ndarray) -> np.ndarray:
    """Projectors (n, 3, 3) onto the local extent of neighbourhoods nb (n, k, 3) m: the span of their principal
    directions whose variance is at least 10 % of the largest (a surface's tangent plane, a line's tangent)."""
    c = nb - np.add.reduce(nb, axis=1, keepdims=True) / nb.shape[1]  # nb.mean(axis=1), without its checks
    lam, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", c, c))
    keep = lam >= 0.1 * lam[:, -1:]
    return np.einsum("nij,nj,nkj->nik", vec, keep, vec)


def project_to_cloud(
    X: np.ndarray, tree: cKDTree, k: int, max_slide_m: float, cache: dict[str, np.ndarray] | None = None
) -> np.ndarray:
    """Project points X (n, 3) m onto the cloud in the tree -> (n, 3) float64 m.

    k <= 1: the nearest cloud point (the paper). Otherwise the nearest point plus the offset to X
    restricted to the local extent of the cloud (``extent_projectors`` of the k nearest points) and
    clamped to ``max_slide_m``; keypoints then slide below the cloud's point spacing instead of
    sticking to voxel centres. cache: a dict the caller passes to every call of one solve (the same
    points X, moving): a point's projector is computed again only when its k nearest cloud points change,
    in place in the cached (n, 3, 3) array.
    """
    pts = tree.data
    if k <= 1:
        return pts[tree.query(X)[1]]
    k = min(k, tree.n)
    nn = tree.query(X, k=k)[1].reshape(len(X), k)
    members = np.sort(nn, axis=1)  # a projector depends on the set of neighbours, not their order
    prev = cache.get("members") if cache is not None else None
    if prev is not None and prev.shape == members.shape:
        proj = cache["projectors"]
        redo = np.logical_or.reduce(members != prev, axis=1).nonzero()[0]
        if len(redo):
            proj[redo] = extent_projectors(pts[nn[redo]])
    else:
        proj = extent_projectors(pts[nn])
    if cache is not None:
        cache["members"], cache["projectors"] = members, proj
    p = pts[nn[:, 0]]
    off = np.einsum("nj,nij->ni", X - p, proj)
    n = np.sqrt(np.add.reduce(off * off, axis=1))[:, None]
    off *= max_slide_m / np.maximum(n, max(max_slide_m, 1e-12))  # 1 (exactly) up to max_slide_m
    return p + off


def solve_keypoints(
    X0: np.ndarray,
    edges: np.ndarray,
    rest: np.ndarray,
    anchor_idx: np.ndarray,
    anchor_pos: np.ndarray,
    cloud: np.ndarray | cKDTree,
    iterations: int,
    params: TrackingParams,
    classes: list[np.ndarray] | None = None,
    anchor_weight: np.ndarray | None = None,
) -> np.ndarray:
    """Solve problem (1) by Algorithm 1 from the warm start X0 (N, 3) m.

    edges (E, 2) int, rest (E,) m; anchor_idx (A,) int fixed at anchor_pos (A, 3) m; cloud (M, 3) m
    segmented points or a prebuilt cKDTree of them. anchor_weight (A,) in (0, 1]: 1 (default) fixes an
    anchor; below 1 the anchor's keypoint stays free in the edge and cloud projections and is moved
    that fraction of the way to its anchor after each iteration (a measured anchor with noise, which a
    hard constraint passes on to its edges). The ablation switches of ``params`` turn the anchor, edge
    and cloud projections off. Returns X (N, 3) float64, metres, world frame.
    """
    X = np.array(X0, np.float64, copy=True)
    N = len(X)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    rest = np.asarray(rest, np.float64)
    anchor_idx = np.asarray(anchor_idx, np.int64).reshape(-1)
    anchor_pos = np.asarray(anchor_pos, np.float64).reshape(-1, 3)
    use_anchors = params.use_anchors and len(anchor_idx) > 0
    w = np.ones(len(anchor_idx)) if anchor_weight is None else np.asarray(anchor_weight, np.float64).reshape(-1)
    hard = w >= 1.0
    hard_idx, hard_pos = anchor_idx[hard], anchor_pos[hard]
    soft_idx, soft_pos, soft_w = anchor_idx[~hard], anchor_pos[~hard], w[~hard, None]
    inv_mass = np.ones(N)
    if use_anchors:
        inv_mass[hard_idx] = 0.0
        X[anchor_idx] = anchor_pos
    if classes is None:
        classes = edge_colouring(edges, N)
    plan = edge_plan(edges, rest, inv_mass, classes)
    tree = None
    if params.use_cloud_projection:
        tree = cloud if isinstance(cloud, cKDTree) else (cKDTree(cloud) if len(cloud) else None)
    cache: dict[str, np.ndarray] = {}  # the cloud projection's local extents, reused while the neighbours stay
    edge_pass = params.use_edge_projection and len(edges) > 0
    soft_pass = use_anchors and len(soft_idx) > 0
    hard_pass = use_anchors and len(hard_idx) > 0
    for _ in range(iterations):
        if edge_pass:
            project_edges(X, edges, rest, inv_mass, classes, plan)
        if tree is not None:
            # every keypoint, the fixed ones too: they are put back on their anchors below, and a point's
            # projection does not depend on the others
            X = project_to_cloud(X, tree, params.surface_k, params.surface_slide_m, cache)
        if soft_pass:
            Xs = X[soft_idx]
            X[soft_idx] = Xs + soft_w * (soft_pos - Xs)
        if hard_pass:
            X[hard_idx] = hard_pos
    return X


def chain_tangents(X: np.ndarray, chains: list[np.ndarray]) -> np.ndarray:
    """Unit tangents (N, 3) of keypoints X (N, 3) m along their chains (index arrays, node to node):
    central differences inside a chain, one-sided at its ends (a keypoint on several chains, e.g. a
    junction, keeps the last one's)."""
    T = np.zeros_like(X)
    for ch in chains:
        if len(ch) >= 2:
            T[ch] = np.gradient(X[ch], axis=0)
    return T / np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-12)


def centre_on_ridge(
    X: np.ndarray,
    tangents: np.ndarray,
    tree: cKDTree,
    eye: np.ndarray,
    radius_m: float,
    k: int = 96,
    band_m: float = 0.003,
) -> np.ndarray:
    """Move points X (n, 3) m on a tube's visible skin to its ridge (the line nearest the camera).

    tangents: (n, 3) unit tube directions; tree: cKDTree of the cloud (m); eye: (3,) camera centre, m.
    The cloud within ``radius_m`` across and ``radius_m / 2`` along the tube (up to k points) is its
    cross-section there: across the tube (perpendicular to the tangent and the line of sight) a
    point goes to the middle of that section (between its 10th and 90th percentiles), along the
    line of sight to the median of the section's points within ``band_m`` of that middle. A
    keypoint's place across the tube is otherwise undetermined (edge lengths along the tube do not
    fix it) and the noise of the one point it was projected on decides it. Returns (n, 3) float64 m.
    """
    X = np.array(X, np.float64)
    n = len(X)
    if n == 0 or tree.n == 0:
        return X
    k = min(k, tree.n)
    d, nn = tree.query(X, k=k, distance_upper_bound=float(np.hypot(radius_m, 0.5 * radius_m)))
    d, nn = d.reshape(n, k), nn.reshape(n, k)
    rel = tree.data[np.minimum(nn, tree.n - 1)] - X[:, None, :]  # (n, k, 3)
    view = X - eye
    lat = np.cross(tangents, view)
    lat /= np.maximum(np.linalg.norm(lat, axis=1, keepdims=True), 1e-12)
    dep = view - np.einsum("nk,nk->n", view, tangents)[:, None] * tangents
    dep /= np.maximum(np.linalg.norm(dep, axis=1, keepdims=True), 1e-12)
    a = np.einsum("nki,ni->nk", rel, lat)  # across, m
    sec = np.isfinite(d) & (np.abs(np.einsum("nki,ni->nk", rel, tangents)) <= 0.5 * radius_m)
    sec &= np.abs(a) <= radius_m
    has = sec.sum(axis=1) >= 3
    across = np.zeros(n)
    if has.any():
        q = np.nanpercentile(np.where(sec[has], a[has], np.nan), [10.0, 90.0], axis=1)
        across[has] = 0.5 * (q[0] + q[1])
    band = sec & (np.abs(a - across[:, None]) <= band_m)
    z = np.where(band, np.einsum("nki,ni->nk", rel, dep), np.nan)
    on = has & band.any(axis=1)
    along_view = np.zeros(n)
    if on.any():
        along_view[on] = np.nanmedian(z[on], axis=1)
    return X + across[:, None] * lat + along_view[:, None] * dep
