"""Classification, anchors and initial topology on synthetic rope, branched rope and cloth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from tdcommon.meshes import sheet_mesh, tube_mesh
from tracking import synthetic as S
from tracking.anchors import CORNER, JUNCTION, LEAF, detect_anchors_1d
from tracking.classify import classify_object
from tracking.geometry import farthest_point_sampling
from tracking.init import initialise
from tracking.metrics import edge_rmse_mm
from tracking.params import TrackingParams
from tracking.segmentation import background_from_depths, segment_against_background

W, H = 640, 480
P = TrackingParams()


@pytest.fixture(scope="module")
def scene():
    K, T = S.default_camera(W, H)
    rng = np.random.default_rng(0)
    bg = background_from_depths(np.stack([S.render_depth([S.table_mesh()], K, T, (H, W), rng=rng) for _ in range(3)]))

    def segment(meshes):
        d = S.render_depth([S.table_mesh(), *meshes], K, T, (H, W), rng=rng)
        return segment_against_background(d, bg, K, T, P).points

    return K, T, segment


@pytest.fixture(scope="module")
def rope(scene):
    K, T, segment = scene
    c = S.rope_centreline(0.3)
    return c, segment([tube_mesh(c, 0.006)])


@pytest.fixture(scope="module")
def yrope(scene):
    K, T, segment = scene
    br = S.y_rope_branches()
    return br, segment([tube_mesh(b, 0.006) for b in br])


@pytest.fixture(scope="module")
def cloth(scene):
    K, T, segment = scene
    cs = S.cloth_surface()
    return cs, segment([sheet_mesh(cs)])


def test_classification(rope, yrope, cloth):
    assert classify_object(rope[1], P).kind == "1d"
    assert classify_object(yrope[1], P).kind == "1d"
    c = classify_object(cloth[1], P)
    assert c.kind == "2d" and c.plane_ratio < P.plane_ratio_max


def test_rope_anchors_at_the_ends(scene, rope):
    K, T, _ = scene
    c, pts = rope
    pos, kinds = detect_anchors_1d(pts, K, T, P)
    assert list(kinds) == [LEAF, LEAF]
    d, _ = cKDTree(pos).query(c[[0, -1]])
    assert d.max() < 0.012  # skin tip vs centreline end: within ~2 radii


def test_rope_initialisation_chain(scene, rope):
    K, T, _ = scene
    c, pts = rope
    ini = initialise(pts, K, T, P)
    tp = ini.topology
    N = P.n_keypoints_1d
    assert tp.kind == "1d" and ini.keypoints.shape == (N, 3)
    assert np.array_equal(tp.edges, np.stack([np.arange(N - 1), np.arange(1, N)], axis=1))
    assert sorted(tp.anchor_idx.tolist()) == [0, N - 1]
    assert abs(tp.rest.sum() - 0.6) < 0.02  # measured length of the 0.6 m rope
    assert edge_rmse_mm(ini.keypoints, tp.edges, tp.rest) < 4.0
    s = np.linspace(0, 0.6, len(c))
    arc = s[cKDTree(c).query(ini.keypoints)[1]]
    assert np.all(np.abs(np.diff(arc)) > 0.01) and (np.all(np.diff(arc) > 0) or np.all(np.diff(arc) < 0))


def test_branched_rope_junction_and_tree(scene, yrope):
    K, T, _ = scene
    br, pts = yrope
    ini = initialise(pts, K, T, P)
    tp = ini.topology
    kinds = tp.anchor_kind
    assert (kinds == LEAF).sum() == 3 and (kinds == JUNCTION).sum() == 1
    junction = ini.keypoints[tp.anchor_idx[kinds == JUNCTION][0]]
    assert np.linalg.norm(junction[:2] - br[0][0, :2]) < 0.02
    leaves = ini.keypoints[tp.anchor_idx[kinds == LEAF]]
    assert cKDTree(leaves).query(np.array([b[-1] for b in br]))[0].max() < 0.015
    deg = np.bincount(tp.edges.ravel())
    assert deg.max() == 3 and len(tp.edges) == len(ini.keypoints) - 1  # a tree
    assert len(tp.chains) == 3
    lengths = [len(ch) - 1 for ch in tp.chains]  # edges per branch roughly proportional to 0.25 : 0.22 : 0.22
    assert max(lengths) - min(lengths) <= 2


def test_cloth_grid(scene, cloth):
    K, T, _ = scene
    cs, pts = cloth
    ini = initialise(pts, K, T, P)
    tp = ini.topology
    R, C = P.grid_rows, P.grid_cols
    assert tp.kind == "2d" and tp.grid_shape == (R, C) and len(tp.edges) == R * (C - 1) + C * (R - 1)
    assert len(tp.anchor_idx) == 2 * R + 2 * C - 4 and (tp.anchor_kind == CORNER).sum() == 4
    corners = ini.keypoints.reshape(R, C, 3)[[0, 0, -1, -1], [0, -1, 0, -1]]
    true = cs[[0, 0, -1, -1], [0, -1, 0, -1]]
    assert cKDTree(corners).query(true)[0].max() < 0.015
    assert abs(tp.rest.mean() - 0.3 / (C - 1)) < 0.01
    assert cKDTree(cs.reshape(-1, 3)).query(ini.keypoints)[0].max() < 0.01


def test_farthest_point_sampling():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 1, (2000, 3))
    idx = farthest_point_sampling(pts, 10, seeds=np.zeros((1, 3)))
    assert len(set(idx.tolist())) == 10
    assert np.linalg.norm(pts[idx[0]]) > 1.5  # first pick is far from the seed


def _rounded_rectangle(w: float, h: float, r: float, n: int = 800) -> np.ndarray:
    """A closed contour (n, 2) px of a w x h rectangle whose corners are rounded with radius r, clockwise on screen."""
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    c, s = np.cos(t), np.sin(t)
    # superellipse-free construction: clamp a circle of radius r swept around the inner rectangle
    x = np.clip(np.abs(c) * 1e3, 0, (w / 2 - r)) * np.sign(c) + r * c
    y = np.clip(np.abs(s) * 1e3, 0, (h / 2 - r)) * np.sign(s) + r * s
    return np.stack([x + w / 2, y + h / 2], axis=1)


def test_refine_corners_meets_the_fitted_sides_on_a_rounded_corner() -> None:
    from tracking.anchors import refine_corners

    c = _rounded_rectangle(200.0, 120.0, 20.0)
    box = np.array([[0.0, 0.0], [200.0, 0.0], [200.0, 120.0], [0.0, 120.0]])
    ci = np.sort([int(np.argmin(np.linalg.norm(c - b, axis=1))) for b in box])
    # start each corner off-centre along the rounded arc: the refinement must not depend on it
    shifted = ci + np.array([6, -6, 6, -6])
    out = refine_corners(c, shifted, np.array([False, False, False, True]))
    # the free corners land where the rounded arc meets the bisector: r (1 - 1/sqrt 2) in from the box corner
    inset = 20.0 * (1 - 1 / np.sqrt(2))
    pts = c[out]
    ref = box[[int(np.argmin(np.linalg.norm(box - p, axis=1))) for p in pts]]
    d = np.abs(np.abs(pts - ref) - inset)
    assert (d[:3] < 1.0).all(), pts
    assert out[3] == shifted[3]  # a fixed (held) corner stays


def test_refine_corners_is_steady_under_contour_jitter() -> None:
    """A rounded corner's pick must not slide along the arc with a pixel of contour jitter (the
    nearest contour point to the sides' meeting point did: 1-1.5 px here; the bisector crossing 0.4)."""
    from tracking.anchors import refine_corners

    c0 = _rounded_rectangle(300.0, 200.0, 40.0, n=1200)
    box = np.array([[0.0, 0.0], [300.0, 0.0], [300.0, 200.0], [0.0, 200.0]])
    picks = []
    for seed in range(20):
        c = np.rint(c0 + np.random.default_rng(seed).normal(0.0, 0.5, c0.shape))  # jitter, whole pixels
        ci = np.sort([int(np.argmin(np.linalg.norm(c - b, axis=1))) for b in box])
        picks.append(c0[refine_corners(c, ci, np.zeros(4, bool))])
    P = np.stack(picks)
    spread = np.sqrt((np.linalg.norm(P - P.mean(axis=0), axis=2) ** 2).mean(axis=0))
    assert (spread < 0.7).all(), spread


def test_refine_corners_finds_a_sagging_sides_corners() -> None:
    """A hanging cloth's bottom side sags between its corners: lines fitted to the middles of its sides meet away
    from the corners; the contour turns at them."""
    from tracking.anchors import refine_corners

    t = np.linspace(0.0, 1.0, 400, endpoint=False)
    top = np.stack([200.0 * t, np.zeros_like(t)], axis=1)
    right = np.stack([np.full_like(t, 200.0), 150.0 * t], axis=1)
    bottom = np.stack([200.0 * (1 - t), 150.0 + 60.0 * np.sin(np.pi * t)], axis=1)  # sags 60 px in the middle
    left = np.stack([np.zeros_like(t), 150.0 * (1 - t)], axis=1)
    c = np.rint(np.concatenate([top, right, bottom, left]))  # clockwise on screen, whole pixels
    true = np.array([0, 400, 800, 1200])
    start = true + np.array([0, 25, -30, 30])  # a rectangle's corners land off them along the contour
    out = refine_corners(c, start, np.array([True, False, False, False]))
    assert out[0] == start[0]  # held
    assert np.linalg.norm(c[out[1:]] - c[true[1:]], axis=1).max() < 3.0, c[out]


def test_widest_corners_finds_the_free_corners_far_from_the_rectangles() -> None:
    """Two held top corners; the free ones start a third of the way along the sides (where an arm's notch in the
    top edge and a slanted side put the minimum-area rectangle's corners) and end at the true corners, which span
    the largest quadrilateral with the held ones; refine_corners alone searches only near its start."""
    from tracking.anchors import refine_corners, widest_corners

    t = np.linspace(0.0, 1.0, 300, endpoint=False)
    notch = 80.0 * np.clip(1.0 - np.abs(t - 0.3) / 0.15, 0.0, 1.0)  # an arm hides part of the top edge
    top = np.stack([400.0 * t, 100.0 * t + notch], axis=1)
    right = np.stack([400.0 - 30.0 * t, 100.0 + 300.0 * t], axis=1)
    bottom = np.stack([370.0 - 300.0 * t, 400.0 - 100.0 * t + 40.0 * np.sin(np.pi * t)], axis=1)
    left = np.stack([70.0 * (1 - t), 300.0 * (1 - t)], axis=1)
    c = np.rint(np.concatenate([top, right, bottom, left]))  # clockwise on screen, whole pixels
    true = np.array([0, 300, 600, 900])
    start = np.array([0, 300, 700, 1000])  # free corners a third of the way along the bottom and the left side
    fixed = np.array([True, True, False, False])
    assert np.linalg.norm(c[refine_corners(c, start, fixed)[2:]] - c[true[2:]], axis=1).max() > 20.0
    out = widest_corners(c, start, fixed)
    assert (out[:2] == start[:2]).all()  # held
    assert np.linalg.norm(c[out[2:]] - c[true[2:]], axis=1).max() < 8.0, c[out]
    assert (widest_corners(c, start, np.array([True, False, False, False])) == start).all()  # one held: unchanged


def test_lift_pixels_is_the_median_of_the_near_cloud_points() -> None:
    """The compiled lift against a KD-tree query and numpy's nanmedian: up to k cloud points whose pixels lie
    closer than the radius, else the nearest one (pixels far from every cloud pixel)."""
    from scipy.spatial import cKDTree

    from tracking.anchors import lift_pixels

    rng = np.random.default_rng(1)
    uv = rng.uniform(0, 200, (3000, 2))
    cloud = rng.normal(size=(3000, 3))
    pix = np.concatenate([rng.uniform(0, 200, (300, 2)), rng.uniform(250, 300, (20, 2))])
    for k, radius in ((1, 2.0), (2, 3.0), (5, 1.5), (16, 4.0)):
        d, i = cKDTree(uv).query(pix, k=k, distance_upper_bound=radius)
        d, i = d.reshape(len(pix), k), i.reshape(len(pix), k)
        nb = np.where(np.isfinite(d)[..., None], cloud[np.minimum(i, len(cloud) - 1)], np.nan)
        none = ~np.isfinite(d[:, 0])
        nb[none, 0] = cloud[cKDTree(uv).query(pix[none])[1]]
        assert none.sum() >= 20
        np.testing.assert_array_equal(lift_pixels(pix, uv, cloud, radius, k), np.nanmedian(nb, axis=1))


def test_savgol_quadratic_matches_scipy() -> None:
    from scipy.signal import savgol_filter

    from tracking.anchors import _savgol_quadratic

    p = np.random.default_rng(3).normal(size=(90, 3)).cumsum(axis=0)
    for w in (5, 31, 89):
        np.testing.assert_allclose(_savgol_quadratic(p, w), savgol_filter(p, w, 2, axis=0, mode="interp"), atol=1e-9)


def test_savgol_weights_are_scipys_bit_for_bit() -> None:
    """The weights are solved as scipy solves them (odd and even windows), so no track changes by a bit."""
    from scipy.signal import savgol_coeffs

    from tracking.anchors import _savgol_weights

    for w in range(3, 64):
        np.testing.assert_array_equal(_savgol_weights(w)[0], savgol_coeffs(w, 2), err_msg=f"window {w}")


def test_leaf_on_axis_removes_the_skeleton_tips_lateral_offset() -> None:
    from tracking.anchors import _leaf_on_axis

    x = np.linspace(0.0, 0.06, 31)
    poly = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    poly[0, 1] = 0.004  # the skeleton's last pixel off the tube's axis
    leaf, inner = _leaf_on_axis(poly, 0.025)
    assert abs(leaf[1]) < 5e-4 and abs(leaf[0]) < 1e-3
    assert inner[0] > leaf[0]  # further in along the branch
    short = poly[:3]
    leaf2, _ = _leaf_on_axis(short, 0.025)
    np.testing.assert_array_equal(leaf2, short[0])  # too short to fit: left alone


def test_extended_leaf_is_centred_on_the_tube_not_on_a_tilted_axis() -> None:
    """A leaf pushed along an axis 5 degrees off lands on the tube's centre, not 1.7 mm aside."""
    from tracking.anchors import _extend_leaf

    rng = np.random.default_rng(7)
    x = rng.uniform(0.0, 0.1, 4000)
    a = rng.uniform(0.0, np.pi, 4000)  # the visible half of a tube of radius 7 mm along x
    cloud = np.stack([x, 0.007 * np.cos(a), 0.007 * np.sin(a)], axis=1)
    tree = cKDTree(cloud)
    leaf = np.array([0.08, 0.0, 0.0])
    tilt = np.array([np.cos(np.radians(5.0)), np.sin(np.radians(5.0)), 0.0])
    tip = _extend_leaf(leaf, leaf - 0.02 * tilt, tree, cloud, 0.03, 0.01)
    assert abs(tip[0] - 0.1) < 0.002
    assert abs(tip[1]) < 0.0005, tip
    off_axis = _extend_leaf(leaf, leaf - 0.02 * tilt, tree, cloud, 0.03, 0.0)
    assert abs(off_axis[1]) > 0.0012  # the axis alone


def test_a_branch_held_across_a_hidden_gap_gets_that_gap_as_one_edge() -> None:
    """Keypoints spread evenly along a branch, unless an end was put at a TCP across a gap the hand hides: that
    straight segment is one edge from the seen tip (its chord the rest length), the rest spread as before."""
    from tracking.init import polyline_arc, space_branch

    seen = np.stack([np.linspace(0.0, 0.3, 31), np.zeros(31), np.zeros(31)], axis=1)  # 30 cm seen, x = 0 .. 0.3
    tcp = np.array([0.3, 0.0, 0.1])  # held 10 cm above the seen tip
    poly = np.concatenate([seen, tcp[None]])
    X, rest = space_branch(poly, 4)
    assert X.shape == (4, 3) and rest.shape == (5,)
    np.testing.assert_allclose(rest, polyline_arc(poly)[-1] / 5)
    X, rest = space_branch(poly, 4, (False, True))
    np.testing.assert_allclose(X[-1], seen[-1])  # the seen tip is a keypoint
    np.testing.assert_allclose(rest, [0.075, 0.075, 0.075, 0.075, 0.1])
    np.testing.assert_allclose(X[:, 0], [0.075, 0.15, 0.225, 0.3])
    Xr, rr = space_branch(poly[::-1], 4, (True, False))  # the same branch from the other end
    np.testing.assert_allclose(Xr, X[::-1], atol=1e-12)
    np.testing.assert_allclose(rr, rest[::-1])
    np.testing.assert_allclose(space_branch(poly[:2], 3, (True, True))[1], np.full(4, 0.0025))  # no seen part


def test_a_gap_longer_than_the_spacing_to_a_held_end_is_one_edge(scene, rope) -> None:
    """A rope whose held end is 5 cm beyond its seen tip (the hand hides the rest): the gap, longer than the
    keypoint spacing (~3 cm), is one edge of its own, so no keypoint is placed in it and pulled back onto the
    seen rope (which stretched the held end's edge and squeezed the next)."""
    K, T, _ = scene
    c, pts = rope
    out = (c[0] - c[1]) / np.linalg.norm(c[0] - c[1])
    tcp = c[0] + 0.05 * out
    ini = initialise(pts, K, T, P, held=tcp[None])
    tp, X = ini.topology, ini.keypoints
    L = np.linalg.norm(X[tp.edges[:, 0]] - X[tp.edges[:, 1]], axis=1)
    assert np.abs(L - tp.rest).max() < 0.003  # m
    held = int(np.argmin(np.linalg.norm(X - tcp, axis=1)))
    assert np.linalg.norm(X[held] - tcp) < 1e-6
    e = np.flatnonzero((tp.edges == held).any(axis=1))
    assert len(e) == 1 and tp.rest[e[0]] == pytest.approx(0.05, abs=0.01)  # the chord from the seen tip
