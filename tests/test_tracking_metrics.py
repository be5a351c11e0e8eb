"""Paper metrics on hand-computed examples."""

from __future__ import annotations

import numpy as np
import pytest

from tracking.metrics import (
    anchor_error_mm,
    chamfer_mm,
    distance_to_polyline,
    edge_rmse_mm,
    percent_below,
    sequence_summary,
    surface_error_mm,
    surface_errors_mm,
)


def test_edge_rmse():
    X = np.array([[0.0, 0, 0], [0.103, 0, 0], [0.103, 0.096, 0]])
    edges = np.array([[0, 1], [1, 2]])
    rest = np.array([0.1, 0.1])
    # errors +3 mm and -4 mm -> sqrt((9 + 16) / 2)
    assert np.isclose(edge_rmse_mm(X, edges, rest), np.sqrt(12.5))


def test_chamfer_and_percentages():
    cloud = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    X = np.array([[0.0, 0.002, 0], [1.0, 0, 0.006]])
    assert np.isclose(chamfer_mm(X, cloud), 4.0)
    assert percent_below(np.array([1.0, 4.9, 5.0, 7.0]), 5.0) == 50.0
    s = sequence_summary(
        np.array([3.0, 6.0]),
        np.array(
            [
                9.0,
                11.0,
            ]
        ),
    )
    assert s == {"Abs": 4.5, "E<5": 50.0, "CD": 10.0, "F<10": 50.0}


def test_ground_truth_errors():
    line = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    X = np.array([[0.5, 0.003, 0.0], [0.2, 0.0, 0.010], [1.5, 0.0, 0.0]])
    assert np.allclose(distance_to_polyline(X, line), [0.003, 0.010, 0.5])
    # radius 5 mm: on the skin counts as exact, 10 mm off the centreline is 5 mm
    e = surface_error_mm(X[:2], line, 0.005, polyline=True)
    assert np.isclose(e, np.sqrt((0.0 + 25.0) / 2))
    samples = np.linspace([0, 0, 0], [1, 0, 0], 1001)
    assert np.isclose(surface_error_mm(X[:2], samples, 0.005), e, atol=1e-6)
    true = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    pred = np.array([[1.0, 0.004, 0], [0.0, 0, 0.002]])  # swapped order: Hungarian matches
    assert np.isclose(anchor_error_mm(pred, true), 3.0)



def test_branched_gt_is_measured_to_each_chain_not_the_join():
    """A branched rope's samples are its trunk then its branch: a keypoint on the false segment from the
    trunk's end to the branch's tip is 75 mm off the object, not on it."""
    from tracking.metrics import split_chains

    trunk = np.stack([np.linspace(0.0, 0.3, 151), np.zeros(151), np.zeros(151)], axis=1)
    branch = np.stack([np.full(101, 0.15), np.linspace(0.2, 0.0, 101), np.zeros(101)], axis=1)  # tip to junction
    samples = np.concatenate([trunk, branch])
    assert [len(c) for c in split_chains(samples)] == [151, 101]
    on_false_segment = np.array([[0.225, 0.1, 0.0]])
    assert surface_error_mm(on_false_segment, samples, 0.0, polyline=True) == pytest.approx(75.0, abs=1e-6)
    on_branch = np.array([[0.15, 0.1, 0.004]])
    assert surface_error_mm(on_branch, samples, 0.003, polyline=True) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("polyline", [True, False])
def test_batched_gt_errors_equal_the_per_frame_metric(polyline: bool) -> None:
    """surface_errors_mm over F frames (chunked, jumps masked) gives surface_error_mm of each frame."""
    rng = np.random.default_rng(3)
    F, N, M = 45, 12, 90
    s = np.linspace(0.0, 1.0, M)
    samples = np.stack([np.c_[s, 0.2 * np.sin(3 * s + 0.1 * f), 0.05 * s] for f in range(F)])
    samples[:, 60:] += [0.0, 0.4, 0.1]  # a second chain (a branch): no segment may join the two
    X = samples[:, ::7][:, :N] + rng.normal(0.0, 0.01, (F, N, 3))
    X[:, 0] = samples[:, 59] + 0.5 * (samples[:, 60] - samples[:, 59])  # on the false join segment
    want = [surface_error_mm(X[i], samples[i], 0.003, polyline=polyline) for i in range(F)]
    got = surface_errors_mm(X, samples, 0.003, polyline=polyline, chunk=16)
    assert got.shape == (F,)
    assert np.allclose(got, want, atol=1e-9)
