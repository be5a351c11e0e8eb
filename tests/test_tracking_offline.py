"""Offline gap filling: frames without keypoints tracked backwards / forwards from a tracked neighbour."""

from __future__ import annotations

import numpy as np
import pytest

from tracking import synthetic as S
from tracking.metrics import surface_error_mm
from tracking.offline import FrameInput, fill_missing, gaps, retrack_frames, switch_frame
from tracking.params import TrackingParams
from tracking.pipeline import LivePipeline
from tracking.segmentation import background_from_depths, render_arm_mask, segment_against_background
from tracking.tracker import Tracker

W, H = 640, 480
P = TrackingParams()


def test_gaps_are_the_runs_without_keypoints() -> None:
    assert gaps(np.array([False, False, True, True, False, True, False])) == [(0, 2), (4, 5), (6, 7)]
    assert gaps(np.ones(3, bool)) == [] and gaps(np.zeros(2, bool)) == [(0, 2)]


def test_retrack_frames_are_tangled_runs_before_a_good_frame() -> None:
    bad = np.array([0, 1, 1, 0, 1, 0, 1, 1], bool)
    good = np.array([1, 0, 0, 1, 0, 0, 0, 0], bool)  # frame 5: tracked, but not a start (a filled tangle)
    assert retrack_frames(bad, good).tolist() == [1, 2]  # 4 has no good frame after it, 6-7 end the clip
    assert retrack_frames(np.zeros(3, bool), np.ones(3, bool)).tolist() == []


def test_switch_frame_at_the_least_seam_and_only_when_better() -> None:
    rng = np.random.default_rng(0)
    fwd = rng.normal(size=(5, 4, 3))
    bwd = fwd + np.array([0.3, 0.2, 0.0, 0.1, 0.4])[:, None, None]  # nearest at frame 2
    tangled_f = np.array([[1, 9.0]] * 5)
    assert switch_frame(fwd, bwd, tangled_f, np.array([[1, 12.0], [1, 12.0], [0, 3.0], [0, 2.0], [0, 2.0]])) == 2
    # from the seam on, the backward frames must be no more tangled and no larger in edge error, summed
    assert switch_frame(fwd, bwd, tangled_f, np.array([[0, 1.0]] * 2 + [[0, 20.0]] * 3)) == 5
    assert switch_frame(fwd, bwd, tangled_f, np.array([[0, 3.0]] * 2 + [[np.inf, np.inf]] * 3)) == 5
    assert switch_frame(fwd, bwd, tangled_f, tangled_f) == 5  # the same: keep the forward pass
    assert switch_frame(fwd[:0], bwd[:0], tangled_f[:0], tangled_f[:0]) == 0


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
    assert res.frames == [*range(seed - 1, -1, -1), *range(seed + 1, len(frames))]  # backwards, then forwards
    errs = [surface_error_mm(k, fr.centreline, fr.radius, polyline=True) for k, fr in zip(kps, frames, strict=True)]
    assert max(errs) < 3.0  # mm: every frame tracked, on the rope
    # the filled keypoints follow the rope: frame 0 and frame 11 differ by the rope's motion
    assert np.linalg.norm(kps[0] - kps[-1], axis=1).max() > 0.03  # type: ignore[operator]


def test_fill_missing_from_prepared_frames_equals_fill_from_depth() -> None:
    """Frames handed over as the forward pass prepared them (decimated depth, arm mask) fill the same keypoints."""
    K, T = S.default_camera(W, H)
    rng = np.random.default_rng(1)
    bg = background_from_depths(np.stack([S.rope_scene(0, K, T, (H, W), rng, with_object=False).depth] * 2))
    frames = [S.rope_scene(0.15 * k, K, T, (H, W), rng) for k in range(6)]
    f = frames[-1]
    am = render_arm_mask(f.arm_vertices, f.arm_triangles, K, T, (H, W), P.arm_margin_px, f.depth, P.arm_margin_m)
    tr = Tracker(P, K, T)
    tr.initialise(segment_against_background(f.depth, bg, K, T, P, am).points)
    assert tr.topology is not None and tr.keypoints is not None

    def make() -> LivePipeline:
        return LivePipeline(P, K, T, "1d")

    prep = make()
    prepared = [prep.prepare(fr.depth, fr.arm_vertices, fr.arm_triangles) for fr in frames]
    assert all(p.arm is not None and p.arm.any() for p in prepared)
    out = []
    for inputs in (lambda i: FrameInput(frames[i].depth, frames[i].arm_vertices, frames[i].arm_triangles),
                   lambda i: FrameInput(None, prepared=prepared[i])):
        kps: list[np.ndarray | None] = [None] * (len(frames) - 1) + [tr.keypoints.copy()]
        grasp: list[np.ndarray | None] = [None] * (len(frames) - 1) + [np.zeros(0, np.int64)]
        res = fill_missing(kps, grasp, tr.topology, make().decimate(bg), make, inputs)
        assert res.backward == len(frames) - 1
        out.append(np.stack(kps))  # type: ignore[arg-type]
    np.testing.assert_array_equal(out[0], out[1])


def test_prepared_frame_alone_cannot_initialise() -> None:
    K, T = S.default_camera(W, H)
    pipe = LivePipeline(P, K, T, "1d")
    fr = S.rope_scene(0, K, T, (H, W), np.random.default_rng(2))
    first = pipe.process(fr.depth)
    assert first.status == "reference" and first.prepared is not None
    with pytest.raises(ValueError, match="full-resolution depth"):
        pipe.process(None, prepared=first.prepared)
    with pytest.raises(ValueError, match="no depth and no prepared frame"):
        pipe.process(None)


def test_prepare_from_the_recorded_image_equals_prepare_from_metres() -> None:
    """Decimating the uint16 image before scaling it gives the float32 values decimating depth_m() gives."""
    K, T = S.default_camera(1280, 720)
    pipe = LivePipeline(P, K, T, "1d")
    assert pipe.stride > 1
    raw = np.random.default_rng(3).integers(0, 4000, (720, 1280)).astype(np.uint16)
    for scale in (0.001, 0.000125, 1 / 3000):
        a = pipe.prepare(raw.astype(np.float32) * np.float32(scale))
        b = pipe.prepare(raw, depth_scale=scale)
        assert b.depth.dtype == np.float32 and b.depth.flags.c_contiguous
        np.testing.assert_array_equal(a.depth, b.depth)


def test_a_reinitialised_track_is_put_in_the_clips_numbering_or_refused() -> None:
    # after a loss the tracker initialises again: a rope's chain may come numbered from its other end (put back
    # in the clip's order), a branched rope's keypoints split otherwise among its branches or rest lengths that
    # add up to another length (refused: filled)
    from orchestrator.cli_tracking import _renumbering
    from tracking.init import Topology

    n = 6
    E = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    topo = Topology("1d", E, np.full(n - 1, 0.04), np.array([0, n - 1]), np.zeros(2, np.int64), [np.arange(n)])
    again = Topology("1d", E[::-1, ::-1].copy(), np.full(n - 1, 0.041), np.array([0, n - 1]), np.zeros(2, np.int64),
                     [np.arange(n)])
    last = np.stack([np.arange(n) * 0.04, np.zeros(n), np.zeros(n)], axis=1)
    X = last[::-1] + 0.003  # the same rope, numbered from the other end
    perm = _renumbering(topo, again, X, last, 0.06)
    assert perm is not None and np.allclose(X[perm], last + 0.003)
    assert np.array_equal(_renumbering(topo, again, last, last, 0.06), np.arange(n))
    Y = Topology("1d", np.array([[0, 1], [1, 2], [2, 3], [1, 4], [4, 5]]), np.full(5, 0.04), np.array([0, 3, 5, 1]),
                 np.zeros(4, np.int64), [np.array([0, 1]), np.array([1, 2, 3]), np.array([1, 4, 5])])
    assert _renumbering(topo, Y, X, last, 0.06) is None
    short = Topology("1d", E.copy(), np.full(n - 1, 0.03), np.array([0, n - 1]), np.zeros(2, np.int64), [np.arange(n)])
    assert _renumbering(topo, short, X[::-1], last, 0.06) is None  # 25 % shorter
    assert _renumbering(topo, short, X[::-1], last, 0.3) is not None


class _ReplayPipeline:
    """A stand-in for ``LivePipeline`` in the offline passes: frame i (its depth is the index) yields
    ``answers[i]`` = (keypoints (N, 3), tangled, Abs mm), whatever it resumed from."""

    def __init__(self, answers: dict[int, tuple[np.ndarray, int, float]]) -> None:
        from types import SimpleNamespace

        self.answers = answers
        self.tracker = SimpleNamespace(initialised=True)
        self.background = np.zeros((2, 2), np.float32)
        self.resumed_from: list[np.ndarray] = []

    def resume(self, topology: object, keypoints: np.ndarray, grasp_idx: np.ndarray, background: np.ndarray) -> None:
        self.resumed_from.append(np.array(keypoints))

    def process(self, depth: np.ndarray, *args: object, **kwargs: object) -> object:
        from types import SimpleNamespace

        X, tangled, abs_mm = self.answers[int(depth)]
        return SimpleNamespace(keypoints=X, grasp_idx=np.zeros(0, np.int64), tangled=tangled, abs_mm=abs_mm,
                               timings_ms={})


def test_retrack_tangled_keeps_the_backward_run_from_its_least_seam() -> None:
    from types import SimpleNamespace

    from tracking.offline import retrack_tangled

    T, N = 9, 3
    truth = np.arange(T, dtype=float)[:, None, None] * np.ones((T, N, 3)) * 0.01
    fwd: list[np.ndarray | None] = [truth[i].copy() for i in range(T)]
    for i in (3, 4, 5):  # tangled forward frames: 3 near the truth, 4 and 5 far off
        fwd[i] = truth[i] + (0.001 if i == 3 else 0.2)
    fwd[8] = truth[8] + 0.2  # tangled at the clip's end: nothing to track back from
    tangled = {3: (1, 9.0), 4: (1, 30.0), 5: (1, 30.0), 8: (1, 30.0)}
    answers = {i: (truth[i] + 0.0005, 0, 1.0) for i in range(T)}
    pipe = _ReplayPipeline(answers)
    keypoints = list(fwd)
    grasp: list[np.ndarray | None] = [np.zeros(0, np.int64)] * T
    topo = SimpleNamespace(n_keypoints=N)
    res, again, kept = retrack_tangled(keypoints, grasp, tangled, [], topo, pipe.background,  # type: ignore[arg-type]
                                       lambda: pipe,  # type: ignore[arg-type, return-value]
                                       lambda i: FrameInput(np.array(i)))
    assert (again, kept, res.backward) == (3, 3, 3)  # frames 5, 4, 3 from frame 6; frame 8 left as it was
    np.testing.assert_allclose(pipe.resumed_from[0], truth[6])
    for i in (3, 4, 5):
        np.testing.assert_allclose(keypoints[i], truth[i] + 0.0005)  # type: ignore[arg-type]
    np.testing.assert_allclose(keypoints[8], fwd[8])  # type: ignore[arg-type]
    # a backward pass that is no better (more edge error) leaves the forward frames
    worse = {i: (truth[i] + 0.0005, 0, 50.0) for i in range(T)}
    pipe = _ReplayPipeline(worse)
    keypoints = list(fwd)
    _, again, kept = retrack_tangled(keypoints, grasp, tangled, [], topo, pipe.background,  # type: ignore[arg-type]
                                     lambda: pipe,  # type: ignore[arg-type, return-value]
                                     lambda i: FrameInput(np.array(i)))
    assert (again, kept) == (3, 0)
    for i in (3, 4, 5):
        np.testing.assert_allclose(keypoints[i], fwd[i])  # type: ignore[arg-type]


@pytest.mark.parametrize(("answer_edge", "taken"), [(0.1, True), (0.05, False)])
def test_retrack_grown_tracks_the_frames_up_to_a_growth_again_and_keeps_the_better(
    answer_edge: float, taken: bool
) -> None:
    """A chain initialised at frame 2 and lengthened at frame 4 (rest 0.10 m an edge, 0.07 measured before):
    frames 0-4 are tracked backwards from frame 5 with the longer chain; frames 2-4 take that solution only where
    it fits the rest lengths better (edges of answer_edge m), frames 0-1 (never tracked) take it in any case."""
    from types import SimpleNamespace

    from tracking.offline import retrack_grown

    def chain(edge: float, i: int) -> np.ndarray:
        return np.array([[0.0, 0.0, 0.0], [edge, 0.0, 0.0], [2 * edge, 0.0, 0.0]]) + [0.0, 0.01 * i, 0.0]

    T, first, grown = 8, 2, 4
    topo = SimpleNamespace(n_keypoints=3, edges=np.array([[0, 1], [1, 2]]), rest=np.array([0.1, 0.1]))
    fwd: list[np.ndarray | None] = [None, None] + [chain(0.07 if i <= grown else 0.1, i) for i in range(2, T)]
    keypoints = list(fwd)
    grasp: list[np.ndarray | None] = [None, None] + [np.zeros(0, np.int64)] * (T - 2)
    pipe = _ReplayPipeline({i: (chain(answer_edge, i), 0, 1.0) for i in range(T)})
    res, took = retrack_grown(keypoints, grasp, first, grown, {}, topo, pipe.background,  # type: ignore[arg-type]
                              lambda: pipe,  # type: ignore[arg-type, return-value]
                              lambda i: FrameInput(np.array(i)))
    assert took is taken
    assert (res.backward, res.frames) == (grown + 1, [4, 3, 2, 1, 0])
    np.testing.assert_allclose(pipe.resumed_from[0], fwd[5])  # type: ignore[arg-type]
    for i in range(T):
        want = chain(answer_edge, i) if i < first or (taken and i <= grown) else fwd[i]
        np.testing.assert_allclose(keypoints[i], want)  # type: ignore[arg-type]
    assert all(g is not None for g in grasp)
    assert set(res.quality) == ({0, 1, 2, 3, 4} if taken else {0, 1})


def test_a_ropes_size_for_initialisation_does_not_fall_with_its_distance() -> None:
    """``LivePipeline.voxels_worth``: the same rope 1, 1.5 and 2 m from a 1280x720 camera lifts to ever fewer points
    (its pixels widen past a voxel), but to the same surface, which ``min_init_points`` is judged against."""
    from tdcommon.meshes import tube_mesh
    from tdcommon.transforms import look_at
    from tracking.geometry import depth_to_points
    from tracking.segmentation import voxel_downsample

    K = S.intrinsics(1280, 720)
    c = S.rope_centreline(0.0, radius=0.0045)
    counts, worth = [], []
    for dist in (1.0, 1.5, 2.0):
        T = look_at([0.0, -0.6 * dist, 0.8 * dist], [0.0, 0.0, 0.0])
        pipe = LivePipeline(P, K, T, "1d")
        depth = pipe.decimate(S.render_depth([tube_mesh(c, 0.0045)], K, T, (720, 1280)))
        pts = voxel_downsample(depth_to_points(depth, pipe.K_seg, T)[0], P.voxel_m)
        counts.append(len(pts))
        worth.append(pipe.voxels_worth(pts))
    assert counts[0] > 3 * counts[2]
    assert max(worth) < 1.15 * min(worth) and min(worth) >= counts[0]
    assert LivePipeline(P, K, look_at([0.0, -0.6, 0.8], [0.0, 0.0, 0.0]), "1d").voxels_worth(np.zeros((0, 3))) == 0
