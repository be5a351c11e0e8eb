"""Object classification 1D vs 2D from local PCA eigenvalue ratios (paper section III-D.1)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from tracking.params import TrackingParams
from tracking.segmentation import voxel_downsample


@dataclass(frozen=True)
class ObjectClass:
    """Classification result: kind "1d" or "2d" and the median ratios lambda2/lambda1, lambda3/lambda2."""

    kind: str
    line_ratio: float
    plane_ratio: float


def local_eigenvalues(points: np.ndarray, seeds: np.ndarray, radius_m: float, k: int) -> np.ndarray:
    """Covariance eigenvalues (S, 3), descending, of the neighbourhoods (<= k points within radius_m)
    of seeds (S, 3) in points (N, 3), metres. Neighbourhoods with fewer than 5 points give NaN rows."""
    tree = cKDTree(points)
    k = min(k, len(points))
    d, idx = tree.query(seeds, k=k, distance_upper_bound=radius_m)
    d = d.reshape(len(seeds), k)
    idx = idx.reshape(len(seeds), k)
    w = np.isfinite(d)
    nb = points[np.minimum(idx, len(points) - 1)]
    cnt = w.sum(axis=1)
    wf = w[..., None].astype(np.float64)
    mean = (nb * wf).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    c = (nb - mean[:, None, :]) * wf
    cov = np.einsum("ski,skj->sij", c, c) / np.maximum(cnt - 1, 1)[:, None, None]
    ev = np.linalg.eigvalsh(cov)[:, ::-1]
    ev[cnt < 5] = np.nan
    return ev


def classify_object(points: np.ndarray, params: TrackingParams) -> ObjectClass:
    """Classify a segmented cloud (N, 3) float64 m as 1D (line-like) or 2D (surface-like).

    The cloud is voxelised at ``voxel_m`` first (so k neighbours span the radius). Seeds are drawn
    with ``params.seed``; 1D when the median lambda2/lambda1 is below
    ``line_ratio_max``, otherwise 2D (lambda3/lambda2 is reported; a 2D surface has it small).
    """
    points = voxel_downsample(points, params.voxel_m)
    rng = np.random.default_rng(params.seed)
    n = min(params.classify_seeds, len(points))
    seeds = points[rng.choice(len(points), size=n, replace=False)]
    ev = local_eigenvalues(points, seeds, params.classify_radius_m, params.classify_k)
    ok = np.all(np.isfinite(ev), axis=1) & (ev[:, 0] > 0)
    if not ok.any():
        return ObjectClass("1d", float("nan"), float("nan"))
    ev = ev[ok]
    r21 = float(np.median(ev[:, 1] / ev[:, 0]))
    r32 = float(np.median(ev[:, 2] / np.maximum(ev[:, 1], 1e-18)))
    kind = "1d" if r21 < params.line_ratio_max else "2d"
    return ObjectClass(kind, r21, r32)
