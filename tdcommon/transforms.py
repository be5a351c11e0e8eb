"""Rigid transforms and pose conversions: (4, 4) homogeneous matrices, 7-vector poses, the arm input.

All poses are float64, metres, ``T_a_b`` maps frame b into frame a. Rotation vectors are axis * angle (rad).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def pose7_to_matrix(pose: np.ndarray) -> np.ndarray:
    """(..., 7) [x, y, z, qw, qx, qy, qz] (m, unit quaternion scalar first) -> (..., 4, 4)."""
    p = np.asarray(pose, dtype=np.float64)
    flat = p.reshape(-1, 7)
    T = np.tile(np.eye(4), (len(flat), 1, 1))
    if len(flat):
        T[:, :3, :3] = Rotation.from_quat(flat[:, [4, 5, 6, 3]]).as_matrix()
        T[:, :3, 3] = flat[:, :3]
    return T.reshape(*p.shape[:-1], 4, 4)


def matrix_to_pose7(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> (..., 7) [x, y, z, qw, qx, qy, qz] with qw >= 0."""
    T = np.asarray(T, dtype=np.float64)
    flat = T.reshape(-1, 4, 4)
    out = np.zeros((len(flat), 7))
    if len(flat):
        q = Rotation.from_matrix(flat[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
        q *= np.where(q[:, :1] < 0, -1.0, 1.0)
        out[:, :3] = flat[:, :3, 3]
        out[:, 3:] = q
    return out.reshape(*T.shape[:-2], 7)


def input_to_matrix(u: np.ndarray) -> np.ndarray:
    """(..., 6) [x, y, z (m), rotation vector (rad)] -> (..., 4, 4); NaN rows give NaN matrices."""
    u = np.asarray(u, dtype=np.float64)
    flat = u.reshape(-1, 6)
    T = np.tile(np.eye(4), (len(flat), 1, 1))
    ok = np.isfinite(flat).all(axis=1)
    if ok.any():
        T[ok, :3, :3] = Rotation.from_rotvec(flat[ok, 3:]).as_matrix()
        T[ok, :3, 3] = flat[ok, :3]
    T[~ok] = np.nan
    return T.reshape(*u.shape[:-1], 4, 4)


def pose_to_input(T: np.ndarray) -> np.ndarray:
    """(6,) [x, y, z, rx, ry, rz]: position (m) and rotation vector (rad, axis * angle) of a pose (4, 4).

    OpenCV's Rodrigues (≈2 µs; scipy's Rotation ≈50 µs): called for both arms at every joint state.
    """
    import cv2

    rvec, _ = cv2.Rodrigues(np.ascontiguousarray(T[:3, :3], dtype=np.float64))
    return np.concatenate([T[:3, 3], rvec.ravel()])


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_cam (4, 4) of an OpenCV camera (x right, y down, z forward) at ``eye`` (3,) m looking at
    ``target`` (3,) m, with ``up`` (3,) the world direction that points up in the image."""
    eye_a, target_a, up_a = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target_a - eye_a
    z /= np.linalg.norm(z)
    x = np.cross(z, up_a)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye_a
    return T
