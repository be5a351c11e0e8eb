"""Colour-free segmentation: lifting, arm mask, depth differencing, background model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from tdcommon.meshes import box_mesh, tube_mesh
from tdcommon.transforms import look_at
from tracking import synthetic as S
from tracking.geometry import depth_to_points, gaps_hidden, hidden_behind, project_points
from tracking.params import TrackingParams
from tracking.segmentation import (
    background_from_depths,
    behind_continuing,
    behind_near_object,
    change_threshold,
    rasterise_depth,
    render_arm_depth,
    render_arm_mask,
    segment_against_background,
    segment_by_difference,
    unchanged_object_pixels,
    update_background,
)

W, H = 640, 480
P = TrackingParams()


@pytest.fixture(scope="module")
def cam():
    return S.default_camera(W, H)


def test_lift_and_project_round_trip(cam):
    K, T = cam
    depth = S.render_depth([S.table_mesh()], K, T, (H, W))
    pts, rc = depth_to_points(depth, K, T)
    assert pts.shape == (H * W, 3)
    assert np.abs(pts[:, 2]).max() < 2e-3  # the table top is z = 0 (1 mm depth quantisation)
    uv, z = project_points(pts, K, T)
    assert np.allclose(uv[:, ::-1], rc, atol=1e-6)
    assert np.allclose(z, depth[rc[:, 0], rc[:, 1]], atol=1e-6)


def test_resolution_is_not_hard_coded():
    K, T = S.default_camera(320, 200)
    depth = S.render_depth([S.table_mesh()], K, T, (200, 320))
    pts, _ = depth_to_points(depth, K, T)
    assert len(pts) == 200 * 320


def test_arm_mask_removes_arm_keeps_object_in_front(cam):
    K, T = cam
    arm = box_mesh((0.0, 0.1, 0.2), (0.05, 0.05, 0.2))
    rope = tube_mesh(np.array([[-0.2, -0.05, 0.1], [0.2, -0.05, 0.1]]), 0.01)
    depth = S.render_depth([S.table_mesh(), arm, rope], K, T, (H, W))
    mask = render_arm_mask(arm[0], arm[1], K, T, (H, W), margin_px=4, depth=depth, margin_m=0.02)
    arm_only = S.render_depth([arm], K, T, (H, W)) > 0
    assert mask[arm_only & (np.abs(depth - S.render_depth([arm], K, T, (H, W))) < 1e-3)].mean() > 0.99
    rope_px = S.render_depth([rope], K, T, (H, W)) > 0
    in_front = rope_px & arm_only
    assert in_front.sum() > 50
    assert not mask[in_front].any()  # the rope crossing in front of the arm survives
    sil = render_arm_mask(arm[0], arm[1], K, T, (H, W), margin_px=0)
    assert abs(int(sil.sum()) - int(arm_only.sum())) < 0.05 * arm_only.sum()


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_arm_depth_casts_only_rays_that_can_hit_and_equals_casting_every_ray(cam, stride):
    """The culled render (rays inside triangle boxes, triangles the grid reaches) is the brute-force one."""
    import open3d as o3d

    K, T = cam
    parts = [box_mesh((x, 0.1, 0.2), (0.05, 0.05, 0.2)) for x in (-0.25, 0.25)]  # two "arms" apart
    parts.append(tube_mesh(np.array([[-3.0, 0.3, 0.1], [3.0, 0.3, 0.1]]), 0.02))  # reaching far out of view
    V = np.concatenate([v for v, _ in parts])
    F = np.concatenate([f + sum(len(v) for v, _ in parts[:k]) for k, (_, f) in enumerate(parts)]).astype(np.int32)
    got = render_arm_depth(V, F, K, T, (H, W), stride)
    # brute force: every ray of the meshes' projected bounding box against every triangle
    R, t = T[:3, :3], T[:3, 3]
    vc = (V - t) @ R
    u, v = K[0, 0] * vc[:, 0] / vc[:, 2] + K[0, 2], K[1, 1] * vc[:, 1] / vc[:, 2] + K[1, 2]
    c0, c1 = int(np.clip(np.floor(u.min()), 0, W)), int(np.clip(np.ceil(u.max()) + 1, 0, W))
    r0, r1 = int(np.clip(np.floor(v.min()), 0, H)), int(np.clip(np.ceil(v.max()) + 1, 0, H))
    cc, rr = np.meshgrid(np.arange(c0, c1, stride), np.arange(r0, r1, stride))
    dc = np.stack([(cc - K[0, 2]) / K[0, 0], (rr - K[1, 2]) / K[1, 1], np.ones_like(cc, dtype=np.float64)], -1)
    dc = dc.reshape(-1, 3) / np.linalg.norm(dc.reshape(-1, 3), axis=1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(t, dc.shape), dc @ R.T], axis=1).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    z = (scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() * dc[:, 2]).astype(np.float32)
    want = np.full((H, W), np.inf, np.float32)
    want[r0:r1, c0:c1] = np.repeat(np.repeat(z.reshape(cc.shape), stride, 0), stride, 1)[: r1 - r0, : c1 - c0]
    assert np.isfinite(got).sum() > 1000 and np.isfinite(got[:, : W // 2]).any() and np.isfinite(got[:, W // 2:]).any()
    np.testing.assert_array_equal(got, want)



@pytest.mark.parametrize("stride", [1, 2, 3])
def test_rasterised_arm_depth_is_the_raycast_one(cam, stride):
    """The z-buffer render hits the pixels the raycast one hits, at the same depth (float32 rounding aside);
    a mesh reaching behind the camera is raycast."""
    K, T = cam
    parts = [box_mesh((x, 0.1, 0.2), (0.05, 0.05, 0.2)) for x in (-0.25, 0.25)]
    parts.append(tube_mesh(np.array([[-3.0, 0.3, 0.1], [3.0, 0.3, 0.1]]), 0.02))  # reaching far out of view
    V = np.concatenate([v for v, _ in parts])
    F = np.concatenate([f + sum(len(v) for v, _ in parts[:k]) for k, (_, f) in enumerate(parts)]).astype(np.int32)
    want = render_arm_depth(V, F, K, T, (H, W), stride)
    got = rasterise_depth(V, F, K, T, (H, W), stride)
    hit = np.isfinite(want)
    assert hit.sum() > 1000
    assert (np.isfinite(got) != hit).sum() <= 0.002 * hit.sum()  # pixel centres on a triangle's edge at most
    both = hit & np.isfinite(got)
    np.testing.assert_allclose(got[both], want[both], atol=1e-5)
    eye = T[:3, 3]
    behind = np.concatenate([V, eye + (eye - V.mean(axis=0))[None]])  # an extra vertex behind the camera
    Fb = np.concatenate([F, [[0, 1, len(V)]]]).astype(np.int32)
    np.testing.assert_array_equal(rasterise_depth(behind, Fb, K, T, (H, W), stride),
                                  render_arm_depth(behind, Fb, K, T, (H, W), stride))

def test_arm_depth_skips_the_arms_back_faces_and_draws_the_same_image(cam):
    """The Panda's link meshes are closed and outward: drawn without their back faces they give the same
    z-buffer image, pixel for pixel; a mesh whose faces are not all outward keeps them (box turned inside out)."""
    from tdcommon.meshes import closed_outward
    from tdcommon.robot import HOME_Q, PandaKinematics

    K, T = cam
    V, F = PandaKinematics(np.array([[1, 0, 0, 0.35], [0, 1, 0, -0.4], [0, 0, 1, 0], [0, 0, 0, 1.0]])).world_meshes(
        np.array(HOME_Q)
    )
    cull = closed_outward(V, F)
    assert cull.all()
    for stride in (1, 2):
        want = rasterise_depth(V, F, K, T, (H, W), stride)
        assert np.isfinite(want).sum() > 500
        np.testing.assert_array_equal(rasterise_depth(V, F, K, T, (H, W), stride, cull), want)
    v, f = box_mesh((0.0, 0.1, 0.2), (0.05, 0.05, 0.1))
    inside_out = f[:, ::-1]
    assert not closed_outward(v, inside_out).any()
    np.testing.assert_array_equal(
        rasterise_depth(v, inside_out, K, T, (H, W), 1, closed_outward(v, inside_out)),
        rasterise_depth(v, f, K, T, (H, W), 1),
    )


def test_difference_segmentation_isolates_rope_without_colour(cam):
    K, T = cam
    rng = np.random.default_rng(1)
    f0 = S.rope_scene(0.0, K, T, (H, W), rng, arm_offset=0.1)
    f1 = S.rope_scene(0.8, K, T, (H, W), rng)
    f2 = S.rope_scene(1.6, K, T, (H, W), rng, arm_offset=-0.1)
    am = render_arm_mask(f1.arm_vertices, f1.arm_triangles, K, T, (H, W), P.arm_margin_px, f1.depth, P.arm_margin_m)
    seg = segment_by_difference(np.stack([f0.depth, f2.depth]), f1.depth, K, T, P, am)
    d, _ = cKDTree(f1.centreline).query(seg.points)
    assert d.max() < f1.radius + 0.004  # nothing but rope
    cover, _ = cKDTree(seg.points).query(f1.centreline)
    assert cover.max() < 0.01  # the whole rope
    one_ref = segment_by_difference(f0.depth, f1.depth, K, T, P, am)
    assert np.all(cKDTree(f1.centreline).query(one_ref.points)[0] < f1.radius + 0.004)


def test_background_model_segmentation_and_update(cam):
    K, T = cam
    rng = np.random.default_rng(2)
    f0 = S.rope_scene(0.0, K, T, (H, W), rng)
    f1 = S.rope_scene(1.0, K, T, (H, W), rng)
    bg = background_from_depths(np.stack([f0.depth, S.rope_scene(0.0, K, T, (H, W), rng).depth]))
    am = render_arm_mask(f1.arm_vertices, f1.arm_triangles, K, T, (H, W), P.arm_margin_px, f1.depth, P.arm_margin_m)
    bg = update_background(bg, f1.depth, P, am)  # where the rope stood at t=0 the table is revealed
    seg = segment_against_background(f1.depth, bg, K, T, P, am, prev_keypoints=f1.centreline[::20])
    d, _ = cKDTree(f1.centreline).query(seg.points)
    assert d.max() < f1.radius + 0.004
    # the old rope position is now background: nothing segmented there
    far_from_new = cKDTree(f1.centreline).query(f0.centreline)[0] > 0.03
    assert cKDTree(seg.points).query(f0.centreline[far_from_new])[0].min() > 0.01


def test_dbscan_labels_clusters_and_noise():
    from tracking.segmentation import dbscan_labels

    rng = np.random.default_rng(0)
    a = rng.uniform(0, 0.1, (300, 3)) * [1, 1, 0.05]
    b = a + [0.5, 0, 0]
    noise = np.array([[1.0, 1.0, 1.0], [-1.0, 0.5, 0.0]])
    lab = dbscan_labels(np.concatenate([a, b, noise]), 0.015, 3)
    assert len(set(lab[:300].tolist())) == 1 and len(set(lab[300:600].tolist())) == 1
    assert lab[0] != lab[300] and (lab[:600] >= 0).all() and (lab[600:] == -1).all()
    assert sorted(set(lab[:600].tolist())) == [0, 1]


def test_growth_stops_at_the_depth_step_behind_an_outline():
    from tracking.segmentation import grow_depth_region

    depth = np.full((40, 60), 2.0, np.float32)  # background 2 m
    depth[10:30, 10:40] = np.linspace(1.0, 1.05, 30, dtype=np.float32)[None, :]  # a smooth sheet in front
    seeds = np.zeros(depth.shape, bool)
    seeds[15, 12] = True
    grown = grow_depth_region(depth, seeds, np.ones(depth.shape, bool), 0.02)
    sheet = np.zeros(depth.shape, bool)
    sheet[10:30, 10:40] = True
    assert (grown == sheet).all()


def test_thin_growth_follows_a_diagonal_staircase_across_a_dropped_reading():
    from tracking.segmentation import grow_depth_region

    depth = np.full((30, 30), 2.0, np.float32)  # background 2 m
    line = np.arange(3, 27)
    depth[line, line] = 1.0 + 0.005 * (line - 3)  # a tube one pixel wide, receding 5 mm a pixel
    depth[15, 15] = 0.0  # one reading dropped out
    seeds = np.zeros(depth.shape, bool)
    seeds[3, 3] = True
    cand = np.ones(depth.shape, bool)
    assert grow_depth_region(depth, seeds, cand, 0.01).sum() == 1  # 4-connected: the seed alone
    grown = grow_depth_region(depth, seeds, cand, 0.01, thin=True)
    tube = (depth > 0) & (depth < 1.5)
    assert (grown == tube).all()


def test_empty_space_behind_the_scene_is_far_in_the_references():
    from tracking.segmentation import difference_masks, far_where_no_return

    refs = np.full((2, 60, 80), 1.5, np.float32)
    refs[:, :, :30] = 0.0  # no return on the left third: empty space beyond the sensor's range
    refs[0, 40, 50] = refs[1, 40, 50] = 0.0  # one hole on the table: unknown, not far
    K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
    out = far_where_no_return(refs, K, P)
    assert (out[:, :, :30] == np.float32(P.depth_max_m)).all() and (out[:, 40, 50] == 0).all()
    depth = np.full((60, 80), 1.5, np.float32)
    depth[:, :30] = 0.0
    depth[20:40, 10:12] = 1.0  # a rope hanging in front of the empty space
    depth[40, 50] = 1.0  # a reading where the references had a hole
    appeared, _ = difference_masks(out, depth, P)
    assert appeared[20:40, 10:12].all() and appeared.sum() == 40


def _lying_rope(length: float = 0.3, radius: float = 0.007) -> tuple[np.ndarray, S.Mesh]:
    """A straight rope lying on the table along x: centreline (M, 3) m at height radius, and its mesh."""
    c = np.stack([np.linspace(-length / 2, length / 2, 121), np.zeros(121), np.full(121, radius)], axis=1)
    return c, tube_mesh(c, radius)


def _rope_on_table(cam, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``_lying_rope`` rendered with noise: centreline (M, 3) m, table-only and scene depths (H, W) m, rope pixels."""
    K, T = cam
    rng = np.random.default_rng(seed)
    c, rope = _lying_rope()
    table = S.render_depth([S.table_mesh()], K, T, (H, W), rng=rng)
    depth = S.render_depth([S.table_mesh(), rope], K, T, (H, W), rng=rng)
    return c, table, depth, S.render_depth([rope], K, T, (H, W)) > 0


def test_support_plane_is_the_table(cam):
    from tracking.segmentation import support_plane

    K, T = cam
    rng = np.random.default_rng(0)
    box = box_mesh((0.1, 0.1, 0.1), (0.1, 0.1, 0.1))
    depth = S.render_depth([S.table_mesh(), box], K, T, (H, W), rng=rng)
    plane = support_plane(depth, K, T, P)
    assert plane is not None
    n, off = plane
    assert abs(n[2]) > 0.999 and n[2] > 0  # the table's normal, towards the camera (above the table)
    assert abs(off) < 2e-3
    # no plane holds this share of the pixels: no support, no height test
    strict = TrackingParams(attach_plane_min_fraction=0.999, attach_plane_tol_m=0.0005)
    assert support_plane(depth, K, T, strict) is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_support_plane_finds_a_far_table_whose_noise_is_wider_than_the_fixed_tolerance(seed):
    """A table ~1.9 m away reads ~8 mm RMS: under a third of the image lies within ``attach_plane_tol_m`` of it
    (a cabinet fills the rest), so the fixed tolerance alone finds no plane; the depth-noise one does."""
    from tracking.segmentation import support_plane

    w, h = 160, 120
    K, T = S.intrinsics(w, h), look_at([0.0, -1.2, 1.5], [0.0, 0.0, 0.0])
    cabinet = box_mesh((0.0, 0.1, 0.3), (0.55, 0.55, 0.3))
    depth = S.render_depth([S.table_mesh(), cabinet], K, T, (h, w), noise_coeff=0.0022,
                           rng=np.random.default_rng(seed))
    assert support_plane(depth, K, T, TrackingParams(support_sigma_k=0.0)) is None
    plane = support_plane(depth, K, T, P)
    assert plane is not None
    n, off = plane
    assert n[2] > 0.999 and abs(off) < 3e-3


def test_a_far_tables_noise_does_not_stand_above_it():
    """~2 m from the camera the table's noise reaches past ``attach_min_height_m``: the height test's floor widens
    with the depth noise, so few table pixels count as above it, while a box 3 cm tall still does."""
    from tracking.segmentation import above_support, support_plane

    w, h = 160, 120
    K, T = S.intrinsics(w, h), look_at([0.0, -1.2, 1.5], [0.0, 0.0, 0.0])
    box = box_mesh((0.0, 0.0, 0.015), (0.1, 0.1, 0.015))
    rng = np.random.default_rng(3)
    depth = S.render_depth([S.table_mesh(), box], K, T, (h, w), noise_coeff=0.0018, rng=rng)
    on_box = S.render_depth([box], K, T, (h, w)) > 0
    plane = support_plane(depth, K, T, P)
    fixed = TrackingParams(support_sigma_k=0.0)
    noisy = above_support(depth, K, T, plane, fixed)[~on_box].mean()
    above = above_support(depth, K, T, plane, P)
    assert noisy > 0.1 and above[~on_box].mean() < 0.5 * noisy
    assert above[on_box].mean() > 0.9


def test_attached_growth_completes_an_unmoved_end_lying_on_the_table(cam):
    from tracking.segmentation import Segmentation, grow_attached_tubes, support_plane, voxel_downsample

    K, T = cam
    c, table, depth, on_rope = _rope_on_table(cam, 1)
    pts, _ = depth_to_points(depth, K, T, on_rope)
    pts = pts[pts[:, 2] > 0.004]  # the rope's upper part, as differencing sees it
    moved = voxel_downsample(pts[pts[:, 0] < 0.15 - 0.025], P.voxel_m)  # the last 2.5 cm did not move
    seg = Segmentation(moved, len(moved), 1)
    out = grow_attached_tubes(depth, seg, K, T, P, None, support_plane(table, K, T, P))
    assert len(out.points) > len(moved)
    np.testing.assert_array_equal(out.points[: len(moved)], moved)  # what was there stays
    added = out.points[len(moved):]
    assert added[:, 0].max() > 0.15 - 0.005  # the end is reached
    d, _ = cKDTree(c).query(added)
    assert (d < 0.007 + 0.004).all()  # rope only: none of the table around it
    # the same end without the table plane cannot be told from the table: nothing is taken from it
    bare = grow_attached_tubes(depth, seg, K, T, P, None, None)
    d, _ = cKDTree(c).query(bare.points[len(moved):])
    assert (d < 0.011).all()


def test_refined_cloud_is_relifted_at_full_resolution(cam):
    from tracking.geometry import decimated_intrinsics
    from tracking.segmentation import refine_object_cloud, voxel_downsample

    K, T = cam
    rng = np.random.default_rng(2)
    c, rope = _lying_rope()
    depth = S.render_depth([S.table_mesh(), rope], K, T, (H, W), rng=rng)
    on_rope = S.render_depth([rope], K, T, (H, W)) > 0
    s = 4
    Kd = decimated_intrinsics(K, s)
    coarse_pts, _ = depth_to_points(depth[::s, ::s], Kd, T, on_rope[::s, ::s])
    coarse = voxel_downsample(coarse_pts, P.voxel_m)
    fine = refine_object_cloud(depth, coarse, K, T, P)
    assert len(fine) > 1.5 * len(coarse)
    d, _ = cKDTree(coarse).query(fine)
    assert d.max() <= 1.5 * P.voxel_m  # nothing far from the segmented object comes in
    skin = np.abs(cKDTree(c).query(fine)[0] - 0.007)
    assert np.percentile(skin, 95) < 0.003


def test_component_spreads_match_per_component_pca():
    from tracking.segmentation import component_spreads

    rng = np.random.default_rng(4)
    pts = rng.normal(size=(300, 3)) * np.array([0.05, 0.01, 0.002])
    labels = rng.integers(0, 4, 300)
    labels[labels == 2] = 3  # label 2 empty
    out = component_spreads(pts, labels)
    assert out.shape == (4, 3)
    np.testing.assert_allclose(out[2], 0.0)
    for c in (0, 1, 3):
        q = pts[labels == c] - pts[labels == c].mean(axis=0)
        ref = np.sqrt(np.maximum(np.linalg.eigvalsh(q.T @ q / len(q)), 0.0))
        np.testing.assert_allclose(out[c], ref, atol=1e-12)


def test_refined_grown_cloud_regrows_an_edge_on_surface_at_full_resolution(cam):
    """A surface seen almost edge-on steps 24 mm per decimated pixel (over ``grow_step_m``): the
    decimated growth lost its upper half; against the references it is regrown at full resolution,
    and nothing of the table behind its outline comes in."""
    from tracking.geometry import decimated_intrinsics
    from tracking.segmentation import refine_object_cloud, voxel_downsample

    K, T = cam
    table = S.render_depth([S.table_mesh()], K, T, (H, W))
    depth = table.copy()
    r0, r1, c0, c1 = 200, 280, 250, 390
    rows = np.arange(r0, r1, dtype=np.float32)[:, None]
    depth[r0:r1, c0:c1] = 0.4 + 0.006 * (rows - r0)  # 6 mm a row: 24 mm a decimated row
    assert table[r0:r1, c0:c1].min() > 0.95
    s = 4
    Kd = decimated_intrinsics(K, s)
    kept = np.zeros((H, W), bool)
    kept[240:r1, c0:c1] = True  # what the decimated growth found
    coarse_pts, _ = depth_to_points(depth[::s, ::s], Kd, T, kept[::s, ::s])
    coarse = voxel_downsample(coarse_pts, P.voxel_m)
    refs = table[None, ::s, ::s]
    plain = refine_object_cloud(depth, coarse, K, T, P)
    grown = refine_object_cloud(depth, coarse, K, T, P, refs=refs)
    top = lambda pts: project_points(pts, K, T)[0][:, 1].min()  # noqa: E731
    assert top(plain) > 235  # near the coarse cloud only
    assert top(grown) < r0 + 2  # the whole strip
    z = project_points(grown, K, T)[1]
    assert z.max() < 0.4 + 0.006 * (r1 - r0) + 0.01  # no table point


def test_refined_1d_cloud_regrows_its_unmoved_end_at_full_resolution(cam):
    """With the table plane, refinement grows a rope's end the decimated cloud missed, at full resolution."""
    from tracking.geometry import decimated_intrinsics
    from tracking.segmentation import refine_object_cloud, support_plane, voxel_downsample

    K, T = cam
    c, table, depth, on_rope = _rope_on_table(cam, 5)
    s = 4
    coarse_pts, _ = depth_to_points(depth[::s, ::s], decimated_intrinsics(K, s), T, on_rope[::s, ::s])
    coarse_pts = coarse_pts[(coarse_pts[:, 2] > 0.004) & (coarse_pts[:, 0] < 0.15 - 0.03)]  # the end did not move
    coarse = voxel_downsample(coarse_pts, P.voxel_m)
    plain = refine_object_cloud(depth, coarse, K, T, P)
    grown = refine_object_cloud(depth, coarse, K, T, P, support=support_plane(table, K, T, P))
    assert plain[:, 0].max() < 0.15 - 0.02
    assert grown[:, 0].max() > 0.15 - 0.005  # the end is reached
    d, _ = cKDTree(c).query(grown)
    assert (d < 0.007 + 0.004).all()  # rope only: none of the table around it


def test_object_standing_still_in_the_references_is_not_background(cam):
    """A rope that stood where it is in every reference: its pixels' background becomes unknown, so the
    tracking segmentation finds it (near the tracked keypoints) instead of treating it as background; an
    unknown pixel away from the object is learned from two frames."""
    K, T = cam
    rng = np.random.default_rng(4)
    refs = np.stack([S.rope_scene(0.0, K, T, (H, W), rng).depth for _ in range(2)])
    f1 = S.rope_scene(0.0, K, T, (H, W), rng)  # not moved yet (slow motion)
    bg = background_from_depths(refs)
    cloud, _ = depth_to_points(f1.depth, K, T, S.render_depth([tube_mesh(f1.centreline, f1.radius)], K, T, (H, W)) > 0)
    kp = f1.centreline[::20]
    old = segment_against_background(f1.depth, bg, K, T, P, None, kp)
    assert len(old.points) <= 2  # the rope is in the background (a stray reading near it at most)
    still = unchanged_object_pixels(f1.depth, bg, cloud, K, T, P)
    rope_px = S.render_depth([tube_mesh(f1.centreline, f1.radius)], K, T, (H, W)) > 0
    assert still[rope_px].mean() > 0.9
    pts, _ = depth_to_points(f1.depth, K, T, still)
    assert (cKDTree(f1.centreline).query(pts)[0] < f1.radius + 0.004).all()  # rope only, no table
    bg[still] = 0.0
    bg[:20, :20] = 0.0  # table pixels never seen (missing in every reference)
    behind = behind_near_object(f1.depth, bg, P, cloud, K, T)
    seg = segment_against_background(f1.depth, bg, K, T, P, None, kp, behind)
    d, _ = cKDTree(f1.centreline).query(seg.points)
    assert d.max() < f1.radius + 0.004
    assert cKDTree(seg.points).query(f1.centreline)[0].max() < 0.01  # the whole rope
    upd = update_background(bg, f1.depth, P, prev_depth=f1.depth, keep=behind)
    assert (upd[:20, :20] > 0).all()  # learned: nothing tracked there
    assert (upd[still] == 0).all()  # still unknown: the tracked object stands there


def test_background_moves_back_on_a_small_step_only_after_consecutive_frames():
    """Just behind the background (noise): every frame of the window must agree and the nearest reading is
    taken; far behind (a revealed surface): the current and the previous frame suffice."""
    from tracking.segmentation import change_threshold

    bg = np.full((4, 4), 1.0, np.float32)
    thr = float(change_threshold(bg, P)[0, 0])
    small, big = 1.5 * thr, 3.0 * P.background_jump_k * thr
    prev2, prev1, cur = (np.full((4, 4), 1.0, np.float32) for _ in range(3))
    prev1[0, 0] = cur[0, 0] = 1.0 + small  # two frames just behind: not enough
    prev2[1, 1], prev1[1, 1], cur[1, 1] = 1.0 + small, 1.0 + 1.2 * thr, 1.0 + small  # three frames
    prev1[2, 2] = cur[2, 2] = 1.0 + big  # revealed
    out = update_background(bg, cur, P, prev_depth=np.stack([prev2, prev1]))
    assert out[0, 0] == 1.0
    assert out[1, 1] == pytest.approx(1.0 + 1.2 * thr)  # the nearest of the three
    assert out[2, 2] == pytest.approx(1.0 + big)
    assert (out[3] == 1.0).all()
    two = update_background(bg, cur, P, prev_depth=prev1, nearest=False)  # one previous frame: as before
    assert two[0, 0] == pytest.approx(1.0 + small) == two[1, 1]  # the current reading


def test_initial_rope_cloud_is_grown_up_to_the_grippers_holding_it(cam):
    """Only the middle of a hanging rope moved (slow start): its still ends are grown up to the held TCPs; a
    growth that cannot reach another gripper is dropped, and the still parts are then grown as free ends (rope
    only, nothing near that gripper)."""
    from tracking.pipeline import LivePipeline
    from tracking.segmentation import Segmentation

    K, T = cam
    s = np.linspace(-1.0, 1.0, 200)
    c = np.stack([0.25 * s, np.zeros_like(s), 0.03 + 0.15 * s**2], axis=1)  # a U hanging between two grippers
    r = 0.006
    depth = S.render_depth([S.table_mesh(), tube_mesh(c, r)], K, T, (H, W))
    table = S.render_depth([S.table_mesh()], K, T, (H, W))
    pipe = LivePipeline(P, K, T, "1d")
    d, t = pipe.decimate(depth), pipe.decimate(table)
    pipe.set_reference(t)
    pts, _ = depth_to_points(d, pipe.K_seg, T, np.abs(d - t) > 0.002)
    middle = pts[np.abs(pts[:, 0]) < 0.08]
    seg = Segmentation(middle, len(middle), 1)
    out = pipe.reach_grippers(d, seg, None, c[[0, -1]])
    assert cKDTree(out.points).query(c[[0, -1]])[0].max() < P.grasp_gate_m
    assert (cKDTree(c).query(out.points)[0] < r + 0.005).all()  # rope only
    far = np.array([[0.0, 0.6, 0.3]])  # nothing leads there
    free = pipe.reach_grippers(d, seg, None, far)
    np.testing.assert_array_equal(free.points[: len(middle)], middle)
    assert len(free.points) > len(middle)
    assert (cKDTree(c).query(free.points)[0] < r + 0.005).all()  # rope only
    assert cKDTree(free.points).query(far)[0].min() > P.grasp_gate_m


@pytest.mark.parametrize("gap", [0.10, 0.25])
def test_an_end_the_hand_hides_beyond_the_grasp_gate_is_still_put_at_its_tcp(gap: float) -> None:
    """A rope whose seen end stops 10 or 25 cm short of a TCP (beyond ``grasp_gate_m``) is held there when the
    arm's pixels cover the way from that end to the TCP; not when the way is in plain sight."""
    from tracking.pipeline import LivePipeline

    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)  # camera at the origin looking along +z
    x = np.linspace(-0.35, 0.0, 300)
    cloud = np.stack([x, 0.03 * np.sin(6.0 * x), np.ones_like(x)], axis=1)  # seen up to x = 0
    tcp = np.array([[-0.35, 0.0, 1.0], [gap, 0.0, 1.0]])  # the second beyond the seen end
    pipe = LivePipeline(P, K, T, "1d")
    h, w = pipe.decimate(np.zeros((480, 640))).shape
    u = pipe.K_seg[0, 0] * 0.003 + pipe.K_seg[0, 2]  # a hand over x > 3 mm around the row of the rope
    v0, v1 = pipe.K_seg[1, 2] - pipe.K_seg[1, 1] * 0.05, pipe.K_seg[1, 2] + pipe.K_seg[1, 1] * 0.05
    hand = np.zeros((h, w), bool)
    hand[int(v0): int(v1) + 1, int(u):] = True
    gates = pipe.grasp_gates(cloud, hand, tcp)
    np.testing.assert_allclose(gates, [P.grasp_gate_m, gap + P.grasp_gate_m])
    np.testing.assert_allclose(pipe.grasp_gates(cloud, np.zeros_like(hand), tcp), P.grasp_gate_m)  # in sight
    ini, _ = pipe.tracker.initialise(cloud, tcp=tcp, kind="1d", grasp_gate=gates)
    assert (pipe.tracker.grasp_idx >= 0).all()
    np.testing.assert_allclose(ini.keypoints[pipe.tracker.grasp_idx], tcp, atol=1e-9)
    assert ini.topology.rest.sum() > 0.34 + gap  # the rest lengths span the hidden gap
    pipe.tracker.initialise(cloud, tcp=tcp, kind="1d")  # the default gate: that end is left free
    assert pipe.tracker.grasp_idx[1] < 0


def test_a_cloth_corner_the_hand_hides_beyond_the_grasp_gate_is_still_put_at_its_tcp() -> None:
    """A cloth seen up to 10 cm short of a TCP that holds its corner (beyond ``grasp_gate_m``), the hand covering
    the way, has that corner put at the TCP; with the default gate the grid ends on the seen corner instead."""
    from tracking.pipeline import LivePipeline

    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)  # camera at the origin looking along +z
    x, y = np.meshgrid(np.linspace(-0.2, 0.2, 81), np.linspace(-0.15, 0.15, 61))
    cloud = np.stack([x.ravel(), y.ravel(), 1.0 + 0.02 * np.sin(8.0 * x.ravel())], axis=1)  # seen up to x = 0.2
    z = 1.0 + 0.02 * np.sin(8.0 * np.array([-0.2, 0.3]))
    tcp = np.array([[-0.2, -0.15, z[0]], [0.3, -0.15, z[1]]])  # the second 10 cm beyond the seen top corner
    pipe = LivePipeline(P, K, T, "2d")
    h, w = pipe.decimate(np.zeros((480, 640))).shape
    u = pipe.K_seg[0, 0] * 0.2 + pipe.K_seg[0, 2]  # a hand over x > 0.2 around the top side
    v0, v1 = pipe.K_seg[1, 2] - pipe.K_seg[1, 1] * 0.2, pipe.K_seg[1, 2] - pipe.K_seg[1, 1] * 0.1
    hand = np.zeros((h, w), bool)
    hand[int(v0): int(v1) + 1, int(u):] = True
    gates = pipe.grasp_gates(cloud, hand, tcp)
    assert gates[0] == P.grasp_gate_m and gates[1] > 0.1 + P.grasp_gate_m - 0.01
    ini, _ = pipe.tracker.initialise(cloud, tcp=tcp, kind="2d", grasp_gate=gates)
    assert (pipe.tracker.grasp_idx >= 0).all()
    np.testing.assert_allclose(ini.keypoints[pipe.tracker.grasp_idx], tcp, atol=1e-9)
    pipe.tracker.initialise(cloud, tcp=tcp, kind="2d")  # the default gate: that corner is left free
    assert pipe.tracker.grasp_idx[1] < 0


def test_a_cloth_corner_the_hand_hides_within_the_grasp_gate_gets_the_hidden_length_too() -> None:
    """A cloth seen 6 cm short of a TCP (within ``grasp_gate_m``), the hand covering the way: the gate is that
    distance plus ``grasp_gate_m``, since where the hand hides the corner the contour's corner may lie farther than
    the nearest seen point (cloth_medium_c408: seen 73 mm from the TCP, its contour's corner 86 mm). A rope's end
    keeps the plain gate there."""
    from tracking.pipeline import LivePipeline

    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    x, y = np.meshgrid(np.linspace(-0.2, 0.2, 81), np.linspace(-0.15, 0.15, 61))
    cloud = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=1)
    tcp = np.array([[-0.2, -0.15, 1.0], [0.26, -0.15, 1.0]])  # the second 6 cm beyond the seen top corner
    gates = {}
    for kind in ("2d", "1d"):
        pipe = LivePipeline(P, K, np.eye(4), kind)
        h, w = pipe.decimate(np.zeros((480, 640))).shape
        u = pipe.K_seg[0, 0] * 0.2 + pipe.K_seg[0, 2]  # a hand over x > 0.2 around the top side
        v0, v1 = pipe.K_seg[1, 2] - pipe.K_seg[1, 1] * 0.2, pipe.K_seg[1, 2] - pipe.K_seg[1, 1] * 0.1
        hand = np.zeros((h, w), bool)
        hand[int(v0): int(v1) + 1, int(u):] = True
        gates[kind] = pipe.grasp_gates(cloud, hand, tcp)
    assert gates["2d"][0] == P.grasp_gate_m and gates["2d"][1] == pytest.approx(0.06 + P.grasp_gate_m, abs=1e-6)
    np.testing.assert_array_equal(gates["1d"], [P.grasp_gate_m, P.grasp_gate_m])


def test_grown_segmentation_with_the_table_plane_takes_the_still_part_of_a_hanging_sheet(cam):
    """Only the upper half of a sheet hanging in front of the table moved: growth over changed pixels keeps
    that half; with the reference's table plane it also crosses the still lower half, and never the table."""
    from tracking.segmentation import support_plane

    K, T = cam
    table = S.render_depth([S.table_mesh()], K, T, (H, W))
    r0, rm, r1, c0, c1 = 120, 200, 280, 220, 420
    frame = table.copy()
    frame[r0:r1, c0:c1] = 0.6
    ref = frame.copy()
    ref[r0:rm, c0:c1] = 0.65  # the upper half was farther back in the reference
    sheet = np.zeros((H, W), bool)
    sheet[r0:r1, c0:c1] = True
    pts, _ = depth_to_points(frame, K, T, sheet)
    assert pts[:, 2].min() > 0.05  # the sheet hangs above the table
    plain = segment_by_difference(ref[None], frame, K, T, P, grow=True)
    full = segment_by_difference(ref[None], frame, K, T, P, grow=True, support=support_plane(table, K, T, P))
    rows = lambda seg: project_points(seg.points, K, T)[0][:, 1]  # noqa: E731
    assert rows(plain).max() < rm + 3  # the moved half only
    assert rows(full).max() > r1 - 4 and rows(full).min() < r0 + 3  # the whole sheet
    assert (project_points(full.points, K, T)[1] < 0.6 + 0.01).all()  # no table point


def _steep_tube(shape: tuple[int, int]):
    """A rope end hanging away from a camera above, at 70 degrees to the image plane: camera (K, T),
    centreline (M, 3) m, table-only and scene depths (H, W) m (noisy)."""
    h, w = shape
    K, T = S.intrinsics(w, h), look_at([0.0, -0.7, 0.8], [0.0, 0.0, 0.0])
    ray = np.array([0.0, 0.1, 0.35]) - T[:3, 3]
    ray /= np.linalg.norm(ray)
    d = np.cos(np.radians(20)) * ray + np.sin(np.radians(20)) * np.array([1.0, 0.0, 0.0])
    c = np.array([0.0, 0.1, 0.35]) + np.linspace(0.0, 0.24, 97)[:, None] * (d / np.linalg.norm(d))
    rng = np.random.default_rng(3)
    table = S.render_depth([S.table_mesh()], K, T, shape, rng=rng)
    depth = S.render_depth([S.table_mesh(), tube_mesh(c, 0.006)], K, T, shape, rng=rng)
    return K, T, c, table, depth


def test_attached_growth_follows_a_tube_hanging_away_from_the_camera():
    # on a decimated image (a 5 mm pixel footprint) neighbouring pixels of such a tube lift ~1.5 cm apart in
    # depth, and each growth step (attach_reach_m) adds a row of one or two pixels: still the tube's rest
    # (as LivePipeline.reach_grippers grows a free end)
    from tracking.segmentation import Segmentation, grow_attached_tubes, support_plane

    K, T, c, table, depth = _steep_tube((180, 240))
    plane = support_plane(table, K, T, P)
    top = c[c[:, 2] > c[0, 2] - 0.04]  # the part that moved: its first 4 cm or so
    pts, _ = depth_to_points(depth, K, T, depth > 0)
    seg = Segmentation(pts[cKDTree(top).query(pts)[0] < 0.008], 0, 1)
    out = seg
    for _ in range(P.attach_iterations):
        grown = grow_attached_tubes(depth, out, K, T, P, None, plane, min_part_px=1)
        if len(grown.points) == len(out.points):
            break
        out = grown
    d, _ = cKDTree(c).query(out.points)
    assert (d < 0.006 + 0.01).all()  # the tube only
    reach, _ = cKDTree(out.points).query(c)
    assert reach[-10:].min() < 0.015  # its far end is reached


def test_tracking_keeps_the_sparse_points_of_a_steep_tube_on_the_object():
    # a tube steep to the image plane lifts to single points ~2 cm apart: DBSCAN calls them noise, yet where
    # the object just was they are object; noise elsewhere is not
    from tracking.segmentation import dbscan_labels, select_clusters_near

    rng = np.random.default_rng(0)
    body = rng.uniform([0.0, 0.0, 0.0], [0.3, 0.012, 0.012], (400, 3))  # a dense rope part
    steep = np.array([0.3, 0.0, 0.0]) + np.linspace(0.06, 0.24, 10)[:, None] * np.array([0.0, 0.0, 1.0])
    # 10-20 cm from the object, and a flying pixel 2 cm beside the dense part, within track_attach_m of it
    stray = np.array([[0.3, 0.0, 0.3], [0.0, 0.2, 0.0], [0.15, 0.006, 0.032]])
    pts = np.concatenate([body, steep, stray])
    lab = dbscan_labels(pts, P.dbscan_eps_m, P.dbscan_min_points)
    assert (lab[400:] == -1).all()
    object_now = np.concatenate([body[::20], steep + [0.01, 0.0, 0.0]])  # where the object was a frame ago
    assert cKDTree(object_now).query(stray[-1])[0] < P.track_attach_m
    kept = select_clusters_near(pts, lab, object_now, P)
    assert len(kept) == 410
    np.testing.assert_array_equal(select_clusters_near(pts, lab, body[::20], P, samples=object_now), kept)
    np.testing.assert_array_equal(kept[-10:], steep)
    # without the steep part in the previous object its points are too far from it
    assert len(select_clusters_near(pts, lab, body[::20], P)) == 400
    # nor on the table: a plane through the top of the steep part leaves it out
    table = (np.array([0.0, 0.0, 1.0]), 0.3)
    assert len(select_clusters_near(pts, lab, object_now, P, table)) == 400


def test_table_level_points_go_but_a_flat_objects_beside_where_it_lay():
    # a branch hangs down to 2 cm above the table; the table's noise below its tip (a shadow) joins its cluster
    # and would extend the tip. A cloth lying on the table keeps its table-level points.
    from tracking.segmentation import dbscan_labels, select_clusters_near

    rng = np.random.default_rng(1)
    table = (np.array([0.0, 0.0, 1.0]), 0.0)
    hanging = np.stack([np.zeros(60), np.zeros(60), np.linspace(0.3, 0.02, 60)], axis=1)  # tip 2 cm up
    trail = np.stack([np.linspace(0.004, 0.12, 25), np.zeros(25), rng.uniform(-0.003, 0.003, 25)], axis=1)
    pts = np.concatenate([hanging, trail])
    lab = dbscan_labels(pts, P.dbscan_eps_m, P.dbscan_min_points)
    assert (lab >= 0).all()  # clusters (near the hanging part), not noise
    kept = select_clusters_near(pts, lab, hanging[::5], P, table)
    d = np.linalg.norm(trail[:, None] - hanging[None, ::5], axis=2).min(axis=1)
    assert len(kept) == 60 + int((d < P.track_attach_m).sum()) < len(pts)
    assert np.abs(kept[:, 0]).max() < P.track_attach_m + 0.02
    # without the table plane (none measured) nothing changes
    assert len(select_clusters_near(pts, lab, hanging[::5], P)) == len(pts)
    # a tube's (not flat) table-level points all go: noise, or the sides of one whose top stands above the table
    tube = select_clusters_near(pts, lab, hanging[::5], P, table, flat=False)
    np.testing.assert_array_equal(tube, hanging[hanging[:, 2] >= P.attach_min_height_m])
    # a flat object (a cloth) lying on the table, where it lay a frame ago: all of it stays
    gx, gy = np.meshgrid(np.arange(0.0, 0.3, 0.008), np.arange(0.0, 0.2, 0.008))
    lying = np.stack([gx.ravel(), gy.ravel(), rng.uniform(0.0, 0.003, gx.size)], axis=1)
    lab2 = dbscan_labels(lying, P.dbscan_eps_m, P.dbscan_min_points)
    assert len(select_clusters_near(lying, lab2, lying[::3] + [0.005, 0.0, 0.0], P, table)) == len(lying)
    assert len(select_clusters_near(lying, lab2, lying[::3], P, table, flat=False)) == 0


def test_a_cloth_side_hanging_edge_on_from_the_hand_is_kept_chained_from_its_held_corner():
    # a cloth's side turned edge-on below the hand lifts to single points ~2 cm apart going away from the camera:
    # DBSCAN calls them noise, and the grid that left them (bunched on the sheet below) keeps nothing near them;
    # chained from the held corner in steps of at most tip_step_m they are kept, stray points are not
    from dataclasses import replace

    from tracking.init import Topology, grid_topology
    from tracking.segmentation import dbscan_labels, select_clusters_near
    from tracking.tracker import held_seeds

    rng = np.random.default_rng(2)
    sheet = rng.uniform([0.12, -0.15, 0.0], [0.3, 0.15, 0.004], (600, 3))  # the seen part, 12-30 cm from the hand
    tcp = np.array([0.0, -0.15, 0.0])
    strip = tcp + np.linspace(0.018, 0.09, 5)[:, None] * np.array([0.6, 0.0, 0.8])  # steps of 1.8 cm
    stray = np.array([[0.0, 0.1, 0.15], [-0.06, -0.15, -0.08]])  # 25 cm from the hand; 10 cm, but 5 cm off the strip
    pts = np.concatenate([sheet, strip, stray])
    lab = dbscan_labels(pts, P.dbscan_eps_m, P.dbscan_min_points)
    assert (lab[600:] == -1).all()
    gx, gy = np.meshgrid(np.linspace(0.15, 0.3, 6), np.linspace(-0.15, 0.15, 6))
    grid = np.stack([gx.ravel(), gy.ravel(), np.zeros(36)], axis=1)  # where the grid lay: on the sheet
    grid[0] = tcp  # its held corner at the TCP
    edges, rest = grid_topology(6, 6, 0.06, 0.06)
    topo = Topology("2d", edges, rest, np.zeros(0, np.int64), np.zeros(0, np.int64), [], grid_shape=(6, 6))
    seeds = held_seeds(grid, topo, np.array([0, -1]))
    assert seeds.shape == (1, 4) and np.allclose(seeds[0, :3], tcp)
    assert np.isclose(seeds[0, 3], 0.6)  # the far corner, 10 edges of 6 cm away along the grid
    kept = select_clusters_near(pts, lab, grid, P, held=seeds)
    assert len(kept) == 605
    np.testing.assert_array_equal(kept[-5:], strip)
    assert len(select_clusters_near(pts, lab, grid, P, flat=False, held=seeds)) < 605  # a tube: its tips' rule
    alone = select_clusters_near(pts, lab, grid, P)  # without: only the strip's point within track_attach_m of it
    assert len(alone) == 601 and np.array_equal(alone[-1], strip[0])
    assert held_seeds(grid, topo, np.array([-1, -1])) is None  # nothing held: nothing to chain from
    assert held_seeds(grid, replace(topo, grid_shape=None), np.array([0, -1])) is None  # a rope: its tips' rule


def test_a_tubes_cluster_is_kept_only_near_where_the_object_was():
    # the table's noise beside a rope joins the rope's cluster and trails 15 cm away from it: a rope (not flat)
    # keeps the points within track_gate_m of where it was a frame ago, a cloth (flat) its whole cluster
    from tracking.segmentation import dbscan_labels, select_clusters_near

    rope = np.stack([np.linspace(0.0, 0.3, 100), np.zeros(100), np.zeros(100)], axis=1)
    trail = np.stack([np.full(40, 0.3), np.linspace(0.004, 0.16, 40), np.zeros(40)], axis=1)
    pts = np.concatenate([rope, trail])
    lab = dbscan_labels(pts, P.dbscan_eps_m, P.dbscan_min_points)
    assert len(np.unique(lab)) == 1 and (lab >= 0).all()  # one cluster
    before = rope[::4] + [0.0, 0.01, 0.0]  # where the rope was: 1 cm beside
    tube = select_clusters_near(pts, lab, before, P, flat=False)
    d = np.linalg.norm(pts[:, None] - before[None], axis=2).min(axis=1)
    np.testing.assert_array_equal(tube, pts[d < P.track_gate_m])
    assert len(tube) < len(pts) and len(tube) >= 100
    assert len(select_clusters_near(pts, lab, before, P, flat=True)) == len(pts)


def test_gaps_hidden_only_when_the_mask_covers_the_way_beyond_the_start() -> None:
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)  # camera at the origin looking along +z: (x, y, 1 m) is seen at pixel (320 + 500 x, 240 + 500 y)
    mask = np.zeros((480, 640), bool)
    mask[230:250, 340:] = True  # a "hand" over x > 4 cm on the row y = 0
    a = np.tile([0.0, 0.0, 1.0], (4, 1))
    b = a + [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    got = gaps_hidden(a, b, mask, K, T, skip_m=0.045)
    # hidden beyond its first 4.5 cm / in plain sight / no gap / hidden, then out of the image
    assert got.tolist() == [True, False, False, True]
    assert not gaps_hidden(a[:1], b[:1], mask, K, T, skip_m=0.02)[0]  # its first 4 cm are in sight


def test_hidden_behind_the_mask_unless_well_in_front_of_it() -> None:
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)  # camera at the origin looking along +z
    mask = np.zeros((480, 640), bool)
    mask[:, 320:] = True  # the arm over the right half, seen at 1 m
    depth = np.ones((480, 640))
    depth[:, 600:] = 0.0  # no reading there
    pts = np.array([
        [-0.1, 0.0, 1.1],  # left of the mask: seen
        [0.1, 0.0, 1.1],  # behind the arm
        [0.1, 0.0, 0.99],  # touching it (between fingers): no cloud of its own either
        [0.1, 0.0, 0.8],  # a rope passing well in front of the arm: seen
        [0.59, 0.0, 1.0],  # masked pixel without a depth reading
        [5.0, 0.0, 1.0],  # out of the image: out of sight, whatever the mask
    ])
    got = hidden_behind(pts, mask, depth, K, T, margin_m=0.02)
    assert got.tolist() == [False, True, True, False, True, True]
    assert hidden_behind(pts, np.zeros_like(mask), depth, K, T, margin_m=0.02).tolist() == [False] * 5 + [True]
    # without a mask, behind whatever the depth shows by more than the margin: the first point is behind the surface
    # left of the arm too; the one touching the surface is on it, seen
    got = hidden_behind(pts, None, depth, K, T, margin_m=0.02)
    assert got.tolist() == [True, True, False, False, True, True]
    on = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.015], [0.0, 0.0, 1.03]])  # on the surface, within, beyond the margin
    assert hidden_behind(on, None, depth, K, T, margin_m=0.02).tolist() == [False, False, True]


def test_hidden_behind_a_near_layer_beside_it() -> None:
    """A point in open space with the object's near layer within reach across the image is behind that layer."""
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    depth = np.full((480, 640), 1.5)  # the table
    depth[:, 300:311] = 0.8  # a cloth seen edge-on: a strip in front
    # at 1 m depth, 0.03 m is 15 px: columns 320 and 330 are within reach of the strip (last column 310), 400 not
    pts = np.array([[0.0, 0.0, 1.0], [0.02, 0.0, 1.0], [0.16, 0.0, 1.0], [0.0, 0.0, 0.75]])
    got = hidden_behind(pts, None, depth, K, T, margin_m=0.02, reach_m=0.03)
    assert got.tolist() == [True, False, False, False]  # the last is in front of the strip: seen
    got = hidden_behind(pts, None, depth, K, T, margin_m=0.02, reach_m=0.05)
    assert got.tolist() == [True, True, False, False]
    assert not hidden_behind(pts, None, depth, K, T, margin_m=0.02).any()  # no reach: the old rule


def test_tracking_regains_a_hanging_part_its_background_holds():
    # the tube's lower part hung where it is now in the reference: the background there is the tube itself, and
    # only its upper part (moved since) stands out of it; the thin part continuous with it is grown back
    from tracking.segmentation import complete_thin_parts, support_plane

    K, T, c, table, depth = _steep_tube((180, 240))
    top = c[:40]
    ref = S.render_depth(
        [S.table_mesh(), tube_mesh(c[38:], 0.006), tube_mesh(top + [0.04, 0.0, 0.0], 0.006)], K, T, (180, 240),
        rng=np.random.default_rng(5),
    )
    seg = segment_against_background(depth, ref, K, T, P, None, c[::8])
    assert cKDTree(seg.points).query(c[-10:])[0].min() > 0.03  # the lower part is background
    out = complete_thin_parts(depth, seg, K, T, P, None, support_plane(table, K, T, P))
    d, _ = cKDTree(c).query(out.points)
    assert (d < 0.006 + 0.01).all()  # the tube only
    assert cKDTree(out.points).query(c[-10:])[0].min() < 0.015  # its far end is regained
    off = complete_thin_parts(depth, seg, K, T, TrackingParams(track_attach_iterations=0), None,
                              support_plane(table, K, T, P))
    assert off is seg


def test_voxel_downsample_is_open3ds_grid_and_centroids_bit_for_bit() -> None:
    """The compiled voxel grid (no open3d import on the tracking path) keeps open3d's voxels and centroids."""
    import open3d as o3d

    from tracking.segmentation import voxel_downsample

    rng = np.random.default_rng(11)
    pts = np.concatenate([rng.normal(0.4, 0.05, (3000, 3)), rng.uniform(-0.3, 0.9, (500, 3))])
    for voxel in (0.003, 0.0047, 0.009):
        got = voxel_downsample(pts, voxel)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        want = np.asarray(pcd.voxel_down_sample(voxel).points)
        assert got.shape == want.shape
        np.testing.assert_array_equal(got[np.lexsort(got.T)], want[np.lexsort(want.T)])
    assert voxel_downsample(np.zeros((0, 3)), 0.005).shape == (0, 3)


def test_in_open_space_only_where_the_depth_sees_past_a_point() -> None:
    from tracking.geometry import in_open_space

    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    depth = np.ones((480, 640))  # a wall 1 m in front of a camera at the origin looking along +z
    depth[:, 600:] = 0.0  # no reading there
    pts = np.array([
        [0.0, 0.0, 0.5],  # in front of the wall: the camera would see it
        [0.0, 0.0, 0.99],  # on the wall, within the margin
        [0.0, 0.0, 1.5],  # behind it: out of sight
        [0.59, 0.0, 0.5],  # no reading at its pixel: not known to be open
        [5.0, 0.0, 0.5],  # outside the image
    ])
    assert in_open_space(pts, depth, K, np.eye(4), margin_m=0.02).tolist() == [True, False, False, False, False]


def test_behind_nearest_occluder_moves_a_point_the_camera_would_see_behind_the_arm_beside_it() -> None:
    from tracking.geometry import behind_nearest_occluder, in_open_space, pixels_of

    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    depth = np.ones((480, 640))  # a table 1 m in front of a camera at the origin looking along +z
    arm = np.zeros((480, 640), bool)
    arm[:, 340:360] = True  # a finger 0.5 m from the camera, columns 340-359
    arm[100:120, 130:135] = True  # another finger, 0.5 m from the camera
    depth[arm] = 0.5
    depth[100:120, 100:120] = 0.8  # something the cloud left out, at 0.8 m, beside it
    pts = np.array([
        [0.030, 0.0, 0.8],  # open space at column 338, 2 px left of the finger: behind it
        [0.100, 0.0, 0.8],  # column 382, 22 px (26 mm at 0.8 m) right of it: beyond a 20 mm reach, stays
        [0.052, 0.0, 0.4],  # in front of the finger (on an arm pixel): the camera sees it there, stays
        [-0.312, -0.208, 0.8],  # column 125, 5 px from the other finger, 6 px from a surface at its own depth
        [0.030, 0.0, 1.5],  # behind the table: not in open space, stays
    ])
    X, moved = behind_nearest_occluder(pts, depth, K, np.eye(4), arm, reach_m=0.02, margin_m=0.02)
    assert moved.tolist() == [True, False, False, False, False]
    np.testing.assert_array_equal(X[~moved], pts[~moved])
    r, c, inside, z = pixels_of(X[:1], K, np.eye(4), depth.shape)
    assert inside[0] and c[0] == 340 and z[0] == pytest.approx(0.8)  # the finger's nearest pixel, same depth
    assert not in_open_space(X[:1], depth, K, np.eye(4), 0.02)[0]


def test_a_free_tips_sparse_continuation_is_kept_and_nothing_beside_it() -> None:
    # a branch pointing away from the camera lifts to single points ~2 cm apart beyond where its tip was: DBSCAN
    # calls them noise and they are farther than track_attach_m from the previous object; chained to the tip
    # inside its cone they are kept, a point beside the cone, one beyond the reach and one past a gap are not
    from tracking.segmentation import dbscan_labels, select_clusters_near, tip_continuations
    from tracking.tracker import free_tips

    rng = np.random.default_rng(1)
    body = rng.uniform([0.0, 0.0, 0.0], [0.3, 0.012, 0.012], (400, 3))
    tip = np.array([0.3, 0.006, 0.006])
    beyond = tip + np.array([[0.02, 0.0, 0.0], [0.04, 0.002, 0.0], [0.058, 0.0, 0.002]])
    beside = tip + np.array([[0.02, 0.024, 0.0]])  # 50 degrees off the tip's direction
    far = tip + np.array([[0.09, 0.0, 0.0]])  # beyond tip_reach_m
    pts = np.concatenate([body, beyond, beside, far])
    lab = dbscan_labels(pts, P.dbscan_eps_m, P.dbscan_min_points)
    assert (lab[400:] == -1).all() and (lab[:400] >= 0).all()
    chain = np.linspace([0.0, 0.006, 0.006], tip, 7)  # the previous object's keypoints, its tip last
    tips = free_tips(chain, np.stack([np.arange(6), np.arange(1, 7)], axis=1), np.array([0, -1]))
    np.testing.assert_allclose(tips, [[*tip, 1.0, 0.0, 0.0]], atol=1e-12)  # keypoint 0 is held: one tip
    assert len(select_clusters_near(pts, lab, chain, P, flat=False)) == 400
    kept = select_clusters_near(pts, lab, chain, P, flat=False, tips=tips)
    assert len(kept) == 403
    np.testing.assert_array_equal(kept[-3:], beyond)
    assert len(select_clusters_near(pts, lab, chain, P, tips=tips)) == 400  # a cloth's sheet: no tips
    # a gap wider than tip_step_m ends the chain
    gap = np.concatenate([beyond[:1], beyond[2:]])
    assert tip_continuations(gap, tips, P.tip_reach_m, P.tip_step_m, P.tip_cone_cos).tolist() == [True, False]


def test_a_surface_continuing_the_object_behind_the_references_is_object_revealed_background_is_not() -> None:
    """The references held a hand at 1 m over the right of the image; the cloth now hangs there at 1.22-1.25 m,
    behind that background, continuing the part seen in front of the 2 m background on the left: that part is
    object however far the keypoints lag. The far wall revealed below, behind the same background but apart
    from the cloth, and an arm pixel are not."""
    h, w = 60, 80
    K = np.array([[80.0, 0.0, 40.0], [0.0, 80.0, 30.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    background = np.full((h, w), 2.0, np.float32)
    background[10:58, 40:60] = 1.0  # the hand in the references
    depth = np.full((h, w), 2.0, np.float32)
    cols = np.arange(10, 60)
    depth[10:50, 10:60] = (1.2 + 0.001 * (cols - 10))[None, :]  # the cloth: seen on the left, behind on the right
    seeds = np.zeros((h, w), bool)
    seeds[10:50, 10:26] = True  # the last frame's object pixels
    arm = np.zeros((h, w), bool)
    arm[20, 50] = True
    thr = change_threshold(background, P)
    out = behind_continuing(depth, background, P, seeds, K, T, arm, None, thr)
    expect = np.zeros((h, w), bool)
    expect[10:50, 40:60] = True
    expect[20, 50] = False
    np.testing.assert_array_equal(out, expect)  # rows 52-57 there show the wall at 2 m: revealed, not object
    assert not behind_continuing(depth, background, P, np.zeros((h, w), bool), K, T, arm, None, thr).any()
