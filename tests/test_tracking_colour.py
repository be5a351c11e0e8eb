"""Colour as depth's second opinion on points lying low (tracking.colour, select_clusters_near's colour)."""

import numpy as np

from tracking.colour import BACKGROUND, OBJECT, UNKNOWN, ColourModel, chroma, classify, measure_object
from tracking.params import TrackingParams

P = TrackingParams()
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
T = np.eye(4)  # camera at the origin looking along +z: (x, y, 1 m) is seen at pixel (320 + 500 x, 240 + 500 y)
WOOD, BLUE = np.array([168, 132, 92], np.uint8), np.array([51, 128, 230], np.uint8)


def _scene() -> tuple[np.ndarray, np.ndarray]:
    """A wooden table (reference) and the frame where a blue rope lies along the row y = 0 (rows 238-242), its
    right half in the shadow of an arm (every channel at 40 %)."""
    ref = np.tile(WOOD, (480, 640, 1))
    now = ref.copy()
    now[238:243, 100:540] = BLUE
    now[:, 320:] = (now[:, 320:] * 0.4).astype(np.uint8)
    return ref, now


def test_chroma_leaves_a_shadow_out() -> None:
    dark = (WOOD * 0.4).astype(np.uint8)
    assert np.abs(chroma(dark) - chroma(WOOD)).max() < 0.01
    assert np.linalg.norm(chroma(BLUE) - chroma(WOOD)) > 0.2


def test_low_points_are_told_by_colour_in_light_and_shadow() -> None:
    ref, now = _scene()
    rope = np.stack([np.linspace(-0.4, 0.4, 9), np.zeros(9), np.ones(9)], axis=1)  # on the rope, both halves
    model = measure_object(now, ref, rope, K, T, P.colour_min_separation)
    assert model is not None and np.linalg.norm(model.object - chroma(BLUE)) < 0.005  # lit or in shadow
    table = rope + [0.0, 0.05, 0.0]  # 2.5 cm beside it: the table, lit and shadowed
    edge = rope[:2] + [0.0, 0.008, 0.0]  # 4 mm off its edge (a stereo edge a few pixels off the colour's)
    got = classify(np.concatenate([rope, table, edge]), now, model, K, T, P.colour_radius_m)
    assert got.tolist() == [OBJECT] * 9 + [BACKGROUND] * 9 + [OBJECT] * 2
    # where the reference held the object's colour itself (or a table of its colour) colour cannot decide
    same = ColourModel(chroma(now), model.object, model.separation)
    assert (classify(rope, now, same, K, T, P.colour_radius_m) == UNKNOWN).all()
    # out of the image: unknown
    assert classify(np.array([[5.0, 0.0, 1.0]]), now, model, K, T, P.colour_radius_m).tolist() == [UNKNOWN]


def test_the_tables_noise_beside_a_lying_rope_stays_out_by_colour() -> None:
    # a rope lies on the table (its sparse points 5-9 mm up), the table's noise beside it reaches as high: depth
    # keeps both (above attach_min_height_m); colour keeps the rope's only
    from tracking.segmentation import dbscan_labels, select_clusters_near

    rng = np.random.default_rng(2)
    table = (np.array([0.0, 0.0, 1.0]), 0.0)
    x = np.arange(0.0, 0.3, 0.03)
    rope = np.stack([x, np.zeros_like(x), rng.uniform(0.005, 0.009, len(x))], axis=1)  # sparse: DBSCAN noise
    noise = np.stack([x + 0.015, np.full_like(x, 0.012), rng.uniform(0.005, 0.009, len(x))], axis=1)
    low = rope[:3] * [1.0, 1.0, 0.0] + [0.01, 0.0, 0.002]  # 2 mm up: out, whatever its colour
    pts = np.concatenate([rope, noise, low])
    lab = dbscan_labels(pts, 0.005, P.dbscan_min_points)
    assert (lab == -1).all()
    before = rope + [0.0, -0.005, 0.0]  # where the rope lay a frame ago
    depth_only = select_clusters_near(pts, lab, before, P, table, flat=False)
    np.testing.assert_array_equal(depth_only, np.concatenate([rope, noise]))

    def told(q: np.ndarray) -> np.ndarray:  # the rope's pixels are blue, the noise's the table's
        return np.where(np.abs(q[:, 1]) < 0.006, OBJECT, BACKGROUND).astype(np.int8)

    np.testing.assert_array_equal(select_clusters_near(pts, lab, before, P, table, flat=False, colour=told), rope)
    # colour that cannot decide leaves depth's rule, and a cloth (flat) keeps depth's rule
    unknown = select_clusters_near(pts, lab, before, P, table, flat=False,
                                   colour=lambda q: np.full(len(q), UNKNOWN, np.int8))
    np.testing.assert_array_equal(unknown, depth_only)
    np.testing.assert_array_equal(select_clusters_near(pts, lab, before, P, table, colour=told),
                                  select_clusters_near(pts, lab, before, P, table))
