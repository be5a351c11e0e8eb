"""Anchor detection (paper section III-D): skeleton leaves and junctions (1D), contour corners and sides (2D).

Both work on the segmented cloud only: it is projected into a scaled virtual image (``object_image``),
the image-space result is lifted back to 3D from the cloud.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.ndimage import convolve1d
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from tracking.geometry import object_image, project_points
from tracking.kernels import lift_median, nearest
from tracking.params import TrackingParams
from tracking.skeleton import JUNCTION, LEAF, skeleton_graph

BOUNDARY = 2
CORNER = 3
SIDE_SMOOTH_M = 0.12  # a cloth side's lifted contour is smoothed over this before it is measured, m
SIDE_LIFT_M = 0.008  # a contour pixel is lifted as the median of the cloud points projected within this, m
SIDE_LIFT_K = 16  # ... of at most this many of them


@dataclass(frozen=True)
class Skeleton3D:
    """A 1D object's skeleton lifted to 3D.

    nodes: (K, 3) float64 m world (leaf anchors pushed to the cloud's tips); kinds: (K,) LEAF / JUNCTION;
    branches: list of (node_a, node_b, polyline (M, 3) float64 m from a to b, ends = the nodes);
    component: (K,) int64 connected component per node, 0 = largest.
    """

    nodes: np.ndarray
    kinds: np.ndarray
    branches: list[tuple[int, int, np.ndarray]]
    component: np.ndarray


@dataclass(frozen=True)
class Contour3D:
    """A 2D object's boundary: grid boundary nodes and the four measured side lengths.

    sides: four (n_i, 3) float64 m polylines corner to corner: top (c0->c1, cols), right (c1->c2, rows),
    bottom (c3->c2, cols), left (c0->c3, rows); sides_uv: the same in image pixels (n_i, 2);
    lengths: (4,) m measured along the dense contour. Kc: (3, 3) camera matrix of the contour image;
    cloud_uv: (N, 2) cloud pixels in it; pixel_m: its pixel size at the object, m;
    T_world_cam: (4, 4) the camera pose.
    """

    sides: list[np.ndarray]
    sides_uv: list[np.ndarray]
    lengths: np.ndarray
    Kc: np.ndarray
    cloud_uv: np.ndarray
    pixel_m: float
    T_world_cam: np.ndarray


def lift_pixels(pix_uv: np.ndarray, cloud_uv: np.ndarray, cloud: np.ndarray, radius_px: float, k: int) -> np.ndarray:
    """Robust 3D of image points: median of up to k cloud points projected within radius_px, else the nearest.

    pix_uv: (P, 2) pixels (col, row); cloud_uv: (N, 2) pixels of cloud (N, 3) m. Returns (P, 3) float64 m
    (``tracking.kernels.lift_median``).
    """
    if len(pix_uv) == 0:
        return np.zeros((0, 3))
    return lift_median(
        _on_image(pix_uv), _on_image(cloud_uv), np.ascontiguousarray(cloud, np.float64), float(radius_px), int(k)
    )


def _on_image(uv: np.ndarray) -> np.ndarray:
    """Image points uv (N, 2) as (N, 3) float64 points at z 0, for the compiled 3D searches."""
    out = np.zeros((len(uv), 3))
    out[:, :2] = uv
    return out


def _smooth_polyline(p: np.ndarray, window: int) -> np.ndarray:
    """Moving average (window samples) of a polyline (M, 3), ends kept."""
    if len(p) <= 2 or window <= 1:
        return p
    w = min(window, len(p) - (1 - len(p) % 2))
    w = w if w % 2 == 1 else w - 1
    if w <= 1:
        return p
    h = w // 2
    pad = np.concatenate([np.repeat(p[:1], h, 0), p, np.repeat(p[-1:], h, 0)])
    c = np.cumsum(np.concatenate([np.zeros((1, 3)), pad]), axis=0)
    out = (c[w:] - c[:-w]) / w
    out[0], out[-1] = p[0], p[-1]
    return out


def _fit_line(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares line through points p (M, D): (centroid (D,), unit direction (D,))."""
    m = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - m, full_matrices=False)
    return m, vt[0]


def _leaf_on_axis(poly: np.ndarray, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A leaf (poly[0]) moved onto the axis of its branch's end, and a point further in on that axis.

    poly: (M, 3) m, the branch polyline starting at the leaf. A line is fitted to the polyline from
    a fifth of ``length_m`` to ``length_m`` of arc from the leaf; the leaf goes to its foot on that
    line (the skeleton's last pixel sits off the tube's axis by up to a radius, differently from one
    capture to the next).
    Returns (leaf (3,), inner (3,)); the polyline itself when it is too short to fit.
    """
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    seg = poly[(arc >= 0.2 * length_m) & (arc <= length_m)]  # the last pixels themselves are the doubt
    if len(seg) < 3 or arc[-1] < 0.5 * length_m:
        return poly[0], poly[min(len(poly) - 1, max(1, int(np.searchsorted(arc, length_m)) - 1))]
    c, d = _fit_line(seg)
    if (poly[0] - c) @ d < 0:
        d = -d  # towards the leaf
    leaf = c + float((poly[0] - c) @ d) * d
    return leaf, c


def _extend_leaf(
    leaf: np.ndarray, inward: np.ndarray, tree: cKDTree, cloud: np.ndarray, reach: float, slab: float
) -> np.ndarray:
    """Push a leaf (3,) m outward along the branch (inward -> leaf) to the cloud's tip within ``reach`` m.

    The leaf moves along that line by the mean reach of the cloud points within 4 mm of the farthest
    one (the lateral place of those 1-3 points is noise: 5 mm spread over camera seeds), then
    sideways onto the mean of the points within ``slab`` m of the tip along the line: the line is
    fitted to a few centimetres of skeleton, its direction error times the reach put the tip 1-4 mm
    aside, while a slab holds tens of full-resolution points."""
    t = leaf - inward
    n = np.linalg.norm(t)
    if n < 1e-9:
        return leaf
    t /= n
    idx = tree.query_ball_point(leaf, reach)
    if not idx:
        return leaf
    q = cloud[idx] - leaf
    s = q @ t
    lat = q - s[:, None] * t
    ok = (s > 0) & (np.linalg.norm(lat, axis=1) < 0.5 * reach)
    if not ok.any():
        return leaf
    tip = ok & (s > s[ok].max() - 0.004)
    st = float(s[tip].mean())
    near = (np.linalg.norm(lat, axis=1) < 0.5 * reach) & (s > st - slab) & (s <= st + 0.004)
    side = lat[near].mean(axis=0) if slab > 0 and near.sum() >= 5 else np.zeros(3)
    return leaf + st * t + side


def skeleton_3d(
    cloud: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, params: TrackingParams, all_components: bool
) -> Skeleton3D:
    """Leaves, junctions and branches of a 1D object's cloud (N, 3) float64 m, world frame.

    Projects the cloud to a mask, skeletonises, builds the MST, prunes spurs, merges junctions,
    lifts branches robustly to 3D and pushes leaves to the cloud's tips. ``all_components`` keeps
    every skeleton component (tracking) instead of the largest (initialisation).
    """
    empty = Skeleton3D(np.zeros((0, 3)), np.zeros(0, np.int64), [], np.zeros(0, np.int64))
    if len(cloud) < 3:
        return empty
    mask, _, uv, px_m = object_image(cloud, K, T_world_cam, params.mask_pixel_m, params.voxel_m)
    spur_px = params.spur_length_m / px_m
    g = skeleton_graph(mask, spur_px, params.junction_merge_m / px_m, spur_px)
    if len(g.node_rc) == 0:
        return empty
    keep = np.ones(len(g.node_rc), bool) if all_components else g.component == 0
    new_id = np.cumsum(keep) - 1
    branches_px = [(new_id[a], new_id[b], p) for a, b, p in g.branches if keep[a] and keep[b]]
    node_rc = g.node_rc[keep]
    kinds = g.node_kind[keep]
    allpix = np.concatenate([node_rc] + [p for _, _, p in branches_px])[:, ::-1]
    lifted = lift_pixels(allpix, uv, cloud, params.lift_radius_px, params.lift_k)
    nodes = lifted[: len(node_rc)].copy()
    off = len(node_rc)
    win = max(3, int(round(0.01 / px_m)))
    polys = []
    for a, b, p in branches_px:
        poly = lifted[off : off + len(p)].copy()
        off += len(p)
        poly[0], poly[-1] = nodes[a], nodes[b]
        polys.append((int(a), int(b), _smooth_polyline(poly, win)))
    tree = cKDTree(cloud)
    ext = nodes.copy()
    for a, b, poly in polys:
        for end, from_end in ((a, poly), (b, poly[::-1])):
            if kinds[end] == LEAF:
                leaf, inner = _leaf_on_axis(from_end, params.end_axis_m)
                ext[end] = _extend_leaf(leaf, inner, tree, cloud, params.end_extend_m, params.end_slab_m)
    out = []
    for a, b, poly in polys:
        poly = poly.copy()
        poly[0], poly[-1] = ext[a], ext[b]
        out.append((a, b, poly))
    return Skeleton3D(ext, kinds, out, g.component[keep])


def detect_anchors_1d(
    cloud: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, params: TrackingParams
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame 1D anchors: positions (A, 3) float64 m and kinds (A,) LEAF / JUNCTION, all components."""
    sk = skeleton_3d(cloud, K, T_world_cam, params, all_components=True)
    return sk.nodes, sk.kinds


def _resample(poly: np.ndarray, n: int) -> np.ndarray:
    """n points (n, D) equally spaced by arc length along a polyline (M, D)."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return np.repeat(poly[:1], n, axis=0)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, i]) for i in range(poly.shape[1])], axis=1)


def _polyline_length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def _quad_areas(c: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Areas (K,) of the quadrilaterals whose corners are the contour c (M, 2) points idx (K, 4), taken in
    contour order (shoelace)."""
    P = c[np.sort(idx, axis=1)]
    Q = np.roll(P, -1, axis=1)
    return 0.5 * np.abs((P[..., 0] * Q[..., 1] - Q[..., 0] * P[..., 1]).sum(axis=1))


def widest_corners(c: np.ndarray, ci: np.ndarray, fixed: np.ndarray, samples: int = 96) -> np.ndarray:
    """Free corners of a closed contour c (M, 2) px placed where, with the fixed ones, they span the largest
    quadrilateral (shoelace area of the four corners in contour order).

    ci: (4,) contour indices of the corners; fixed: (4,) bool, at least two True (held corners). Free corners
    are searched among ``samples`` contour points evenly spaced by index, then each in turn among the contour
    points between its neighbouring samples. A quadrilateral's corners are its contour's points farthest out: a
    hanging cloth's curved side, or an arm's notch in its top, moves the minimum-area rectangle's corners along a
    side, away from the corner. Returns (4,) int64 contour indices (ci itself with fewer than two fixed or none
    free)."""
    ci, fixed = np.asarray(ci, np.int64), np.asarray(fixed, bool)
    free = np.flatnonzero(~fixed)
    if fixed.sum() < 2 or len(free) == 0:  # of four corners, at most two free
        return ci
    M = len(c)
    cand = np.unique(np.linspace(0, M - 1, min(samples, M)).round().astype(np.int64))
    if len(free) == 1:
        combos = cand[:, None]
    else:
        a, b = np.triu_indices(len(cand), 1)
        combos = np.stack([cand[a], cand[b]], axis=1)
    idx = np.concatenate([np.broadcast_to(ci[fixed], (len(combos), int(fixed.sum()))), combos], axis=1)
    out = ci.copy()
    out[free] = combos[int(np.argmax(_quad_areas(c, idx)))]
    step = int(np.ceil(M / len(cand)))
    for _ in range(2):  # each free corner in turn at full resolution, the others held
        for k in free:
            near = (out[k] + np.arange(-step, step + 1)) % M
            trial = np.repeat(out[None], len(near), axis=0)
            trial[:, k] = near
            out[k] = near[int(np.argmax(_quad_areas(c, trial)))]
    return out


def refine_corners(
    c: np.ndarray, ci: np.ndarray, fixed: np.ndarray, inner: float = 0.2, smooth: int = 5, scale: float = 0.15,
    flat: float = 0.05,
) -> np.ndarray:
    """Free corners of a closed contour c (M, 2) px moved to where the contour turns, then onto the bisector of
    the two sides there.

    ci: (4,) increasing contour indices of the corners; fixed: (4,) bool corners left alone (held).
    A free corner is searched within the outer ``inner`` of each of its two sides (in samples). The turn at a
    contour point is the angle between the chords to the points ``scale`` of the shorter side's length before
    and after it along the contour (smoothed over ``smooth`` samples); at the sharpest turn (the weighted middle
    of the points turning within ``flat`` in cosine of the sharpest), lines are fitted to the contour one to
    three such lengths before and after it, and the corner becomes the window's point nearest the bisector of
    those lines through their meeting point. A cloth's sides are curves where it sags
    or curls, and its corners are where its boundary turns: the minimum-area rectangle's corners, or lines
    fitted to the middles of curved sides, meet away from them (a hanging cloth's bottom corners 20-50 mm off).
    On a rounded corner the turn is flat along the arc and slides with a pixel of contour jitter; the nearest
    point to the lines' meeting point is a flat minimum too; the bisector crosses the arc at one place.
    Lengths are along the contour, so its sampling does not matter. Returns (4,) contour indices.
    """
    M = len(c)
    ci = np.asarray(ci, np.int64)
    span = np.diff(np.append(ci, ci[0] + M))  # side k runs ci[k] -> ci[k+1], span[k] samples
    h = max(1, smooth // 2)
    kern = np.ones(2 * h + 1) / (2 * h + 1)
    cs = np.stack([np.convolve(np.concatenate([c[-h:, i], c[:, i], c[:h, i]]), kern, "valid") for i in range(2)], 1)
    cs3 = np.concatenate([cs, cs, cs])  # unwrapped three times: index i + M is sample i
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(cs3, axis=0), axis=1))])
    side = arc[ci + span + M] - arc[ci + M]  # (4,) side k's length along the contour, px

    def at(a: np.ndarray) -> np.ndarray:
        """Contour points (K, 2) at arc positions a (K,) px."""
        return np.stack([np.interp(a, arc, cs3[:, i]) for i in range(2)], axis=1)

    out = ci.copy()
    for k in np.flatnonzero(~np.asarray(fixed, bool)):
        lo, hi = int(round(inner * span[k - 1])), int(round(inner * span[k]))
        window = ci[k] + np.arange(-lo, hi + 1) + M
        L = scale * min(side[k - 1], side[k])
        if L <= 0:
            continue
        a = cs3[window] - at(arc[window] - L)
        b = at(arc[window] + L) - cs3[window]
        cos = (a * b).sum(axis=1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
        weight = np.maximum(cos.min() + flat - cos, 0.0)  # the sharpest points: a rounded corner's arc is flat
        j = int(window[int(round((weight * np.arange(len(window))).sum() / weight.sum()))])
        out[k] = j % M
        (p0, d0), (p1, d1) = (_fit_line(at(arc[j] + sgn * np.linspace(L, 3 * L, 9))) for sgn in (-1.0, 1.0))
        A = np.stack([d0, -d1], axis=1)
        if abs(np.linalg.det(A)) < 0.3:  # sides nearly parallel: no meeting point to trust
            continue
        x = p0 + np.linalg.solve(A, p1 - p0)[0] * d0
        q = cs3[j]
        d0 = d0 if (q - p0) @ d0 > 0 else -d0  # along the side before, into the corner
        d1 = d1 if (p1 - q) @ d1 > 0 else -d1  # along the side after, out of it
        bis = (d0 - d1) / max(float(np.linalg.norm(d0 - d1)), 1e-12)  # the corner's outward bisector
        r = cs3[window] - x
        out[k] = window[int(np.argmin(np.abs(r[:, 0] * bis[1] - r[:, 1] * bis[0])))] % M
    return out


def contour_3d(
    cloud: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    params: TrackingParams,
    held: np.ndarray | None = None,
    robust: bool = False,
) -> Contour3D | None:
    """Outer contour of a 2D object's cloud (N, 3) m split at four corners into lifted sides; None if no contour.

    Corners start at the contour points nearest the minimum-area rectangle's corners; a rectangle corner
    nearest a held point (``held`` (H, 3) m: TCPs of closed grippers, the cloth's held corners) is
    replaced by the contour point nearest that point's projection. With two corners held, the free ones
    start where they span the largest quadrilateral with them (``widest_corners``). Free corners then
    move to where the contour crosses their fitted sides' bisector (``refine_corners``). Corner 0 is the
    one nearest the image's top-left, sides follow the contour order.

    robust (initialisation): a contour pixel is lifted as the median of the cloud points projected
    near it (``SIDE_LIFT_M``, ``SIDE_LIFT_K``), not the nearest one: a boundary voxel is partly
    filled and its centroid wanders with the edge's dropouts (init spread 1.8 vs 2.0 mm). Per frame
    the nearest point is kept: on a folded cloth the median blends the fold's layers at the contour
    (measured: fast-speed cloth Abs 3.6 vs 3.8 mm, E<5 84 vs 72 %).
    """
    if len(cloud) < 10:
        return None
    mask, Kc, uv, px_m = object_image(cloud, K, T_world_cam, params.mask_pixel_m, params.voxel_m)
    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not cs:
        return None
    c = max(cs, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    if len(c) < 8:
        return None
    if cv2.contourArea(c.astype(np.float32), oriented=True) < 0:
        c = c[::-1]  # clockwise on screen (top-left -> top-right -> ...): side 0 is the top
    box = cv2.boxPoints(cv2.minAreaRect(c.astype(np.float32))).astype(np.float64)
    held = np.zeros((0, 3)) if held is None else np.asarray(held, np.float64).reshape(-1, 3)
    fixed = np.zeros(4, bool)
    if len(held):
        h_uv = project_points(held, Kc, T_world_cam)[0]
        cost = np.linalg.norm(h_uv[:, None, :] - box[None, :, :], axis=2)
        r, k = linear_sum_assignment(cost)
        box[k] = h_uv[r]
        fixed[k] = True
    ci = np.array([int(np.argmin(np.linalg.norm(c - b, axis=1))) for b in box])
    ci = widest_corners(c, ci, fixed)
    if len(np.unique(ci)) < 4:
        return None
    order = np.argsort(ci)
    ci = refine_corners(c, ci[order], fixed[order])
    if len(np.unique(ci)) < 4:
        return None
    start = int(np.argmin(c[ci].sum(axis=1)))
    ci = np.roll(ci, -start)
    c = np.roll(c, -ci[0], axis=0)
    ci = (ci - ci[0]) % len(c)
    ci = np.append(ci, len(c))
    cc = np.concatenate([c, c[:1]])
    dense = [cc[ci[k] : ci[k + 1] + 1] for k in range(4)]
    sides_uv = [dense[0], dense[1], dense[2][::-1], dense[3][::-1]]
    if robust:
        lifted = [lift_pixels(s, uv, cloud, SIDE_LIFT_M / px_m, SIDE_LIFT_K) for s in sides_uv]
    else:  # each contour pixel's nearest cloud pixel
        at = _on_image(np.concatenate(sides_uv))
        lifted = np.split(cloud[nearest(at, _on_image(uv))[1]], np.cumsum([len(s) for s in sides_uv])[:-1])
    lengths = np.array([_polyline_length(_smooth_polyline(p, max(3, int(0.01 / px_m)))) for p in lifted])
    return Contour3D(lifted, sides_uv, lengths, Kc, uv, px_m, np.asarray(T_world_cam, np.float64))


@lru_cache(maxsize=64)
def _savgol_weights(window: int) -> tuple[np.ndarray, np.ndarray]:
    """Savitzky-Golay smoothing weights (window,) for a quadratic, and the Vandermonde matrix (window, 3).

    The weights are the least-squares quadratic's value at the window's centre, solved as
    ``scipy.signal.savgol_coeffs(window, 2)`` solves it (bit for bit): importing scipy.signal
    imports scipy.stats, ~0.4 s of every ``trackdeform track`` command's start-up.
    """
    pos = window // 2 if window % 2 else window / 2 - 0.5  # an even window's centre lies between two samples
    x = np.arange(-pos, window - pos, dtype=np.float64)[::-1]  # convolution order
    unit = np.array([1.0, 0.0, 0.0])
    weights = np.linalg.lstsq(x ** np.arange(3).reshape(-1, 1), unit, rcond=None)[0]
    return weights, np.vander(np.arange(window, dtype=np.float64), 3)


def _savgol_quadratic(p: np.ndarray, window: int) -> np.ndarray:
    """Savitzky-Golay smoothing of a polyline p (M, D), quadratic over ``window`` (odd, <= M) samples.

    As ``scipy.signal.savgol_filter(p, window, 2, axis=0, mode="interp")`` (the first and last
    half-windows take one quadratic fitted to the first / last window), at a tenth of its cost.
    """
    coeffs, V = _savgol_weights(window)
    out = convolve1d(p, coeffs, axis=0, mode="nearest")
    h = window // 2
    head = np.linalg.lstsq(V, p[:window], rcond=None)[0]
    tail = np.linalg.lstsq(V, p[-window:], rcond=None)[0]
    out[:h] = V[:h] @ head
    out[-h:] = V[-h:] @ tail
    return out


def _resample_by_3d(xyz: np.ndarray, n: int, window: int) -> np.ndarray:
    """n points (n, 3) m along a side, equally spaced in 3D arc length on the smoothed side.

    xyz: (M, 3) m the side's lifted contour. It is smoothed first by a Savitzky-Golay filter
    (quadratic over ``window`` samples; it keeps the side's ends and bends unbiased): a lifted
    contour zig-zags with the depth noise, which lengthens the side where it is noisiest (10 %
    over camera seeds) and would move the nodes with the noise; the nodes are placed on the
    smoothed side, not re-lifted from single points.
    """
    if len(xyz) < 2:
        return np.repeat(xyz[:1], n, axis=0)
    w = min(window, len(xyz) - (1 - len(xyz) % 2))
    p = _savgol_quadratic(xyz, w) if w > 3 else xyz
    return _resample(p, n)


def grid_boundary(ct: Contour3D, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Coons-patch grid (rows, cols, 2) in the contour image, and the boundary nodes' 3D positions
    (rows, cols, 3) m (NaN inside).

    Each side is resampled evenly by 3D arc length on its smoothed lift (a corner is the mean of its
    two sides' ends); the Coons patch spans those nodes' projections, not the raw contour pixels,
    whose jitter would otherwise move every interior node (2.5 mm spread over camera seeds where
    the cloth is seen at a slant).
    """
    w = max(5, int(round(SIDE_SMOOTH_M / ct.pixel_m)))
    top3, right3, bottom3, left3 = (
        _resample_by_3d(ct.sides[k], n, w) for k, n in enumerate((cols, rows, cols, rows))
    )
    xyz = np.full((rows, cols, 3), np.nan)
    xyz[0, :], xyz[-1, :], xyz[:, 0], xyz[:, -1] = top3, bottom3, left3, right3
    xyz[0, 0] = 0.5 * (top3[0] + left3[0])
    xyz[0, -1] = 0.5 * (top3[-1] + right3[0])
    xyz[-1, 0] = 0.5 * (bottom3[0] + left3[-1])
    xyz[-1, -1] = 0.5 * (bottom3[-1] + right3[-1])
    ring = np.concatenate([xyz[0], xyz[-1], xyz[1:-1, 0], xyz[1:-1, -1]])
    uv = project_points(ring, ct.Kc, ct.T_world_cam)[0]
    top, bottom = uv[:cols], uv[cols : 2 * cols]
    left = np.concatenate([top[:1], uv[2 * cols : 2 * cols + rows - 2], bottom[:1]])
    right = np.concatenate([top[-1:], uv[2 * cols + rows - 2 :], bottom[-1:]])
    u = np.linspace(0.0, 1.0, cols)[None, :, None]
    v = np.linspace(0.0, 1.0, rows)[:, None, None]
    c00, c01, c10, c11 = top[0], top[-1], bottom[0], bottom[-1]
    ruled = (1 - v) * top[None] + v * bottom[None] + (1 - u) * left[:, None] + u * right[:, None]
    bil = (1 - u) * (1 - v) * c00 + u * (1 - v) * c01 + (1 - u) * v * c10 + u * v * c11
    return ruled - bil, xyz


def boundary_indices(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Grid boundary keypoint indices (2R+2C-4,) row-major, and their kinds CORNER / BOUNDARY."""
    idx = np.arange(rows * cols).reshape(rows, cols)
    b = np.zeros((rows, cols), bool)
    b[0, :] = b[-1, :] = b[:, 0] = b[:, -1] = True
    out = idx[b]
    corners = {0, cols - 1, (rows - 1) * cols, rows * cols - 1}
    kinds = np.array([CORNER if i in corners else BOUNDARY for i in out], np.int64)
    return out, kinds


def lift_grid(ct: Contour3D, cloud: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Grid keypoints (rows*cols, 3) m: the Coons grid in the image lifted robustly (``lift_pixels``), boundary
    nodes on the smoothed sides (``grid_boundary``)."""
    g, b = grid_boundary(ct, rows, cols)
    X = lift_pixels(g.reshape(-1, 2), ct.cloud_uv, cloud, 3.0, 8)
    b = b.reshape(-1, 3)
    on = np.isfinite(b[:, 0])
    X[on] = b[on]
    return X


def detect_anchors_2d(
    cloud: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, params: TrackingParams, held: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame 2D anchors: grid boundary points (A, 3) float64 m and kinds (A,) CORNER / BOUNDARY.

    held: (H, 3) m TCPs of closed grippers (held corners, see ``contour_3d``)."""
    ct = contour_3d(cloud, K, T_world_cam, params, held)
    if ct is None:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    R, C = params.grid_rows, params.grid_cols
    _, X = grid_boundary(ct, R, C)  # the boundary nodes only: the interior is not an anchor
    bi, kinds = boundary_indices(R, C)
    return X.reshape(-1, 3)[bi], kinds


__all__ = [
    "BOUNDARY",
    "CORNER",
    "JUNCTION",
    "LEAF",
    "Contour3D",
    "Skeleton3D",
    "boundary_indices",
    "contour_3d",
    "detect_anchors_1d",
    "detect_anchors_2d",
    "lift_grid",
    "lift_pixels",
    "skeleton_3d",
]
