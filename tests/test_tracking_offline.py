"""Offline gap filling: frames without keypoints tracked backwards / forwards from a tracked neighbour."""

from __future__ import annotations

import numpy as np

from tracking import synthetic as S
from tracking.metrics import surface_error_mm
from tracking.offline import FrameInput, fill_missing, gaps
from tracking.params import TrackingParams
from tracking.pipeline import LivePipeline
from tracking.segmentation import background_from_depths, render_arm_mask, segment_against_background
from tracking.tracker import Tracker

W, H = 640, 480
P = TrackingParams()


def test_gaps_are_the_runs_without_keypoints() -> None:
    assert gaps(np.array([False, False, True, True, False, True, False])) == [(0, 2), (4, 5), (6, 7)]
    assert gaps(np.ones(3, bool)) == [] and gaps(np.zeros(2, bool)) == [(0, 2)]


def test_fill_missing_tracks_backwards_and_forwards_from_one_frame() -> None:
    K, T = S.default_camera(W, H)
    rng = np.random.default_rng(0)
    bg = background_from_depths(np.stack([S.rope_scene(0, K, T, (H, W), rng, with_object=False).depth] * 2))
    frames = [S.rope_scene(0.15 * k, K, T, (H, W), rng) for k in range(12)]
    seed = 6  # the only frame with keypoints: frames 0-5 are filled backwards, 7-11 forwards
    f = frames[seed]
    am = render_arm_mask(f.arm_vertices, f.arm_triangles, K, T, (H, W), P.arm_margin_px, f.depth, P.arm_margin_m)
    tr = Tracker(P, K, T)
    tr.initialise(segment_against_background(f.depth, bg, K, T, P, am).points)
    assert tr.topology is not None and tr.keypoints is not None
    kps: list[np.ndarray | None] = [None] * len(frames)
    grasp: list[np.ndarray | None] = [None] * len(frames)
    kps[seed], grasp[seed] = tr.keypoints.copy(), np.zeros(0, np.int64)

    def make() -> LivePipeline:
        return LivePipeline(P, K, T, "1d")

    res = fill_missing(kps, grasp, tr.topology, make().decimate(bg), make,
                       lambda i: FrameInput(frames[i].depth, frames[i].arm_vertices, frames[i].arm_triangles))
    assert (res.backward, res.forward, len(res.ms)) == (seed, len(frames) - seed - 1, len(frames) - 1)
    errs = [surface_error_mm(k, fr.centreline, fr.radius, polyline=True) for k, fr in zip(kps, frames, strict=True)]
    assert max(errs) < 3.0  # mm: every frame tracked, on the rope
    # the filled keypoints follow the rope: frame 0 and frame 11 differ by the rope's motion
    assert np.linalg.norm(kps[0] - kps[-1], axis=1).max() > 0.03  # type: ignore[operator]
