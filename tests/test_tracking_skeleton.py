"""Image-space skeleton graph: pixel graph, leaves and junctions, spur pruning, branches, components."""

from __future__ import annotations

import cv2
import numpy as np

from tracking.skeleton import JUNCTION, LEAF, pixel_graph, skeleton_graph


def _draw(shape: tuple[int, int], segments: list[tuple[tuple[int, int], tuple[int, int]]], width: int) -> np.ndarray:
    """Mask (H, W) bool of thick line segments given as ((x0, y0), (x1, y1)) pixels."""
    img = np.zeros(shape, np.uint8)
    for a, b in segments:
        cv2.line(img, a, b, 1, width)
    return img.astype(bool)


def test_pixel_graph_is_every_8_neighbour_pair_once_in_csr_order():
    rng = np.random.default_rng(0)
    skel = rng.random((23, 17)) < 0.3
    rc, edges, w = pixel_graph(skel)
    assert np.array_equal(rc, np.argwhere(skel))
    d = np.abs(rc[:, None, :] - rc[None, :, :]).max(axis=2)
    i, j = np.nonzero(np.triu(d == 1))
    assert np.array_equal(edges, np.stack([i, j], axis=1))  # row-major: sorted by i, then j
    assert np.allclose(w, np.linalg.norm(rc[edges[:, 0]] - rc[edges[:, 1]], axis=1))


def test_pixel_graph_of_an_empty_image():
    rc, edges, w = pixel_graph(np.zeros((5, 4), bool))
    assert rc.shape == (0, 2) and edges.shape == (0, 2) and w.shape == (0,)


def test_y_shape_gives_three_leaves_one_junction_and_connected_branches():
    mask = _draw((120, 140), [((70, 60), (10, 10)), ((70, 60), (130, 10)), ((70, 60), (70, 115))], 5)
    g = skeleton_graph(mask, spur_px=8.0, merge_px=4.0, min_component_px=8.0)
    assert sorted(g.node_kind.tolist()) == [LEAF, LEAF, LEAF, JUNCTION]
    assert len(g.branches) == 3
    junction = int(np.flatnonzero(g.node_kind == JUNCTION)[0])
    for a, b, pix in g.branches:
        assert junction in (a, b)
        assert np.array_equal(pix[0], g.node_rc[a]) and np.array_equal(pix[-1], g.node_rc[b])
        assert np.abs(np.diff(pix, axis=0)).max() <= 1  # consecutive 8-neighbours
    assert np.array_equal(g.component, np.zeros(4, np.int64))


def test_short_spur_is_pruned_and_small_components_dropped():
    line = [((10, 40), (150, 40))]
    spur = [((80, 40), (80, 30))]  # ~10 px off the line
    dot = [((5, 5), (6, 5))]
    g = skeleton_graph(_draw((80, 160), line + spur + dot, 5), spur_px=20.0, merge_px=4.0, min_component_px=20.0)
    assert g.node_kind.tolist() == [LEAF, LEAF]
    assert len(g.branches) == 1 and len(g.branches[0][2]) > 100


def test_components_are_ranked_by_node_count():
    line = [((10, 10), (150, 10))]  # first in raster order, two nodes
    y = [((80, 80), (20, 50)), ((80, 80), (140, 50)), ((80, 80), (80, 115))]  # four nodes
    g = skeleton_graph(_draw((120, 160), line + y, 5), spur_px=8.0, merge_px=4.0, min_component_px=8.0)
    assert np.bincount(g.component).tolist() == [4, 2]
    assert set(g.node_kind[g.component == 0].tolist()) == {LEAF, JUNCTION}


def test_mask_without_skeleton_gives_an_empty_graph():
    g = skeleton_graph(np.zeros((30, 30), bool), spur_px=8.0, merge_px=4.0, min_component_px=8.0)
    assert g.node_rc.shape == (0, 2) and g.branches == [] and len(g.component) == 0


def test_every_component_too_short_gives_an_empty_graph():
    g = skeleton_graph(_draw((30, 30), [((5, 5), (12, 5))], 3), spur_px=8.0, merge_px=4.0, min_component_px=50.0)
    assert g.node_rc.shape == (0, 2) and g.branches == []
