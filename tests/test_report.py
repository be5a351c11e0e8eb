"""``trackdeform report``: tables from recorded keypoints, thumbnails, and the page of a whole session in Chromium."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from orchestrator.recorder import EpisodeWriter
from orchestrator.report import ReportError, build_report, draw_thumbnail, project
from tdcommon.types import CameraIntrinsics, RGBDFrame
from tests.conftest import REPO, copy_session

W, H = 160, 120
T_CAM = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1.0], [0, 0, 0, 1]])  # 1 m above, looking down


def _frame(n: int, intr: CameraIntrinsics) -> RGBDFrame:
    color = np.full((H, W, 3), 40, np.uint8)
    depth = np.full((H, W), 1000, np.uint16)
    return RGBDFrame(color, depth, 0.001, intr, 10.0 + n / 30.0, 10.0 + n / 30.0 + 0.002, n)


def _kp_message(n: int, X: np.ndarray, abs_mm: float, cd_mm: float, status: str = "tracking") -> dict:
    return {"schema": "trackdeform.Keypoints/1", "frame_number": n, "stamp": 10.0 + n / 30.0,
            "keypoints": X.tolist(), "edges": [[i, i + 1] for i in range(len(X) - 1)],
            "grasp_indices": {"left": 0, "right": -1}, "object": "rope", "category": "dlo", "status": status,
            "abs_mm": abs_mm, "cd_mm": cd_mm}


def _session(folder: Path) -> tuple[np.ndarray, list[float], list[float], CameraIntrinsics]:
    """Two episodes of one run with recorded keypoints (a straight line of 5 on the table); journal + summary."""
    intr = CameraIntrinsics.from_fov(W, H, 69.0)
    X = np.stack([np.linspace(-0.1, 0.1, 5), np.zeros(5), np.zeros(5)], axis=1)
    abs_mm, cd_mm = [], []
    meta = {"object": "rope", "category": "dlo", "program": "rope_swing", "speed": "fast", "repeat": 0,
            "run_index": 0, "attempt": 1, "plan_pass": 0, "session_started": "2025-01-01T00:00:00Z",
            "calibration": {"K": intr.K.tolist(), "width": W, "height": H, "T_world_cam": T_CAM.tolist()}}
    for e in range(2):
        w = EpisodeWriter(folder / f"episode_{e:06d}.mcap", "cam0")
        for n in range(e * 10, e * 10 + 10):
            w.write_frame(_frame(n, intr), T_CAM)
            status = "init" if n == 0 else ("lost" if n == 5 else "tracking")
            a, c = 1.0 + 0.5 * n, 2.0 + 0.9 * n  # CD crosses 10 mm at frame 9
            w.write_keypoints(_kp_message(n, X, a, c, status), 10.0 + n / 30.0)
            if status != "lost":
                abs_mm.append(a)
                cd_mm.append(c)
        w.close({**meta, "episode_index": e, "complete": True, "fault": e == 1})
    run = {"pass": 0, "object": "rope", "program": "rope_swing", "speed": "fast", "repeat": 0, "attempt": 1}
    lines = [{"type": "header", "format": "trackdeform-journal/1"}, {"type": "session", "index": 0},
             {**run, "type": "live_init", "outcome": "ok", "reason": None, "seconds": 6.84, "track_id": "t1",
              "attempts": [{"outcome": "ok", "metrics": {"n_keypoints": 20, "abs_mm": 0.012, "edge_error": 0.0012,
                                                          "gripper_distance_m": {"left": 0.011, "right": 0.009}}}]},
             {**run, "type": "live_init", "object": "cloth", "outcome": "failed", "seconds": 20.5,
              "reason": "36 keypoints, expected 49", "attempts": [{"outcome": "failed"}] * 3, "track_id": None},
             {"type": "start", **run}, {**run, "type": "run", "outcome": "done", "reason": None,
                                        "episodes": ["episode_000000.mcap", "episode_000001.mcap"]},
             {**run, "type": "start", "speed": "slow"},
             {**run, "type": "run", "speed": "slow", "outcome": "skipped", "reason": "program not safe at slow"}]
    (folder / "session.journal.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    (folder / "summary.json").write_text(json.dumps({"frames_captured": 20, "frames_dropped": 3, "errors": []}))
    return X, abs_mm, cd_mm, intr


def test_report_tables_from_recorded_keypoints(tmp_path: Path) -> None:
    session = tmp_path / "s"
    session.mkdir()
    X, abs_mm, cd_mm, intr = _session(session)
    page = build_report(session, tmp_path / "r", thumbnails=3)
    html = page.read_text()
    table = html[html.index('id="quality"'):html.index("</table>", html.index('id="quality"'))]
    cells = re.findall(r"<td[^>]*>([^<]*)</td>", table.split("</tr>")[1])
    assert cells[:4] == ["rope", "fast", "1", "19"]  # the lost frame does not count
    assert cells[5] == f"{np.mean(abs_mm):.2f}" and cells[7] == f"{np.mean(cd_mm):.2f}"
    assert cells[6] == f"{100 * np.mean(np.array(abs_mm) < 5):.1f}"
    assert cells[8] == f"{100 * np.mean(np.array(cd_mm) < 10):.1f}"
    assert "program not safe at slow" in html and "skipped" in html
    table = html[html.index('id="live-init"'):html.index("</table>", html.index('id="live-init"'))]
    rows = [re.findall(r"<td[^>]*>([^<]*)</td>", r) for r in table.split("</tr>")[1:3]]
    assert rows[0] == ["rope", "rope_swing · fast · #1", "ok", "1", "6.8",
                       "20 keypoints, edge error 0.01 mm (0.001 of an edge), gripper left 11 mm / right 9 mm"]
    assert rows[1] == ["cloth", "rope_swing · fast · #1", "failed", "3", "20.5", "36 keypoints, expected 49"]
    assert "1 episode(s) flagged with a fault" in html and ">3</b>frames dropped" in html
    imgs = re.findall(r'<img src="([^"]+)"', html)
    assert len(imgs) == 1 + 1 + 3  # trajectory, per-run plot, 3 thumbnails
    assert all((page.parent / i).is_file() for i in imgs)


def test_thumbnail_draws_keypoints_where_the_camera_sees_them() -> None:
    intr = CameraIntrinsics.from_fov(W, H, 69.0)
    X = np.array([[0.0, 0.0, 0.0], [0.05, 0.02, 0.0]])
    uv, front = project(X, intr.K, T_CAM)
    assert front.all()
    np.testing.assert_allclose(uv[0], [intr.K[0, 2], intr.K[1, 2]], atol=1e-9)  # below the camera: the centre
    img = draw_thumbnail(np.zeros((H, W, 3), np.uint8), X, np.array([[0, 1]]), intr.K, T_CAM, width=W)
    for u, v in np.round(uv).astype(int):
        assert img[v, u].max() > 0
    assert img[5, 5].max() == 0


def test_report_refuses_a_folder_without_episodes(tmp_path: Path) -> None:
    with pytest.raises(ReportError, match="no episode_"):
        build_report(tmp_path, tmp_path / "r")


PROBE = """<script>
window.__errors = [];
window.addEventListener('error', function (e) {
  window.__errors.push(String(e.message || (e.target && (e.target.src || e.target.href)) || e)); }, true);
(function () { var err = console.error; console.error = function () {
  window.__errors.push(Array.prototype.join.call(arguments, ' ')); err.apply(console, arguments); }; })();
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var bad = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); })
                .map(function (i) { return i.getAttribute('src'); });
  var pre = document.createElement('pre'); pre.id = '__probe';
  pre.textContent = JSON.stringify({images: imgs.length, broken: bad, errors: window.__errors});
  document.body.appendChild(pre);
});
</script>"""


def chromium() -> str | None:
    """The headless browser binary (Debian's ``chromium``), or None."""
    return next((p for p in (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")) if p), None)


def browser_check(page: Path, tmp: Path) -> dict:
    """Load a copy of the page with a probe script in headless Chromium (no network); what the probe saw."""
    probe = page.with_name("_probe.html")
    probe.write_text(page.read_text().replace("<head>", "<head>" + PROBE, 1))
    try:
        proc = subprocess.run(
            [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={tmp / 'chrome'}",
             "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()],
            capture_output=True, text=True, timeout=120,
        )
    finally:
        probe.unlink()
    m = re.search(r'<pre id="__probe">([^<]*)</pre>', proc.stdout)
    assert m, f"the probe did not run (exit {proc.returncode}):\n{proc.stderr[-2000:]}"
    return json.loads(m.group(1).replace("&quot;", '"'))


@pytest.mark.slow
def test_report_of_a_sim_time_demo_opens_in_chromium(tmp_path: Path, demo_10s: Path) -> None:
    """A 10 s simulated-time demo, its report (runs tracked offline), loaded in headless Chromium."""
    if chromium() is None:
        pytest.skip("chromium is not installed (Debian package `chromium`; .ci/run installs it)")
    out = copy_session(demo_10s, tmp_path / "demo")
    rep = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "report", str(out), "--out", str(tmp_path / "report"),
         "--track-missing"], capture_output=True, text=True, timeout=600, cwd=REPO,
    )
    assert rep.returncode == 0, rep.stderr[-3000:]
    assert "episodes | done in" in rep.stderr  # the progress bar
    page = tmp_path / "report" / "report.html"
    html = page.read_text()
    assert "http://" not in html and "https://" not in html  # nothing fetched from the network
    row = re.search(r'<td class="l">rope</td><td class="l">medium</td>(.*?)</tr>', html, re.S)
    assert row, "no quality row for the rope"
    gt = re.findall(r"<td[^>]*>([^<]*)</td>", row.group(1))[7]
    assert 0.0 < float(gt) < 5.0
    seen = browser_check(page, tmp_path)
    assert seen["errors"] == [] and seen["broken"] == [], seen
    assert seen["images"] == 1 + 1 + 4  # trajectory, per-run plot, 4 thumbnails


def test_report_built_in_two_processes_equals_one(tmp_path: Path) -> None:
    """jobs=2 builds the runs in worker processes: the same page (tables, plots, thumbnails) as in-process."""
    session = tmp_path / "s"
    session.mkdir()
    _, _, _, intr = _session(session)
    X = np.stack([np.linspace(-0.1, 0.1, 5), np.full(5, 0.02), np.zeros(5)], axis=1)
    meta = {"object": "rope", "category": "dlo", "program": "rope_swing", "speed": "medium", "repeat": 1,
            "run_index": 1, "attempt": 1, "plan_pass": 0, "session_started": "2025-01-01T00:00:00Z",
            "calibration": {"K": intr.K.tolist(), "width": W, "height": H, "T_world_cam": T_CAM.tolist()}}
    w = EpisodeWriter(session / "episode_000002.mcap", "cam0")
    for n in range(20, 32):
        w.write_frame(_frame(n, intr), T_CAM)
        w.write_keypoints(_kp_message(n, X, 0.2 * n, 0.3 * n, "tracking"), 10.0 + n / 30.0)
    w.close({**meta, "episode_index": 2, "complete": True, "fault": False})
    pages = [build_report(session, tmp_path / f"r{jobs}", thumbnails=2, jobs=jobs) for jobs in (1, 2)]
    one, two = (re.sub(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d|\d+\.\d s", "", p.read_text()) for p in pages)
    assert one == two
    imgs = re.findall(r'<img src="([^"]+)"', one)
    assert len(imgs) == 1 + 2 + 2 * 2  # one trajectory (one object), two runs' plots and thumbnails
    assert all((pages[1].parent / i).is_file() for i in imgs)
    assert "rope · rope_swing · medium · #2" in one and "rope · rope_swing · fast · #1" in one
