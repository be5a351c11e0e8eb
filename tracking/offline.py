"""Offline passes over a recorded clip: frames the forward pass left without keypoints are tracked from a
neighbouring tracked frame, backwards in time before it (the frames before initialisation, or before a
re-initialisation) or forwards after the last one (a track lost for good), so every frame has keypoints.

The passes run the same ``LivePipeline`` tracking step as the forward pass (same segmentation, anchors and
solver; the frames' decimated depth and arm masks can be handed over from the forward pass, which made them
already, so a frame costs no more than it did there), resumed from the neighbour's keypoints with a
background model that has seen the whole clip (the forward pass's last one: what the object uncovered as it
moved is known there, while the background at initialisation still held the object wherever it had not yet
moved).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from tracking.init import Topology
from tracking.pipeline import LivePipeline, PreparedFrame


@dataclass(frozen=True)
class FrameInput:
    """What ``LivePipeline.process`` takes for one frame: depth (H, W) float32 m; both arms as one mesh
    vertices (V, 3) m world + triangles (F, 3) int (or None); tcp (G, 3) m world, closed (G,) bool and tcp_rot
    (G, 3, 3) the grippers' orientations (optional).
    prepared: the frame's decimated depth and arm mask kept from the forward pass (depth and meshes may
    then be None: a resumed track does not initialise, so it needs neither)."""

    depth: np.ndarray | None
    arm_vertices: np.ndarray | None = None
    arm_triangles: np.ndarray | None = None
    tcp: np.ndarray | None = None
    closed: np.ndarray | None = None
    prepared: PreparedFrame | None = None
    tcp_rot: np.ndarray | None = None


@dataclass
class FillResult:
    """What ``fill_missing`` did: frames tracked backwards / forwards, each one's ``process`` time, ms, and its
    stages' (``PipelineOutput.timings_ms``)."""

    backward: int = 0
    forward: int = 0
    ms: list[float] = field(default_factory=list)
    stages: list[dict[str, float]] = field(default_factory=list)


def gaps(have: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [a, b) of False in have (T,) bool, in order."""
    h = np.concatenate([[True], np.asarray(have, bool), [True]])
    d = np.diff(h.astype(np.int8))
    return list(zip((np.flatnonzero(d == -1)).tolist(), (np.flatnonzero(d == 1)).tolist(), strict=True))


def fill_missing(
    keypoints: list[np.ndarray | None],
    grasp_idx: list[np.ndarray | None],
    topology: Topology,
    background: np.ndarray,
    make_pipeline: Callable[[], LivePipeline],
    frame: Callable[[int], FrameInput],
) -> FillResult:
    """Fill in place the frames of keypoints (T entries: (N, 3) m world or None) that have none.

    A gap followed by a tracked frame b is tracked backwards from b (frames b-1, b-2, ...); a gap at the end
    forwards from the last tracked frame. grasp_idx: per frame (G,) int64 of the tracked frames (filled too);
    topology: the track's (N keypoints); background: decimated (h, w) float32 m, the forward pass's last;
    make_pipeline: a fresh ``LivePipeline`` for the clip; frame(i): frame i's input. A resumed track that is
    lost is resumed again from its last keypoints (the object is still there; the forward pass's loss check
    re-initialises, which these passes cannot).
    """
    T = len(keypoints)
    N = topology.n_keypoints
    have = np.array([k is not None and len(k) == N for k in keypoints])
    res = FillResult()
    if not have.any():
        return res
    for a, b in gaps(have):
        order, seed = (range(b - 1, a - 1, -1), b) if b < T else (range(a, b), a - 1)
        pipe = make_pipeline()
        X = np.asarray(keypoints[seed])
        g = grasp_idx[seed] if grasp_idx[seed] is not None else np.full(0, -1, np.int64)
        pipe.resume(topology, X, g, background)
        for i in order:
            f = frame(i)
            t0 = time.perf_counter()
            out = pipe.process(f.depth, f.arm_vertices, f.arm_triangles, f.tcp, f.closed, prepared=f.prepared,
                               tcp_rot=f.tcp_rot)
            res.ms.append(1e3 * (time.perf_counter() - t0))
            res.stages.append(out.timings_ms)
            if len(out.keypoints) == N:
                X, g = out.keypoints, out.grasp_idx
            keypoints[i], grasp_idx[i] = X, g
            if b < T:
                res.backward += 1
            else:
                res.forward += 1
            if not pipe.tracker.initialised:  # lost: carry on from the last solution
                pipe.resume(topology, X, g, pipe.background if pipe.background is not None else background)
    return res
