"""The simulated object and the renderer of mock mode (drivers/fake/sim_object.py, render.py)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from drivers.config import SimObjectConfig
from drivers.fake.render import INVALID_ID, SceneRenderer, _tensors, mock_camera_pose, static_scene
from drivers.fake.sim_object import SimObject
from tdcommon.meshes import merge_meshes, sheet_mesh, tube_mesh
from tdcommon.robot import PandaKinematics
from tdcommon.types import CameraIntrinsics

CLOSED = {"left": True, "right": True}


def tcp(p) -> np.ndarray:
    """A TCP pose pointing down (z axis = -world z) at position p."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = p
    return T


HOME = [("left", tcp([0.45, 0.25, 0.40])), ("right", tcp([0.45, -0.25, 0.40]))]


def hung(category: str, **kw) -> SimObject:
    sim = SimObject(SimObjectConfig(category=category, **kw))
    sim.reset(HOME, settle_time=1.0)
    return sim


@pytest.mark.parametrize("category", ["dlo", "bdlo"])
def test_ropes_are_inextensible_after_settling(category):
    sim = hung(category)
    r = sim.stretch_ratio()
    assert r.max() < 1.02 and r.min() > 0.98
    assert sim.x[:, 2].min() >= sim.radius - 1e-9  # never below the table


def test_cloth_stretch_is_small_after_settling():
    sim = hung("cloth")
    r = sim.stretch_ratio()
    # Away from the stress concentration at the two pinned corners the sheet is inextensible.
    assert np.percentile(r, 98) < 1.02
    assert abs(r.mean() - 1.0) < 0.01


@pytest.mark.parametrize(("category", "n", "n_anchors"), [("dlo", 20, 2), ("bdlo", 25, 4), ("cloth", 36, 4)])
def test_ground_truth_layout(category, n, n_anchors):
    sim = hung(category)
    gt = sim.ground_truth()
    assert gt.keypoints.shape == (n, 3) and gt.category == category
    assert len(gt.anchors) == n_anchors and gt.edges.max() < n
    assert len(gt.centreline) > 5 * n
    # The grasped anchors are the keypoints at the TCPs.
    for name, T in HOME:
        k = gt.grasp[name]
        assert k in gt.anchors
        assert np.linalg.norm(gt.keypoints[k] - T[:3, 3]) < 1e-3
    if category == "dlo":  # evenly spaced by arc length
        seg = np.linalg.norm(np.diff(gt.keypoints, axis=0), axis=1)
        assert np.allclose(seg, 0.7 / 19, rtol=0.03)


def _run(seed: int) -> tuple[np.ndarray, np.ndarray]:
    sim = SimObject(SimObjectConfig(category="dlo", seed=seed))
    sim.reset(HOME, settle_time=0.3)
    for k in range(20):
        sim.step(1 / 30, {"left": tcp([0.45, 0.25 - 0.004 * k, 0.40 + 0.003 * k]), "right": HOME[1][1]}, CLOSED)
    return sim.positions, sim.keypoints()


def test_determinism():
    a, b = _run(3), _run(3)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], _run(4)[0])


def test_grasped_end_follows_tcp_and_release_drops_it():
    sim = hung("dlo")
    start = sim.keypoints()[0]
    for k in range(1, 16):  # left TCP moves 6 cm in x and up 4.5 cm over 0.5 s
        T = tcp(HOME[0][1][:3, 3] + k * np.array([0.004, 0.0, 0.003]))
        sim.step(1 / 30, {"left": T, "right": HOME[1][1]}, CLOSED)
        assert np.linalg.norm(sim.keypoints()[0] - T[:3, 3]) < 1e-3
    assert np.linalg.norm(sim.keypoints()[0] - start) > 0.07
    sim.step(0.5, {"left": T, "right": HOME[1][1]}, {"left": False, "right": True})
    assert "left" not in sim.held and sim.ground_truth().grasp["left"] == -1
    assert sim.keypoints()[0][2] < T[2, 3] - 0.2  # the free end fell
    # Closing again far from the rope grasps nothing; the right end is still held.
    sim.step(0.1, {"left": T, "right": HOME[1][1]}, CLOSED)
    assert "left" not in sim.held and sim.ground_truth().grasp["right"] == 19


def test_rendered_table_depth_matches_geometry():
    K = CameraIntrinsics.from_fov(320, 240, 69.0)
    T = mock_camera_pose().matrix()
    r = SceneRenderer(K, T, clutter=0, flying_pixels=0.0, edge_dropout=0.0, seed=1)
    out = r.render([], None, frame_index=0)
    # Analytic z of the table plane z_world = 0 along every pixel's ray.
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, dtype=float)], -1) @ T[:3, :3].T
    s = -T[2, 3] / d[..., 2]
    hit = s > 0
    p = T[:3, 3] + d * s[..., None]
    on_table = hit & (np.abs(p[..., 0]) < 0.95) & (np.abs(p[..., 1]) < 1.35)
    assert on_table.mean() > 0.5
    z_true = np.where(on_table, s, 0.0)
    assert np.allclose(out.depth_true[on_table], z_true[on_table], atol=1e-4)
    depth = out.depth.astype(float) * 1e-3
    ok = on_table & (depth > 0)
    assert ok.sum() > 0.95 * on_table.sum()
    err = depth[ok] - z_true[ok]
    sigma = 0.0015 * z_true[ok] ** 2
    assert abs(np.median(err)) < 1e-3
    assert np.mean(np.abs(err) < 4 * sigma + 0.0006) > 0.99  # noise ~ z^2 plus 1 mm quantisation
    assert out.color.shape == (240, 320, 3) and out.color.dtype == np.uint8


def test_object_pixels_exist_and_noise_is_seeded():
    sim = hung("dlo")
    K = CameraIntrinsics.from_fov(320, 240, 69.0)
    r = SceneRenderer(K, mock_camera_pose().matrix(), seed=2)
    mesh = tube_mesh(sim.x, sim.radius)
    a = r.render([], mesh, frame_index=5, with_mask=True)
    b = r.render([], mesh, frame_index=5, with_mask=True)
    c = r.render([], mesh, frame_index=6)
    assert a.mask is not None and a.mask.sum() > 200
    assert np.array_equal(a.depth, b.depth) and np.array_equal(a.color, b.color)
    assert not np.array_equal(a.depth, c.depth)
    # Object pixels are object-coloured and at the object's depth (about 1 m away).
    assert np.median(a.color[a.mask][:, 0]) > np.median(a.color[a.mask][:, 2]) + 40
    zd = a.depth[a.mask & (a.depth > 0)] * 1e-3
    assert 0.6 < np.median(zd) < 1.4


def test_closing_near_the_object_grasps_the_nearest_particle():
    sim = hung("dlo")
    sim.step(1.0, dict(HOME), {"left": False, "right": True})
    end = sim.keypoints()[0]
    T = tcp(end + [0.0, 0.0, 0.01])  # 1 cm above the fallen end
    sim.step(1 / 30, {"left": T, "right": HOME[1][1]}, {"left": False, "right": True})
    sim.step(1 / 30, {"left": T, "right": HOME[1][1]}, CLOSED)
    assert sim.ground_truth().grasp["left"] == 0
    lifted = tcp(end + [0.0, 0.0, 0.15])
    sim.step(0.5, {"left": lifted, "right": HOME[1][1]}, CLOSED)
    assert sim.keypoints()[0][2] > end[2] + 0.12


def _full_cast(r: SceneRenderer, meshes, clutter: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Reference: every pixel's ray cast against static scene + ``meshes`` at once -> (z (H, W), geometry ids)."""
    K = r.intrinsics
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(*_tensors(*merge_meshes(static_scene(clutter, seed)[0])))
    for v, f in meshes:
        scene.add_triangles(*_tensors(v, f))
    hit = scene.cast_rays(o3d.core.Tensor(r._rays(np.arange(K.width * K.height))))
    geom = hit["geometry_ids"].numpy().astype(np.int64)
    z = np.where(geom != INVALID_ID, hit["t_hit"].numpy(), 0.0)
    return z.reshape(K.height, K.width), geom.reshape(K.height, K.width)


@pytest.mark.parametrize("rasterise", [True, False])
def test_composited_render_equals_a_full_ray_cast(rasterise):
    """The static pre-render + per-frame dynamic geometry gives the depth and mask of casting everything."""
    sim = hung("cloth")
    K = CameraIntrinsics.from_fov(320, 240, 69.0)
    r = SceneRenderer(K, mock_camera_pose().matrix(), clutter=4, seed=3, rasterise=rasterise)
    arms = [
        PandaKinematics(np.array([[1, 0, 0, 0], [0, 1, 0, y], [0, 0, 1, 0], [0, 0, 0, 1.0]])).world_meshes(
            np.array([0.1 * s, -0.2, -0.3 * s, -2.1, 0.0, 1.9, 0.8]), 0.02
        )
        for s, y in ((1, 0.45), (-1, -0.45))
    ]
    obj = sheet_mesh(sim.x.reshape(*sim.topology.grid_shape, 3), sim.radius)
    out = r.render(arms, obj, frame_index=1, with_mask=True)
    z_ref, geom = _full_cast(r, [*arms, obj], clutter=4, seed=3)
    assert np.abs(out.depth_true - z_ref).max() < 1e-4
    mask_ref = geom == 1 + len(arms)
    assert mask_ref.sum() > 300
    assert np.count_nonzero(out.mask != mask_ref) <= 2  # a ray through a shared triangle edge may go either way
    # The error model ran on the dynamic pixels: object pixels have depth near the truth.
    ok = out.mask & (out.depth > 0)
    assert ok.sum() > 0.8 * out.mask.sum()
    assert np.median(np.abs(out.depth[ok] * 1e-3 - z_ref[ok])) < 0.002


def test_renderers_share_the_static_prerender_and_frames_are_writable():
    K = CameraIntrinsics.from_fov(160, 120, 69.0)
    T = mock_camera_pose().matrix()
    a, b = SceneRenderer(K, T, seed=5), SceneRenderer(K, T, seed=5)
    assert a._static_depth is b._static_depth  # built once
    assert SceneRenderer(K, T, seed=6)._static_depth is not a._static_depth
    mesh = tube_mesh(np.stack([np.linspace(0.3, 0.6, 20), np.zeros(20), np.full(20, 0.2)], axis=1), 0.01)
    fa, fb = a.render([], mesh, frame_index=3), b.render([], mesh, frame_index=3)
    assert np.array_equal(fa.depth, fb.depth) and np.array_equal(fa.color, fb.color)
    assert fa.depth.flags.writeable and fa.color.flags.writeable and fa.depth_true.flags.writeable
    fa.depth[:] = 0  # the shared pre-render is untouched
    assert np.array_equal(b.render([], mesh, frame_index=3).depth, fb.depth)
