"""Offline passes over a recorded clip: frames the forward pass left without keypoints are tracked from a
neighbouring tracked frame, backwards in time before it (the frames before initialisation, or before a
re-initialisation) or forwards after the last one (a track lost for good), so every frame has keypoints.
The frames tracked before a chain was found longer than initialisation measured are tracked again backwards
with the longer chain (``retrack_grown``). A run of frames the forward pass left tangled (a chain folded onto
itself, a grid's flipped cells) is tracked again backwards from the good frame after it, and switches to that
solution from where the two meet when it is better there (``retrack_tangled``).

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
from tracking.metrics import edge_rmse_mm
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
    """What ``fill_missing`` did: frames tracked backwards / forwards, each one's index (frames), ``process``
    time, ms, and stages' (``PipelineOutput.timings_ms``) in the order tracked; quality: each filled frame's
    (tangled, Abs mm) (``PipelineOutput``: tangled cells or folded keypoints left, edge error), for comparing it
    with another solution of that frame."""

    backward: int = 0
    forward: int = 0
    frames: list[int] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)
    stages: list[dict[str, float]] = field(default_factory=list)
    quality: dict[int, tuple[int, float]] = field(default_factory=dict)


def gaps(have: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [a, b) of False in have (T,) bool, in order."""
    h = np.concatenate([[True], np.asarray(have, bool), [True]])
    d = np.diff(h.astype(np.int8))
    return list(zip((np.flatnonzero(d == -1)).tolist(), (np.flatnonzero(d == 1)).tolist(), strict=True))


def retrack_frames(bad: np.ndarray, good: np.ndarray) -> np.ndarray:
    """The frames (K,) int64 worth tracking again backwards: the runs of bad (T,) bool frames (tracked, but left
    tangled) followed by a good (T,) bool frame to start from. A run at the clip's end has none: tracked forwards
    again it would only repeat the forward pass."""
    bad, good = np.asarray(bad, bool), np.asarray(good, bool)
    T = len(bad)
    out = [np.arange(a, b) for a, b in gaps(~bad) if b < T and good[b]]
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def improves(new: np.ndarray, old: np.ndarray) -> bool:
    """Whether quality new (2,) (tangled, Abs mm; summed over frames) is no worse than old (2,) in either and
    better in one: the test both backward passes (``switch_frame``, ``retrack_grown``) keep their solution by."""
    return bool((new <= old).all() and (new < old).any())


def switch_frame(forward: np.ndarray, backward: np.ndarray, q_forward: np.ndarray, q_backward: np.ndarray) -> int:
    """Where a run of K frames tracked twice switches from its forward solution to its backward one: frames
    before the returned index keep forward (K, N, 3) m, the others take backward (K, N, 3) m; K keeps forward
    throughout. The switch is at the frame where both solutions lie nearest each other (the least seam), and is
    made only when the backward frames from there on are, summed, no more tangled and no larger in edge error
    than the forward ones, and better in one: q_forward, q_backward (K, 2) per frame (tangled, Abs mm), inf
    where a pass gave no solution."""
    K = len(forward)
    if K == 0:
        return 0
    seam = np.linalg.norm(np.asarray(forward) - np.asarray(backward), axis=2).max(axis=1)  # (K,) m
    s = int(np.argmin(np.where(np.isfinite(seam), seam, np.inf)))
    f, b = np.asarray(q_forward, np.float64)[s:].sum(axis=0), np.asarray(q_backward, np.float64)[s:].sum(axis=0)
    return s if improves(b, f) else K


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
            res.frames.append(i)
            res.stages.append(out.timings_ms)
            if len(out.keypoints) == N:
                X, g = out.keypoints, out.grasp_idx
                res.quality[i] = (int(out.tangled), float(out.abs_mm))
            keypoints[i], grasp_idx[i] = X, g
            if b < T:
                res.backward += 1
            else:
                res.forward += 1
            if not pipe.tracker.initialised:  # lost: carry on from the last solution
                pipe.resume(topology, X, g, pipe.background if pipe.background is not None else background)
    return res


def retrack_tangled(
    keypoints: list[np.ndarray | None],
    grasp_idx: list[np.ndarray | None],
    tangled: dict[int, tuple[int, float]],
    untrusted: list[int],
    topology: Topology,
    background: np.ndarray,
    make_pipeline: Callable[[], LivePipeline],
    frame: Callable[[int], FrameInput],
) -> tuple[FillResult, int, int]:
    """Track the runs of frames the forward pass left tangled (tangled: frame -> (tangled, Abs mm)) again
    backwards from the good frame after each (``retrack_frames``; not one of untrusted, e.g. a filled frame left
    tangled too), and keep in each run the backward solution from its least seam on where it is better
    (``switch_frame``). keypoints, grasp_idx: T entries, every frame tracked, updated in place; the rest as
    ``fill_missing``. Returns (the backward pass's FillResult, frames tracked again, frames whose backward
    solution was kept)."""
    T = len(keypoints)
    bad = np.isin(np.arange(T), list(tangled))
    good = np.array([k is not None for k in keypoints]) & ~bad
    good[list(untrusted)] = False
    again = retrack_frames(bad, good)
    forward = {int(i): (keypoints[i], grasp_idx[i]) for i in again}
    for i in again:
        keypoints[i] = grasp_idx[i] = None
    res = fill_missing(keypoints, grasp_idx, topology, background, make_pipeline, frame)
    kept = 0
    for a, b in gaps(~np.isin(np.arange(T), again)):
        run = range(a, b)
        s = a + switch_frame(np.stack([np.asarray(forward[i][0]) for i in run]),
                             np.stack([np.asarray(keypoints[i]) for i in run]),
                             np.array([tangled[i] for i in run], np.float64),
                             np.array([res.quality.get(i, (np.inf, np.inf)) for i in run], np.float64))
        kept += b - s
        for i in range(a, s):
            keypoints[i], grasp_idx[i] = forward[i]
    return res, len(again), kept


def retrack_grown(
    keypoints: list[np.ndarray | None],
    grasp_idx: list[np.ndarray | None],
    first: int,
    grown: int,
    tangled: dict[int, tuple[int, float]],
    topology: Topology,
    background: np.ndarray,
    make_pipeline: Callable[[], LivePipeline],
    frame: Callable[[int], FrameInput],
) -> tuple[FillResult, bool]:
    """Track frames [0, grown] backwards from frame grown + 1, where the forward pass had initialised at first
    (frames before it have no keypoints) and lengthened a chain at frame grown (``Tracker._grow``; topology
    holds the lengthened rest lengths): initialisation measured what it saw, and the frames up to the growth
    were tracked with the shorter chain. Frames [first, grown] take the backward solution when it is, summed,
    no more tangled and no larger in edge error (against the lengthened rest lengths) than the forward one, and
    better in one; the frames before first take it in any case. tangled: the forward frames left tangled
    (frame -> (tangled, Abs mm)); keypoints, grasp_idx: T entries, updated in place; the rest as
    ``fill_missing``. Returns the backward pass's FillResult and whether frames [first, grown] took it."""
    run = range(first, grown + 1)
    forward = {i: (keypoints[i], grasp_idx[i]) for i in run}
    for i in run:
        keypoints[i] = grasp_idx[i] = None
    res = fill_missing(keypoints, grasp_idx, topology, background, make_pipeline, frame)

    def quality(X: np.ndarray | None, tangles: float) -> tuple[float, float]:  # (tangled, Abs mm) of one frame
        if X is None:
            return np.inf, np.inf
        return tangles, edge_rmse_mm(np.asarray(X), topology.edges, topology.rest)

    f = np.sum([quality(forward[i][0], tangled.get(i, (0, 0.0))[0]) for i in run], axis=0)
    b = np.sum([quality(keypoints[i], res.quality.get(i, (np.inf, 0.0))[0]) for i in run], axis=0)
    take = improves(b, f)
    if not take:
        for i in run:
            keypoints[i], grasp_idx[i] = forward[i]
            res.quality.pop(i, None)
    return res, take
