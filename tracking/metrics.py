"""Evaluation metrics as the paper defines them (millimetres), plus ground-truth errors for simulation."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from tracking.kernels import nearest


def edge_lengths(X: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Edge lengths (E,) m of keypoints X (N, 3) m over edges (E, 2)."""
    return np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1)


def edge_rmse_mm(X: np.ndarray, edges: np.ndarray, rest: np.ndarray) -> float:
    """Abs: RMSE (mm) over edges of |x_i - x_j| - d_ij; X (N, 3) m, edges (E, 2), rest (E,) m."""
    if len(edges) == 0:
        return 0.0
    return float(1e3 * np.sqrt(np.mean((edge_lengths(X, edges) - rest) ** 2)))


def chamfer_mm(X: np.ndarray, cloud: np.ndarray | cKDTree) -> float:
    """CD: mean (mm) over keypoints X (N, 3) m of the distance to the nearest segmented point (M, 3) m (or
    of a cKDTree's; without one, ``tracking.kernels.nearest``, cheaper than building a tree)."""
    if isinstance(cloud, cKDTree):
        return float(1e3 * np.mean(cloud.query(X)[0])) if cloud.n else float("inf")
    if len(cloud) == 0:
        return float("inf")
    X = np.ascontiguousarray(X, np.float64).reshape(-1, 3)
    return float(1e3 * np.mean(nearest(X, np.ascontiguousarray(cloud, np.float64).reshape(-1, 3))[0]))


def percent_below(values: np.ndarray, threshold: float) -> float:
    """Percentage (0-100) of per-frame values strictly below threshold (E<5: Abs mm < 5; F<10: CD mm < 10)."""
    v = np.asarray(values, np.float64)
    return float(100.0 * np.mean(v < threshold)) if len(v) else float("nan")


def sequence_summary(abs_mm: np.ndarray, cd_mm: np.ndarray) -> dict[str, float]:
    """Paper table figures from per-frame Abs (T,) and CD (T,) in mm: Abs, E<5, CD, F<10."""
    return {
        "Abs": float(np.mean(abs_mm)),
        "E<5": percent_below(abs_mm, 5.0),
        "CD": float(np.mean(cd_mm)),
        "F<10": percent_below(cd_mm, 10.0),
    }


def segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (N, M) m from each point (N, 3) m to each segment from a (M, 3) to b (M, 3) m."""
    ab = b - a
    L2 = np.maximum(np.einsum("mk,mk->m", ab, ab), 1e-18)
    ap = points[:, None, :] - a[None]
    t = np.clip(np.einsum("nmk,mk->nm", ap, ab) / L2, 0.0, 1.0)
    d = ap - t[..., None] * ab[None]
    return np.sqrt(np.einsum("nmk,nmk->nm", d, d))


def distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance (N,) m from points (N, 3) to the polyline (M, 3) m (segments; N x (M-1) work, N small)."""
    return segment_distances(points, polyline[:-1], polyline[1:]).min(axis=1)


def split_chains(samples: np.ndarray) -> list[np.ndarray]:
    """Concatenated centreline samples (M, 3) m (a branched rope's trunk then its branches) split into
    chains where consecutive samples jump by more than four times their median spacing."""
    if len(samples) < 3:
        return [samples]
    step = np.linalg.norm(np.diff(samples, axis=0), axis=1)
    jumps = np.nonzero(step > 4.0 * np.median(step))[0] + 1
    return [c for c in np.split(samples, jumps) if len(c) >= 2]


def surface_error_mm(X: np.ndarray, samples: np.ndarray, radius: float, polyline: bool = False) -> float:
    """GT keypoint error: RMSE (mm) of max(0, distance to the true centreline / mid-surface - radius).

    X: (N, 3) m; samples: (M, 3) m dense centreline or mid-surface samples. With ``polyline`` (1D objects)
    they are chains (see :func:`split_chains`) measured to their segments, else the nearest sample counts.
    radius: m (half thickness for cloth). The one GT metric of ``trackdeform track`` and the benchmarks.
    """
    if polyline:
        d = np.min(np.stack([distance_to_polyline(X, c) for c in split_chains(samples)]), axis=0)
    else:
        d = cKDTree(samples).query(X)[0]
    e = np.maximum(0.0, d - radius)
    return float(1e3 * np.sqrt(np.mean(e**2)))


def surface_errors_mm(X: np.ndarray, samples: np.ndarray, radius: float, polyline: bool = False,
                      chunk: int = 32) -> np.ndarray:
    """:func:`surface_error_mm` of F frames at once (the report's GT column over a whole run): (F,) mm.

    X: (F, N, 3) m keypoints; samples: (F, M, 3) m the frames' centreline / mid-surface samples. A 1D
    object's chains are its consecutive samples without the jumps :func:`split_chains` cuts at; frames go
    through in chunks of ``chunk`` so the (chunk, N, M) work arrays stay small.
    """
    X, S = np.asarray(X, np.float64), np.asarray(samples, np.float64)
    out = np.empty(len(X))
    for lo in range(0, len(X), chunk):
        x, s = X[lo:lo + chunk], S[lo:lo + chunk]
        if polyline and S.shape[1] >= 2:
            a, ab = s[:, :-1], np.diff(s, axis=1)  # (C, M-1, 3) segments
            L2 = np.einsum("cmk,cmk->cm", ab, ab)
            if S.shape[1] >= 3:  # no segment across a jump between chains (split_chains' rule)
                step = np.sqrt(L2)
                jump = step > 4.0 * np.median(step, axis=1, keepdims=True)
            else:
                jump = np.zeros(L2.shape, bool)
            ap = x[:, :, None, :] - a[:, None]  # (C, N, M-1, 3)
            t = np.clip(np.einsum("cnmk,cmk->cnm", ap, ab) / np.maximum(L2, 1e-18)[:, None], 0.0, 1.0)
            d = ap - t[..., None] * ab[:, None]
            d2 = np.einsum("cnmk,cnmk->cnm", d, d)
            d2[np.broadcast_to(jump[:, None], d2.shape)] = np.inf
            dist = np.sqrt(d2.min(axis=2))
        else:
            diff = x[:, :, None, :] - s[:, None]
            dist = np.sqrt(np.einsum("cnmk,cnmk->cnm", diff, diff).min(axis=2))
        e = np.maximum(0.0, dist - radius)
        out[lo:lo + chunk] = 1e3 * np.sqrt(np.mean(e**2, axis=1))
    return out


def anchor_error_mm(pred: np.ndarray, true: np.ndarray) -> float:
    """Mean distance (mm) between predicted anchors (A, 3) m and true anchors (B, 3) m matched by Hungarian."""
    if len(pred) == 0 or len(true) == 0:
        return float("nan")
    C = np.linalg.norm(pred[:, None, :] - true[None, :, :], axis=2)
    r, c = linear_sum_assignment(C)
    return float(1e3 * C[r, c].mean())
