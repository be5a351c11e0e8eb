"""Baseline trackers (CPD, nearest neighbour) and ``trackdeform eval ablations|baselines|init-consistency``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from tests.conftest import REPO, free_port
from tracking.baselines import BaselineTracker, cpd_nonrigid, nearest_neighbour
from tracking.params import TrackingParams


def _curve(t: np.ndarray, bend: float, shift: np.ndarray) -> np.ndarray:
    """Points (len(t), 3) m on a planar arc: x along t, z = bend * x^2, plus a shift."""
    x = 0.4 * (t - 0.5)
    return np.stack([x, np.zeros_like(x), bend * x**2], axis=1) + shift


def test_cpd_follows_a_bent_and_moved_curve() -> None:
    rng = np.random.default_rng(0)
    Y = _curve(np.linspace(0, 1, 15), 0.0, np.zeros(3))
    X = _curve(rng.uniform(0, 1, 800), 1.5, np.array([0.03, 0.01, 0.02])) + rng.normal(0, 0.001, (800, 3))
    T = cpd_nonrigid(Y, X, beta_m=0.05, lam=2.0, iterations=60)
    d_before = cKDTree(X).query(Y)[0].mean()
    d_after = cKDTree(X).query(T)[0].mean()
    assert d_after < 0.004 < d_before
    # coherent: neighbours stay ordered along the curve (no collapse onto one cluster)
    assert np.all(np.diff(T[:, 0]) > 0)
    spacing = np.linalg.norm(np.diff(T, axis=0), axis=1)
    assert spacing.min() > 0.3 * spacing.mean()


def test_cpd_leaves_points_that_already_fit() -> None:
    """Centroids on the points themselves stay (a centroid is pulled to the mean of the points it owns:
    against a dense cloud the end ones move half a spacing inwards, which is CPD, not a bug)."""
    Y = _curve(np.linspace(0, 1, 10), 0.5, np.zeros(3))
    np.testing.assert_allclose(cpd_nonrigid(Y, np.repeat(Y, 20, axis=0)), Y, atol=1e-4)
    np.testing.assert_array_equal(cpd_nonrigid(Y, np.zeros((0, 3))), Y)


def test_nearest_neighbour_is_the_brute_force_nearest_point() -> None:
    rng = np.random.default_rng(1)
    Y, X = rng.normal(size=(7, 3)), rng.normal(size=(300, 3))
    expect = X[np.linalg.norm(Y[:, None] - X[None], axis=2).argmin(axis=1)]
    np.testing.assert_array_equal(nearest_neighbour(Y, X), expect)


def test_baseline_tracker_keeps_the_initialisation_and_moves_with_the_cloud() -> None:
    from tracking.init import Topology

    P = TrackingParams()
    tr = BaselineTracker(P, np.eye(3), np.eye(4), "nn")
    X0 = _curve(np.linspace(0, 1, 8), 0.0, np.zeros(3))
    edges = np.stack([np.arange(7), np.arange(1, 8)], axis=1)
    rest = np.linalg.norm(np.diff(X0, axis=0), axis=1)
    tr.topology = Topology(kind="1d", edges=edges, rest=rest, anchor_idx=np.array([0, 7]),
                           anchor_kind=np.array([0, 0]), chains=[np.arange(8)])
    tr.keypoints = X0
    cloud = _curve(np.linspace(0, 1, 400), 0.0, np.array([0.0, 0.002, 0.0]))
    res = tr.step(cloud)
    assert res.keypoints.shape == X0.shape and res.chamfer_mm < 1e-6
    np.testing.assert_allclose(res.keypoints[:, 1], 0.002)
    with pytest.raises(ValueError, match="unknown baseline"):
        BaselineTracker(P, np.eye(3), np.eye(4), "icp")


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 20 s simulated-time rope demo: two runs of rope_swing (two captures of the same scene)."""
    out = tmp_path_factory.mktemp("eval") / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "demo", "--sim-time", "--seconds", "20", "--out", str(out),
         "--port", str(free_port()), "--no-tracking"], capture_output=True, text=True, timeout=600, cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def _eval(*args: str) -> dict:
    proc = subprocess.run([sys.executable, "-m", "orchestrator.cli", "eval", *args, "--json"],
                          capture_output=True, text=True, timeout=900, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


@pytest.mark.slow
def test_eval_ablations_and_baselines_on_a_short_session(session: Path) -> None:
    abl = _eval("ablations", str(session), "--max-frames", "90")  # ~100 tracked frames: the rope's 2 runs
    assert len(abl["captures"]) == 2
    rows = {r["method"]: r for r in abl["rows"]}
    assert list(rows) == ["full", "w/o anchors", "w/o edge projection", "w/o cloud projection"]
    full = rows["full"]
    assert full["object"] == "dlo" and full["tracked_frames"] > 80 and full["Abs"] < 3.0 and full["GT"] < 5.0
    assert rows["w/o anchors"]["Abs"] == pytest.approx(full["Abs"])  # held at both ends: the paper's DLO row
    assert rows["w/o edge projection"]["Abs"] > full["Abs"]  # the edge-length term keeps the spacing
    assert rows["w/o cloud projection"]["CD"] > full["CD"]  # without it the keypoints leave the cloud
    base = _eval("baselines", str(session), "--max-frames", "90")
    rows = {r["method"]: r for r in base["rows"]}
    assert list(rows) == ["TrackDeform3D", "CPD", "nearest neighbour"]
    assert rows["TrackDeform3D"]["Abs"] == pytest.approx(full["Abs"])  # the same method, the same frames
    assert rows["CPD"]["Abs"] > rows["TrackDeform3D"]["Abs"]


@pytest.mark.slow
def test_eval_init_consistency_over_the_runs_of_a_session(session: Path) -> None:
    r = _eval("init-consistency", str(session), "--max-frames", "120")
    assert r["captures"] == 2 and r["object"] == "dlo" and len(r["per_keypoint_std_mm"]) == 20
    assert 0.0 < r["spread_std_mm"] < 10.0 and r["spread_maxdev_mm"] >= r["spread_std_mm"] / np.sqrt(2) - 1e-9
    assert r["F<10"] == 100.0


def test_eval_names_a_missing_input(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "orchestrator.cli", "eval", "ablations", str(tmp_path / "nope")],
                          capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 2 and "nope" in proc.stderr
