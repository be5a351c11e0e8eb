"""benchmarks/testbed.py's ground truth written as a tracker's output (``--truth``)."""

from pathlib import Path

import numpy as np

from benchmarks.testbed import truth_keypoints


def test_truth_keypoints_cloth_grid(tmp_path: Path) -> None:
    u = np.linspace(-0.2, 0.2, 11)
    surf = np.stack([*np.meshgrid(u, u, indexing="ij"), np.ones((11, 11))], axis=-1)  # a 0.4 m square at z = 1 m
    np.savez(tmp_path / "gt.npz", object_type="cloth", surface=np.stack([surf, surf + [0.0, 0.0, 0.1]]))
    t = truth_keypoints(tmp_path / "gt.npz")
    assert t["full"].shape == (2, 36, 3) and len(t["edge_connection"]) == 60
    np.testing.assert_allclose(t["reference_lengths"], 80.0)  # mm: 0.4 m over five edges
    np.testing.assert_allclose(t["full"][1, :, 2], 1100.0)
    np.testing.assert_allclose(t["full"][0, 0], [-200.0, -200.0, 1000.0])


def test_truth_keypoints_rope_on_its_ridge_at_the_trackers_spacing(tmp_path: Path) -> None:
    x = np.linspace(-0.45, 0.45, 181)
    line = np.stack([x, np.zeros_like(x), np.full_like(x, 1.0)], axis=1)  # 0.9 m across a camera 1 m away
    np.savez(tmp_path / "gt.npz", object_type="rope", centerline=np.stack([line, line]), radius_m=0.005)
    t = truth_keypoints(tmp_path / "gt.npz")  # no tracker output: 45 mm apart
    assert t["full"].shape == (2, 21, 3) and t["edge_connection"].tolist()[:2] == [[0, 1], [1, 2]]
    mid = t["full"][0, 10]
    np.testing.assert_allclose(mid, [0.0, 0.0, 995.0], atol=1e-6)  # moved its radius towards the camera
    np.savez(tmp_path / "pred.npz", full=np.zeros((2, 31, 3)), reference_lengths=np.full(30, 30.0))
    t = truth_keypoints(tmp_path / "gt.npz", tmp_path / "pred.npz")
    assert t["full"].shape == (2, 31, 3)
    np.testing.assert_allclose(t["reference_lengths"], 30.0, rtol=0.02)


def test_missed_targets_name_the_column_and_whether_exact_keypoints_miss_them_too() -> None:
    from benchmarks.testbed import missed

    ok = {"nan_frame_fraction": 0.0, "gt_object_rmse_mm": 1.0, "anchor_err_mm": 3.0, "coverage_mm": 5.0,
          "Abs_mm": 1.0, "E<5_pct": 100.0, "CD_mm": 2.0, "F<10_pct": 100.0}
    assert missed("rope", ok, radius_mm=6.0) == [] and missed("cloth", ok, None) == []
    assert missed("rope", {**ok, "coverage_mm": 9.5}, radius_mm=6.0) == ["coverage 9.50 (<= 9)"]
    assert missed("cloth", {**ok, "coverage_mm": 9.5}, None) == ["coverage 9.50 (<= 6)"]
    bad = {**ok, "CD_mm": 8.0, "F<10_pct": 60.0, "truth_CD_mm": 7.0, "truth_F<10_pct": 99.0, "nan_frame_fraction": 0.1}
    assert missed("bdlo", bad, radius_mm=5.0) == ["missing 10.00 (<= 0)", "CD 8.00 (<= 5) (truth too)",
                                                  "F<10 60.00 (>= 95)"]


def test_a_row_without_figures_misses_every_target_and_says_why(tmp_path: Path) -> None:
    from benchmarks.testbed import miss_lines

    ok = {"nan_frame_fraction": 0.0, "gt_object_rmse_mm": 1.0, "anchor_err_mm": 3.0, "coverage_mm": 5.0,
          "Abs_mm": 1.0, "E<5_pct": 100.0, "CD_mm": 2.0, "F<10_pct": 100.0}
    jobs = [{"name": "a", "obj": "cloth"}, {"name": "b", "obj": "cloth"}, {"name": "c", "obj": "rope"},
            {"name": "d", "obj": "cloth"}]
    rows = {"a": ok, "b": {"error": "never initialised"}, "d": {**ok, "Abs_mm": 4.0}}
    assert miss_lines(jobs, rows, tmp_path) == ["  b: never initialised", "  c: no result", "  d: Abs 4.00 (<= 3)"]
