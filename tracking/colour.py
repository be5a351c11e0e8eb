"""Colour as a second opinion where depth cannot tell an object from the table it lies on.

A rope lying on the table stands a diameter above it, within the stereo noise of the table's own readings beside
it: depth alone keeps that noise as the rope's (``segmentation.select_clusters_near``). The object's colour is
measured at initialisation (``measure_object``, from the points depth segmented) and the empty scene's at each pixel
is the reference frame's; a low point is the table's where its pixel's chromaticity is nearer the reference's there
than the object's, and no pixel beside it is the object's (``classify``). Chromaticity (r, g over r + g + b) leaves
a shadow's darkening out. Nothing here knows a colour: both come from the frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tracking.geometry import pixels_of

OBJECT, BACKGROUND, UNKNOWN = 1, 0, -1


def chroma(rgb: np.ndarray) -> np.ndarray:
    """(..., 2) float32 chromaticity (r, g) / (r + g + b) of colours (..., 3) uint8 (one added to each channel: a
    black pixel is grey, not undefined)."""
    f = np.asarray(rgb, np.float32) + np.float32(1.0)
    return f[..., :2] / f.sum(axis=-1, keepdims=True)


@dataclass(frozen=True)
class ColourModel:
    """The scene's colours for ``classify``: reference (h, w, 2) float32, the empty scene's chromaticity (the
    reference frame D0's colour, decimated as the depth is); object (2,) float32, the object's median chromaticity;
    separation: the least chromaticity distance between the two at a pixel for colour to decide there."""

    reference: np.ndarray
    object: np.ndarray
    separation: float


def measure_object(
    colour: np.ndarray, reference: np.ndarray, cloud: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
    min_separation: float,
) -> ColourModel | None:
    """The colour model of an object whose segmented cloud (M, 3) m world is seen in colour (h, w, 3) uint8 (a camera
    K (3, 3) at T_world_cam (4, 4) of that image), the reference frame's colour reference (h, w, 3) uint8. The
    separation is min_separation or three robust deviations of the object's own chromaticity, the larger. None
    when no point of the cloud falls in the image."""
    r, c, inside, _ = pixels_of(np.asarray(cloud, np.float64), K, T_world_cam, colour.shape)
    if not inside.any():
        return None
    ch = chroma(colour[r[inside], c[inside]])
    obj = np.median(ch, axis=0)
    spread = 1.4826 * float(np.median(np.linalg.norm(ch - obj, axis=1)))
    return ColourModel(chroma(reference), obj.astype(np.float32), max(min_separation, 3.0 * spread))


def classify(
    points: np.ndarray, colour: np.ndarray, model: ColourModel, K: np.ndarray, T_world_cam: np.ndarray,
    radius_m: float,
) -> np.ndarray:
    """(N,) int8 per point (N, 3) m world: OBJECT where some pixel within radius_m of its own (at its depth) in
    colour (h, w, 3) uint8 is nearer the object's chromaticity than the reference's there, else what its own pixel
    says: BACKGROUND, or UNKNOWN where the reference there is not far enough from the object's colour
    (``model.separation``: the object stood there, or the table's colour is the object's) or the point is outside
    the image. The window spans the colour and depth images' misregistration at a thin object's edge (a stereo
    depth's edge lies a few pixels off the colour's)."""
    out = np.full(len(points), UNKNOWN, np.int8)
    if len(points) == 0:
        return out
    h, w = colour.shape[:2]
    r, c, inside, z = pixels_of(np.asarray(points, np.float64), K, T_world_cam, (h, w))
    idx = np.flatnonzero(inside)
    if not len(idx):
        return out
    rad = np.ceil(radius_m * float(K[0, 0]) / np.maximum(z[idx], 1e-3)).astype(np.int64)  # (P,) px
    m = int(rad.max())
    dy, dx = (a.ravel() for a in np.mgrid[-m : m + 1, -m : m + 1])  # (W,) offsets, the own pixel at W // 2
    rr = np.clip(r[idx, None] + dy, 0, h - 1)  # (P, W)
    cc = np.clip(c[idx, None] + dx, 0, w - 1)
    ch, ref = chroma(colour[rr, cc]), model.reference[rr, cc]  # (P, W, 2)
    sep = np.linalg.norm(ref - model.object, axis=2) > model.separation
    near = np.linalg.norm(ch - model.object, axis=2) < np.linalg.norm(ch - ref, axis=2)
    verdict = np.where(sep, np.where(near, OBJECT, BACKGROUND), UNKNOWN).astype(np.int8)
    window = (np.abs(dy) <= rad[:, None]) & (np.abs(dx) <= rad[:, None])
    seen = (window & (verdict == OBJECT)).any(axis=1)
    out[idx] = np.where(seen, OBJECT, verdict[:, (len(dy) - 1) // 2])
    return out
