"""LivePipeline on the simulated station: each object runs its library program and is tracked.

Short 640x480 sequences (simulated time, deterministic): the pipeline must initialise, never lose
the track, keep the keypoints on the true object (GT error to the centreline / mid-surface minus
the radius), hold the grasped ends at the grippers and keep its edge lengths.
"""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.tracking import (
    anchor_gt_error_mm,
    gt_error_mm,
    object_config,
    params_for,
    run_pipeline,
    simulate,
    station_config,
)
from tdcommon.objects import DIMENSION
from tracking.anchors import CORNER, JUNCTION, LEAF

pytestmark = pytest.mark.slow

W, H = 640, 480  # at 320x240 the 14 mm rope is ~3 px wide and the sim's depth-edge dropout eats it
SECONDS = 3.5


def _run(name: str, sim: dict | None = None):
    cfg = station_config(W, H)
    obj = object_config(cfg, name, sim)
    seq = simulate(cfg, obj, SECONDS, "medium")
    outs, _, _ = run_pipeline(seq, params_for(cfg, obj), DIMENSION[obj.category])
    statuses = [o.status for o in outs]
    assert "init" in statuses, f"{name} never initialised: {outs[-1].note}"
    return seq, outs, statuses.index("init")


def _track(name: str, sim: dict | None = None):
    seq, outs, first = _run(name, sim)
    after = outs[first:]
    assert "lost" not in [o.status for o in after], [o.status for o in after]
    assert len(after) >= 30  # at least a second of tracking to judge
    frames = seq.frames[first:]
    gt = np.array([gt_error_mm(o.keypoints, f.gt) for o, f in zip(after, frames, strict=True)])
    anchors = np.array([anchor_gt_error_mm(o, f.gt) for o, f in zip(after, frames, strict=True)])
    abs_mm = np.array([o.abs_mm for o in after])
    cd_mm = np.array([o.cd_mm for o in after])
    return outs[first], after, gt, anchors, abs_mm, cd_mm


def test_rope_is_tracked_on_the_rope_with_its_ends_in_the_grippers():
    init, after, gt, anchors, abs_mm, cd_mm = _track("rope")
    topo = init.topology
    assert topo is not None and topo.kind == "1d" and topo.n_keypoints == 20
    assert sorted(topo.anchor_kind.tolist()) == [LEAF, LEAF]  # a plain chain: two ends, no junction
    assert set(init.grasp_idx.tolist()) == {0, 19}  # both ends held, keypoint 0 at the left gripper
    assert np.sqrt(np.mean(gt**2)) < 3.0 and gt.max() < 6.0  # mm, keypoints on the rope's skin
    assert np.nanmean(anchors) < 10.0  # mm, ends at the true ends
    assert np.median(abs_mm) < 5.0 and np.median(cd_mm) < 8.0
    moved = np.linalg.norm(after[-1].keypoints - after[0].keypoints, axis=1).max()
    assert moved > 0.03  # the keypoints followed the swing (not frozen at the initialisation)


def test_branched_rope_finds_its_junction_and_tracks_every_branch():
    init, after, gt, anchors, abs_mm, cd_mm = _track("branched_rope")
    topo = init.topology
    assert topo is not None and topo.n_keypoints == 25
    kinds = sorted(topo.anchor_kind.tolist())
    assert kinds == [LEAF, LEAF, LEAF, JUNCTION]  # three ends and the junction
    assert len(topo.chains) == 3
    assert np.sqrt(np.mean(gt**2)) < 4.0 and gt.max() < 8.0
    assert np.nanmean(anchors) < 15.0  # the free branch end and the junction included
    assert np.median(abs_mm) < 8.0 and np.median(cd_mm) < 8.0


CLOTH = {"length": 0.55}  # mock.yaml's 0.4 m cloth cannot span the grippers (0.5 m apart): held by two corners


def test_cloth_initialises_a_grid_on_the_cloth_held_at_the_grippers():
    seq, outs, first = _run("cloth", CLOTH)
    init = outs[first]
    topo = init.topology
    assert topo is not None and topo.kind == "2d" and topo.grid_shape == (6, 6)
    assert int((topo.anchor_kind == CORNER).sum()) == 4
    assert (init.grasp_idx >= 0).all()  # both held corners found at the grippers
    on = [i for i, o in enumerate(outs) if o.status in ("init", "tracking", "degraded")]
    gt = np.array([gt_error_mm(outs[i].keypoints, seq.frames[i].gt) for i in on])
    assert np.sqrt(np.mean(gt**2)) < 6.0  # mm to the true mid-surface, whatever the grid's quality


def test_cloth_is_never_lost_and_keeps_its_grid_on_the_cloth():
    init, after, gt, anchors, abs_mm, cd_mm = _track("cloth", CLOTH)
    assert np.sqrt(np.mean(gt**2)) < 6.0 and gt.max() < 10.0  # mm to the true mid-surface
    assert np.mean(abs_mm) < 5.0 and np.median(cd_mm) < 5.0  # edge lengths kept, keypoints on the cloud
    assert all(o.status == "tracking" for o in after[1:])  # not even degraded


def test_a_ropes_colour_is_measured_at_initialisation_and_tells_it_from_the_table():
    """The pipeline fed colour frames measures the rope's colour when it initialises: the rope's own points read
    as the object, points on the table beside it (where the reference saw the table) as the background."""
    from benchmarks.tracking import _arm_inputs
    from tracking.colour import BACKGROUND, OBJECT, classify
    from tracking.pipeline import LivePipeline

    cfg = station_config(W, H)
    obj = object_config(cfg, "rope")
    seq = simulate(cfg, obj, 2.5, "medium")
    params = params_for(cfg, obj)
    pipe = LivePipeline(params, seq.K, seq.T_world_cam, DIMENSION[obj.category])
    for f, (V, F, tcp, closed, rot) in zip(seq.frames, _arm_inputs(seq), strict=True):
        out = pipe.process(f.depth.astype(np.float32) * np.float32(1e-3), V, F, tcp, closed, tcp_rot=rot,
                           colour=f.color)
        if out.status == "tracking":
            break
    assert out.status == "tracking" and pipe.colour_model is not None
    colour = out.prepared.colour
    assert colour is not None and colour.shape[:2] == out.prepared.depth.shape
    on = f.gt.centreline[::10]
    told = classify(on, colour, pipe.colour_model, pipe.K_seg, pipe.T, params.colour_radius_m)
    assert (told == OBJECT).mean() > 0.8
    # 15 cm beside it (the table, the arms' bases, the other objects): not the rope's colour
    off = classify(on + [0.0, 0.15, 0.0], colour, pipe.colour_model, pipe.K_seg, pipe.T, params.colour_radius_m)
    assert (off != OBJECT).mean() > 0.8 and (off == BACKGROUND).any()
