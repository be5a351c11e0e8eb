"""Baseline trackers for ``trackdeform eval baselines``: coherent point drift and nearest neighbour only.

Both are pure numpy functions of the previous keypoints and the frame's segmented cloud; ``BaselineTracker``
runs one of them in place of Algorithm 2 inside the same pipeline, so segmentation, initialisation and
scoring are those of the full method. Neither uses anchors, edge lengths or the grippers.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from tracking.geometry import cloud_tree
from tracking.params import TrackingParams
from tracking.tracker import FrameResult, Tracker


def cpd_nonrigid(
    Y: np.ndarray,
    X: np.ndarray,
    beta_m: float = 0.05,
    lam: float = 2.0,
    w: float = 0.1,
    iterations: int = 30,
    tol: float = 1e-8,
) -> np.ndarray:
    """Non-rigid coherent point drift (Myronenko & Song 2010): GMM centroids Y (N, 3) m moved onto points
    X (M, 3) m -> (N, 3) m.

    beta_m: width of the Gaussian motion-coherence kernel G, m; lam: regularisation weight (lambda);
    w: outlier weight of the uniform component in (0, 1); iterations: EM steps (stops early once sigma^2
    changes by less than ``tol`` m^2). Vectorised: O(N M) per iteration.
    """
    Y = np.asarray(Y, np.float64)
    X = np.asarray(X, np.float64)
    N, D = Y.shape
    M = len(X)
    if M == 0 or N == 0:
        return Y.copy()
    G = np.exp(-np.sum((Y[:, None] - Y[None]) ** 2, axis=2) / (2.0 * beta_m**2))  # (N, N)
    d2 = np.sum((X[None] - Y[:, None]) ** 2, axis=2)  # (N, M)
    sigma2 = float(d2.sum() / (D * N * M))
    W = np.zeros((N, D))
    T = Y.copy()
    for _ in range(iterations):
        if sigma2 <= 1e-12:
            break
        d2 = np.sum((X[None] - T[:, None]) ** 2, axis=2)
        P = np.exp(-d2 / (2.0 * sigma2))
        c = (2.0 * np.pi * sigma2) ** (D / 2) * w / (1.0 - w) * N / M
        P /= P.sum(axis=0, keepdims=True) + c
        P1 = P.sum(axis=1)  # (N,)
        Pt1 = P.sum(axis=0)  # (M,)
        PX = P @ X  # (N, D)
        Np = float(P1.sum())
        A = P1[:, None] * G + lam * sigma2 * np.eye(N)
        W = np.linalg.solve(A, PX - P1[:, None] * Y)
        T = Y + G @ W
        prev = sigma2
        sigma2 = float((np.sum(Pt1 * np.sum(X**2, axis=1)) - 2.0 * np.sum(PX * T) + np.sum(P1 * np.sum(T**2, axis=1)))
                       / (Np * D))
        sigma2 = max(sigma2, 1e-10)
        if abs(prev - sigma2) < tol:
            break
    return T


def nearest_neighbour(Y: np.ndarray, X: np.ndarray | cKDTree) -> np.ndarray:
    """Each keypoint Y (N, 3) m moved to its nearest point of the cloud X (M, 3) m (or its cKDTree) -> (N, 3)."""
    tree = cloud_tree(X)
    if tree.n == 0:
        return np.asarray(Y, np.float64).copy()
    return np.asarray(tree.data[tree.query(Y)[1]], np.float64)


BASELINES = ("cpd", "nn")


class BaselineTracker(Tracker):
    """The pipeline's tracker with Algorithm 2 replaced by a baseline (``cpd`` or ``nn``) per frame.

    Initialisation, grasp indices, scoring and loss-of-track detection are the full method's
    (:class:`tracking.tracker.Tracker`), so only the per-frame update differs.
    """

    def __init__(self, params: TrackingParams, K: np.ndarray, T_world_cam: np.ndarray, method: str,
                 cpd_beta_m: float = 0.05, cpd_lambda: float = 2.0, cpd_w: float = 0.1) -> None:
        if method not in BASELINES:
            raise ValueError(f"unknown baseline {method!r} (expected one of {', '.join(BASELINES)})")
        super().__init__(params, K, T_world_cam)
        self.method = method
        self.cpd = {"beta_m": cpd_beta_m, "lam": cpd_lambda, "w": cpd_w}

    def step(self, cloud: np.ndarray, tcp: np.ndarray | None = None, gripper_closed: np.ndarray | None = None,
             hidden: np.ndarray | None = None, tcp_rot: np.ndarray | None = None,
             open_space: Callable[[np.ndarray], np.ndarray] | None = None,
             behind_arm: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None) -> FrameResult:
        """One frame's segmented cloud (M, 3) m -> the baseline's keypoints, scored like the full method (the
        keypoints hidden behind the arm, hidden (N,) bool, the grippers' orientations tcp_rot (G, 3, 3) and the
        frame's open-space tests are the full method's concern: a baseline reads none of them)."""
        early = self._begin_step(cloud, tcp, gripper_closed)
        if early is not None:
            return early
        assert self.topology is not None and self.keypoints is not None
        p = self.params
        na = len(self.topology.anchor_idx)
        tree = cKDTree(cloud)
        if self.method == "cpd":
            X = cpd_nonrigid(self.keypoints, cloud, iterations=p.track_iterations + 10, **self.cpd)
        else:
            X = nearest_neighbour(self.keypoints, tree)
        return self._result(X, tree, 0, na)
