"""``trackdeform report SESSION``: the morning report of a collection session as one offline HTML page.

The page (``report.html``, rendered from the jinja2 template ``templates/report.html.j2``) and its PNGs
(``images/``) go to one folder; nothing is fetched from the network when it opens. It holds the paper's
Table I metrics (Abs, E<5, CD, F<10) per object and speed, with the ground-truth error in mock mode; the
collection summary from ``session.journal.jsonl`` and ``summary.json``; per-run plots of edge-length error
and Chamfer distance against time (the paper's Fig. 5); one 3D keypoint-trajectory figure per object
(Fig. 1); and thumbnails with the keypoints drawn on the colour image.

Episodes are streamed: one episode file is read at a time and only per-frame scalars, the run's keypoints
(for its trajectory figure) and a few thumbnails are kept, so memory does not grow with the session.

One module (~550 lines) on purpose: reading, the figures and the page share the per-run ``RunData`` and
the order the page is built in; the template holds the page's layout.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import orjson

from orchestrator.progress import Progress, bar
from tdcommon.wire import edges_from_json, points_from_json
from tdrecord.episodes import ACTIVE_SUFFIX

TRACKED = ("init", "tracking", "degraded")  # keypoint statuses whose keypoints count in the metrics
THUMB_WIDTH = 480  # px, thumbnails are scaled down to this width
IMAGES = "images"


class ReportError(ValueError):
    """The session folder cannot be reported on (missing, no episodes); the message names the path."""


@dataclass
class RunData:
    """What the report keeps of one program run (one attempt): per-frame metrics and a few frames.

    t: (F,) s since the run's first frame, of the F frames with tracked keypoints; abs_mm, cd_mm: (F,)
    the paper's per-frame edge-length RMSE and keypoint-to-cloud distance; gt_mm: (F,) GT error (nan
    without ground truth); keypoints: F arrays (N, 3) m world; frame_numbers: (F,).
    """

    key: tuple
    object: str
    category: str
    program: str
    speed: str
    repeat: int
    attempt: int
    plan_pass: int
    episodes: list[Path]
    frames: int = 0
    source: str = "none"  # "recorded" (the live worker's /keypoints), "offline" (tracked by the report), "none"
    t: list[float] = field(default_factory=list)
    abs_mm: list[float] = field(default_factory=list)
    cd_mm: list[float] = field(default_factory=list)
    gt_mm: list[float] = field(default_factory=list)
    keypoints: list[np.ndarray] = field(default_factory=list)
    frame_numbers: list[int] = field(default_factory=list)
    edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    statuses: dict[str, int] = field(default_factory=dict)
    # frame number -> (file, its frame_info log ns, log ns of the colour keyframe it decodes from)
    log_times: dict[int, tuple[Path, int, int]] = field(default_factory=dict)
    incomplete: int = 0
    faults: int = 0
    bytes: int = 0
    t_trajectory: list[float] = field(default_factory=list)  # t of the frames kept for Fig. 1 (build_run)

    @property
    def label(self) -> str:
        """``object · program · speed · #repeat`` like the session's progress line."""
        extra = f" (attempt {self.attempt})" if self.attempt > 1 else ""
        return f"{self.object} · {self.program} · {self.speed} · #{self.repeat + 1}{extra}"


# ---------------------------------------------------------------------- reading
def _episode_files(session: Path) -> tuple[list[Path], list[Path]]:
    return sorted(session.glob("episode_*.mcap")), sorted(session.glob(f"*{ACTIVE_SUFFIX}"))


def group_runs(files: list[Path]) -> list[RunData]:
    """Episode files grouped into program runs (one attempt each) by their ``episode`` metadata, in file order."""
    from tdrecord import recorded_runs

    out = []
    for rec in recorded_runs(files):
        meta = rec.first
        out.append(RunData(
            key=rec.key, object=str(meta.get("object", "?")), category=str(meta.get("category", "")),
            program=str(meta.get("program", "?")), speed=str(meta.get("speed", "?")),
            repeat=int(meta.get("repeat", 0) or 0), attempt=int(meta.get("attempt", 1) or 1),
            plan_pass=int(meta.get("plan_pass", 0) or 0), episodes=list(rec.episodes),
            bytes=sum(f.stat().st_size for f in rec.episodes),
            incomplete=sum(int(m.get("complete") is False) for m in rec.metadata),
            faults=sum(int(bool(m.get("fault"))) for m in rec.metadata),
        ))
    return out


def _camera_topics(topics: set[str]) -> tuple[str, str]:
    cams = sorted(t.split("/")[2] for t in topics if t.startswith("/cam/") and t.endswith("/color"))
    if not cams:
        raise ReportError(f"no '/cam/<id>/color' channel (channels: {sorted(topics)})")
    return f"/cam/{cams[0]}/color", f"/cam/{cams[0]}/frame_info"


def _gt_errors(frames: list[tuple[int, np.ndarray, dict[str, Any]]], out: list[float]) -> None:
    """GT error (mm) of recorded keypoints: ``out[i]`` for every (i, keypoints (N, 3) m, ground-truth JSON)
    in ``frames`` (:func:`orchestrator.episode_stats.gt_errors_mm`)."""
    from orchestrator.episode_stats import gt_errors_mm

    for (i, _, _), v in zip(frames, gt_errors_mm([(X, d) for _, X, d in frames]), strict=True):
        out[i] = v


def _small_channels(path: Path) -> tuple[Iterator[tuple[str, int, dict[str, Any]]], dict[int, float] | None]:
    """(topic, log time ns, JSON) of an episode's frame info, ``/keypoints`` and ground truth, and the keypoints'
    ground-truth errors by frame number when they were computed already: from its digest (``tdrecord.digest``,
    no image chunk decompressed) when it has one, else (errors None) from the MCAP file."""
    from tdrecord.digest import read_digest

    digest = read_digest(path)
    if digest is not None:
        return iter(digest.messages), digest.gt_error_mm
    return _mcap_small_channels(path), None


def _mcap_small_channels(path: Path) -> Iterator[tuple[str, int, dict[str, Any]]]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic for c in summary.channels.values()} if summary else set()
        _, info = _camera_topics(topics)
        for _, channel, msg in reader.iter_messages(
            topics=[t for t in (info, "/keypoints", "/ground_truth/keypoints") if t in topics]
        ):
            yield channel.topic, int(msg.log_time), orjson.loads(msg.data)


def read_recorded(run: RunData) -> None:
    """Fill ``run`` from its episodes' ``/keypoints`` (and ``/ground_truth/keypoints``), one file at a time."""
    t0: float | None = None
    pending_gt: list[tuple[int, np.ndarray, dict[str, Any]]] = []
    for path in run.episodes:
        kps: dict[int, dict[str, Any]] = {}
        gts: dict[int, dict[str, Any]] = {}
        key = -1
        messages, known_gt = _small_channels(path)
        for topic, log_time, d in messages:
            fn = int(d.get("frame_number", -1))
            if topic.endswith("/frame_info"):
                run.frames += 1
                if d.get("color_keyframe", True) or key < 0:
                    key = log_time
                run.log_times[fn] = (path, log_time, key)
                if t0 is None:
                    t0 = float(d.get("device_stamp", log_time * 1e-9))
            elif topic == "/keypoints":
                kps[fn] = d
            else:
                gts[fn] = d
        for fn in sorted(kps):
            d = kps[fn]
            status = str(d.get("status", ""))
            run.statuses[status] = run.statuses.get(status, 0) + 1
            X = points_from_json(d.get("keypoints", []))
            if status not in TRACKED or not len(X) or d.get("abs_mm") is None or d.get("cd_mm") is None:
                continue
            if run.keypoints and len(X) != len(run.keypoints[0]):
                continue  # a re-initialisation with another keypoint count: the run's figures keep the first
            if not len(run.edges):
                run.edges = edges_from_json(d.get("edges", []))
            run.t.append(float(d.get("stamp", 0.0)) - (t0 or 0.0))
            run.abs_mm.append(float(d["abs_mm"]))
            run.cd_mm.append(float(d["cd_mm"]))
            if known_gt is not None:
                run.gt_mm.append(known_gt.get(fn, float("nan")))
            else:
                if fn in gts:
                    pending_gt.append((len(run.gt_mm), X, gts[fn]))
                run.gt_mm.append(float("nan"))
            run.keypoints.append(X)
            run.frame_numbers.append(fn)
        _gt_errors(pending_gt, run.gt_mm)  # per episode: the ground truth of one file at a time is kept
        pending_gt.clear()
    if run.keypoints:
        run.source = "recorded"


def track_offline(run: RunData, config: Any, tick: Callable[[int], None] | None = None) -> None:
    """Fill ``run`` by tracking its episodes offline (one pipeline across them, frames decoded one at a time);
    ``tick(frames_done)`` is called every 15 frames (progress display)."""
    from orchestrator.offline import track_frames
    from orchestrator.worker import tracking_params
    from tdcommon.objects import DIMENSION
    from tdrecord import read_episode_metadata, read_episodes
    from tracking.metrics import surface_error_mm

    meta = read_episode_metadata(run.episodes[0])
    params = tracking_params(config.tracking, run.category or None, meta.get("n_keypoints"))
    seqs = (read_episodes(p) for p in run.episodes)
    t0: float | None = None
    run.statuses = {}
    for tf in track_frames(seqs, params, DIMENSION.get(run.category)):
        out, frame = tf.out, tf.frame
        if tick is not None and tf.index % 15 == 0:
            tick(tf.index)
        if t0 is None:
            t0 = frame.device_stamp
        run.statuses[out.status] = run.statuses.get(out.status, 0) + 1
        if out.status not in TRACKED or not len(out.keypoints) or not math.isfinite(out.cd_mm):
            continue
        if run.keypoints and len(out.keypoints) != len(run.keypoints[0]):
            continue
        if not len(run.edges) and out.topology is not None:
            run.edges = np.asarray(out.topology.edges, np.int64)
        gt = frame.ground_truth
        run.t.append(frame.device_stamp - t0)
        run.abs_mm.append(float(out.abs_mm))
        run.cd_mm.append(float(out.cd_mm))
        run.gt_mm.append(surface_error_mm(out.keypoints, gt.centreline, gt.radius, polyline=gt.category != "cloth")
                         if gt is not None and len(gt.centreline) else float("nan"))
        run.keypoints.append(np.array(out.keypoints))
        run.frame_numbers.append(frame.frame_number)
    if run.keypoints:
        run.source = "offline"


def read_color_at(path: Path, log_time: int, key_time: int) -> np.ndarray | None:
    """The colour image (H, W, 3) uint8 RGB logged at ``log_time`` ns, decoded from the keyframe logged at
    ``key_time``: only the chunks between the two are read. None when it is not there (then ``read_color``)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from tdrecord.codecs import ImageDecoder

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        topics = {c.topic for c in summary.channels.values()} if summary else set()
        color, _ = _camera_topics(topics)
        factory, decoders, images = DecoderFactory(), {}, ImageDecoder(f"{path} {color}")
        # mcap >= 1.3 names the bounds starting_at / ending_before (start_time / end_time are deprecated)
        new = "starting_at" in inspect.signature(reader.iter_messages).parameters
        bounds = ({"starting_at": key_time, "ending_before": log_time + 1} if new
                  else {"start_time": key_time, "end_time": log_time + 1})
        for schema, channel, msg in reader.iter_messages(topics=[color], **bounds):
            if schema is None or msg.log_time < key_time:
                continue
            dec = decoders.get(schema.id) or decoders.setdefault(
                schema.id, factory.decoder_for(channel.message_encoding, schema))
            img = images.decode(schema.name, dec(msg.data))
            if msg.log_time == log_time:
                return img
    return None


def read_color(path: Path, frame_number: int) -> np.ndarray:
    """The colour image (H, W, 3) uint8 RGB of frame ``frame_number`` of an episode file (decoded through
    the episode reader, so an H.264 frame is decoded from its keyframe on)."""
    from tdrecord import read_episodes

    seq = read_episodes(path)
    where = np.flatnonzero(seq.frame_numbers == frame_number) if seq.frame_numbers is not None else []
    if not len(where):
        raise ReportError(f"{path}: no frame {frame_number}")
    return next(iter(seq.frames.iter_from(int(where[0])))).color  # type: ignore[attr-defined]


# ---------------------------------------------------------------------- figures
def project(points: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) of world points (N, 3) m through K (3, 3) and the camera pose (4, 4), and
    which of them lie in front of the camera (N,) bool."""
    T_cam_world = np.linalg.inv(T_world_cam)
    pc = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = pc[:, 2]
    front = z > 1e-6
    uvw = pc @ K.T
    uv = uvw[:, :2] / np.where(front, z, 1.0)[:, None]
    return uv, front


def draw_thumbnail(color: np.ndarray, X: np.ndarray, edges: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                   width: int = THUMB_WIDTH) -> np.ndarray:
    """The colour image (H, W, 3) RGB scaled to ``width`` px with keypoints X (N, 3) m (coloured by index)
    and their edges (E, 2) drawn on it."""
    import cv2
    from matplotlib import colormaps

    h, w = color.shape[:2]
    s = width / w
    img = cv2.resize(color, (width, max(1, int(round(h * s)))), interpolation=cv2.INTER_AREA)
    uv, front = project(X, K, T_world_cam)
    px = np.round(uv * s).astype(int)
    for i, j in edges:
        if front[i] and front[j]:
            cv2.line(img, tuple(map(int, px[i])), tuple(map(int, px[j])), (255, 255, 255), 1, cv2.LINE_AA)
    cols = (np.asarray(colormaps["viridis"](np.linspace(0, 1, max(2, len(X))))[:, :3]) * 255).astype(int)
    for k in np.nonzero(front)[0]:
        cv2.circle(img, tuple(map(int, px[k])), 3, tuple(int(c) for c in cols[k]), -1, cv2.LINE_AA)
    return img


class Fig5:
    """Fig. 5: edge-length error (Abs) and Chamfer distance (and the GT error in mock mode) against time.

    One figure drawn again for every run (its lines get the run's data): building a matplotlib figure per
    run cost as much as drawing it twice (0.14 s CPU a run against 0.07).
    """

    def __init__(self) -> None:
        import matplotlib.pyplot as plt

        self.fig, self.axes = plt.subplots(2, 1, figsize=(7.0, 3.8), sharex=True, constrained_layout=True)
        ax0, ax1 = self.axes
        (self.abs_line,) = ax0.plot([], [], lw=1.0, color="tab:blue", label="Abs (edge-length RMSE)")
        (self.gt_line,) = ax0.plot([], [], lw=1.0, color="tab:green", label="GT error")
        (self.cd_line,) = ax1.plot([], [], lw=1.0, color="tab:orange", label="CD (Chamfer distance)")
        ax0.axhline(5.0, color="grey", lw=0.6, ls="--")
        ax0.set_ylabel("mm")
        ax1.axhline(10.0, color="grey", lw=0.6, ls="--")
        ax1.set_ylabel("mm")
        ax1.set_xlabel("time in run, s")
        ax1.legend(handles=[self.cd_line], loc="upper right", fontsize=7)

    def save(self, run: RunData, path: Path) -> None:
        """Draw ``run`` and write the PNG to ``path``."""
        t = np.asarray(run.t)
        gt = np.asarray(run.gt_mm)
        has_gt = bool(np.isfinite(gt).any())
        self.abs_line.set_data(t, run.abs_mm)
        self.gt_line.set_data(t if has_gt else [], gt if has_gt else [])
        self.cd_line.set_data(t, run.cd_mm)
        ax0, ax1 = self.axes
        ax0.legend(handles=[self.abs_line] + ([self.gt_line] if has_gt else []), loc="upper right", fontsize=7)
        for ax in self.axes:
            ax.relim()
            ax.autoscale_view()
        self.fig.suptitle(run.label, fontsize=9)
        self.fig.savefig(path, dpi=90, pil_kwargs={"compress_level": 1})  # level 6: half of each save
        if self.fig.get_layout_engine() is not None:  # laid out once: the layout was half of every later save
            self.fig.set_layout_engine("none")

    def close(self) -> None:
        import matplotlib.pyplot as plt

        plt.close(self.fig)


def plot_run(run: RunData, path: Path) -> None:
    """Fig. 5 of one run as a PNG (``Fig5`` draws many runs on one figure)."""
    fig = Fig5()
    try:
        fig.save(run, path)
    finally:
        fig.close()


def plot_trajectory(run: RunData, path: Path, max_samples: int = 120) -> None:
    """Fig. 1: every keypoint's 3D trajectory, colour by keypoint index, opacity by time (faint early,
    opaque late), with the last frame's edges."""
    import matplotlib.pyplot as plt
    from matplotlib import colormaps

    traj = np.stack(run.keypoints)  # (F, N, 3) m
    F, N = traj.shape[:2]
    idx = np.unique(np.linspace(0, F - 1, min(F, max_samples)).round().astype(int))
    sub = traj[idx]
    cols = np.asarray(colormaps["viridis"](np.linspace(0, 1, max(2, N))))[:N]
    alpha = np.linspace(0.08, 1.0, len(idx))
    rgba = np.repeat(cols[None], len(idx), axis=0)
    rgba[..., 3] = alpha[:, None]
    fig = plt.figure(figsize=(5.5, 4.5), constrained_layout=True)
    ax = fig.add_subplot(projection="3d")
    ax.scatter(sub[..., 0].ravel(), sub[..., 1].ravel(), sub[..., 2].ravel(), c=rgba.reshape(-1, 4), s=4,
               depthshade=False)
    last = traj[-1]
    for i, j in run.edges:
        ax.plot(*np.stack([last[i], last[j]]).T, color="black", lw=0.8)
    ax.set_xlabel("x, m")
    ax.set_ylabel("y, m")
    ax.set_zlabel("z, m")
    lo, hi = sub.reshape(-1, 3).min(axis=0), sub.reshape(-1, 3).max(axis=0)
    c, r = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-3)
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_title(f"{run.object}: {N} keypoints over {run.t[-1] - run.t[0]:.1f} s ({run.label})", fontsize=8)
    sm = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(0, N - 1))
    fig.colorbar(sm, ax=ax, shrink=0.6, label="keypoint index")
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------- tables
def _fmt(v: float, digits: int = 2) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def quality_rows(runs: list[RunData]) -> list[dict[str, Any]]:
    """Table I per object and speed: Abs, E<5, CD, F<10 over every tracked frame of its runs, GT RMSE."""
    from tracking.metrics import sequence_summary

    groups: dict[tuple[str, str], list[RunData]] = {}
    for r in runs:
        if r.abs_mm:
            groups.setdefault((r.object, r.speed), []).append(r)
    rows = []
    for (obj, speed), rs in sorted(groups.items()):
        a = np.concatenate([r.abs_mm for r in rs])
        c = np.concatenate([r.cd_mm for r in rs])
        g = np.concatenate([r.gt_mm for r in rs])
        m = sequence_summary(a, c)
        g = g[np.isfinite(g)]
        rows.append({
            "object": obj, "speed": speed, "runs": len(rs), "frames": int(len(a)),
            "tracked": f"{100.0 * len(a) / max(1, sum(r.frames for r in rs)):.0f} %",
            "Abs": _fmt(m["Abs"]), "E<5": _fmt(m["E<5"], 1), "CD": _fmt(m["CD"]), "F<10": _fmt(m["F<10"], 1),
            "GT": _fmt(float(np.sqrt(np.mean(g**2)))) if len(g) else "–",
            "source": ", ".join(sorted({r.source for r in rs})),
        })
    return rows


def live_init_row(record: dict[str, Any]) -> dict[str, str]:
    """A journal ``live_init`` record as a row of the report's table: the object, the run it preceded, the
    outcome, attempts, seconds and the last attempt's check (keypoints, edge error, gripper distance) or reason."""
    attempts = record.get("attempts") or []
    m = (attempts[-1].get("metrics") or {}) if attempts else {}
    grip = m.get("gripper_distance_m") or {}
    check = ""
    if m:
        check = (f"{m.get('n_keypoints', '?')} keypoints, edge error {_fmt(float(m.get('abs_mm') or 0.0))} mm"
                 f" ({_fmt(float(m.get('edge_error') or 0.0), 3)} of an edge)")
        if grip:
            check += ", gripper " + " / ".join(f"{k} {1000 * float(v):.0f} mm" for k, v in grip.items())
    return {"object": str(record.get("object", "?")),
            "before": f"{record.get('program')} · {record.get('speed')} · #{int(record.get('repeat', 0)) + 1}",
            "outcome": str(record.get("outcome", "?")), "attempts": str(len(attempts)),
            "seconds": _fmt(float(record.get("seconds") or 0.0), 1),
            "check": check if record.get("outcome") == "ok" else (record.get("reason") or check)}


def collection_summary(session: Path, runs: list[RunData], active: list[Path]) -> dict[str, Any]:
    """Runs done / failed / skipped with reasons (journal), frames (summary.json), episodes, disk, incidents."""
    from orchestrator.journal import read_journal

    journal_path = session / "session.journal.jsonl"
    records: list[dict[str, Any]] = read_journal(journal_path).records if journal_path.is_file() else []
    outcomes = [r for r in records if r.get("type") == "run"]

    def label(r: dict[str, Any]) -> str:
        return (f"{r.get('object')} · {r.get('program')} · {r.get('speed')} · #{int(r.get('repeat', 0)) + 1}"
                f" (pass {r.get('pass', 0)}, attempt {r.get('attempt', 1)})")

    runs_table = [{"run": label(r), "outcome": r.get("outcome", "?"), "reason": r.get("reason") or "",
                   "episodes": len(r.get("episodes") or []), "wall": _fmt(float(r.get("wall_seconds") or 0), 1),
                   "finished": r.get("finished", "")} for r in outcomes]
    counts = {k: sum(1 for r in outcomes if r.get("outcome") == k) for k in ("done", "failed", "skipped")}
    live_init = [live_init_row(r) for r in records if r.get("type") == "live_init"]
    incidents: list[str] = []
    open_starts: dict[tuple, dict[str, Any]] = {}
    for r in records:
        k = (r.get("pass"), r.get("object"), r.get("program"), r.get("speed"), r.get("repeat"), r.get("attempt"))
        if r.get("type") == "start":
            open_starts[k] = r
        elif r.get("type") == "run":
            open_starts.pop(k, None)
            if r.get("outcome") != "done":
                incidents.append(f"{label(r)}: {r.get('outcome')}: {r.get('reason') or 'no reason given'}")
    for r in open_starts.values():
        incidents.append(f"{label(r)}: started {r.get('started', '?')} and never finished (crash or stop)")
    sessions = [r for r in records if r.get("type") == "session"]
    if len(sessions) > 1:
        incidents.append(f"the folder was recorded by {len(sessions)} sessions (resumed "
                         f"{len(sessions) - 1} time(s): " + ", ".join(str(s.get('started')) for s in sessions) + ")")
    summary: dict[str, Any] = {}
    summary_path = session / "summary.json"
    if summary_path.is_file():
        try:
            summary = json.loads(summary_path.read_text())
        except json.JSONDecodeError as e:
            incidents.append(f"{summary_path.name}: unreadable ({e})")
    for e in summary.get("errors") or []:
        incidents.append(f"error: {e}")
    for e in summary.get("runs_cut_short") or []:
        incidents.append(f"cut short: {e}")
    if summary.get("stopped_early"):
        incidents.append(f"stopped early: {summary['stopped_early']}")
    if summary.get("faults_recovered"):
        incidents.append(f"{summary['faults_recovered']} fault(s) recovered during runs")
    for r in runs:
        if r.faults:
            incidents.append(f"{r.label}: {r.faults} episode(s) flagged with a fault")
        if r.incomplete:
            incidents.append(f"{r.label}: {r.incomplete} episode(s) incomplete (cut short)")
    for a in active:
        incidents.append(f"{a.name}: unfinished file (run `trackdeform recover {session}`)")
    disk = sum(p.stat().st_size for p in session.iterdir() if p.is_file())
    return {
        "runs_done": counts["done"], "runs_failed": counts["failed"], "runs_skipped": counts["skipped"],
        "runs_table": runs_table, "live_init": live_init,
        "journal": journal_path.name if records else "(no journal)",
        "frames_captured": summary.get("frames_captured", sum(r.frames for r in runs)),
        "frames_dropped": summary.get("frames_dropped", "–"),
        "recorded_seconds": _fmt(float(summary.get("recorded_seconds") or 0.0), 1),
        "episodes": sum(len(r.episodes) for r in runs), "disk": f"{disk / 1e9:.2f} GB" if disk > 1e8
        else f"{disk / 1e6:.1f} MB", "sessions": len(sessions), "incidents": incidents,
    }


# ---------------------------------------------------------------------- the page
@dataclass
class RunReport:
    """What building one run's part of the page returns to the page (picklable: runs are built in worker
    processes): the run's per-frame scalars (keypoints dropped), its view for the template, its row of the
    keypoint-version table, a note, and up to ``TRAJECTORY_SAMPLES`` frames of keypoints for Fig. 1."""

    run: RunData
    view: dict[str, Any]
    version_row: dict[str, Any] | None = None
    note: str | None = None
    trajectory: list[np.ndarray] = field(default_factory=list)


TRAJECTORY_SAMPLES = 120  # frames of a run kept for its object's Fig. 1 (plot_trajectory draws at most these)
_FIG5: list[Fig5] = []  # one Fig5 per process, redrawn for every run it builds


def build_run(n: int, run: RunData, out: Path, config: Any, track_missing: bool, thumbnails: int,
              has_versions: bool, session: Path, tick: Callable[[int], None] | None = None) -> RunReport:
    """Read (or, with ``track_missing``, track) one run and write its Fig. 5 plot and thumbnails into
    ``out/images``; ``n`` is the run's place on the page (its file names)."""
    import cv2

    read_recorded(run)
    if run.source == "none" and track_missing:
        if config is None:
            from orchestrator.config import DEFAULT_CONFIG, load_config

            config = load_config(DEFAULT_CONFIG)
        track_offline(run, config, tick)
    rep = RunReport(run, {"label": run.label, "episodes": len(run.episodes), "frames": run.frames,
                          "tracked": len(run.t), "source": run.source, "statuses": run.statuses,
                          "plot": None, "thumbs": []})
    if has_versions:  # keypoint versions made by `trackdeform retrack`, against this run's keypoints and each other
        from orchestrator.retrack import version_differences

        diff = version_differences(session, run.episodes, run.frame_numbers, run.keypoints)["rows"]
        rep.version_row = {"run": run.label, "source": run.source, "cells": [
            (f"{_fmt(d['vs_live_mm'], 3)} ({d['vs_live_frames']})", f"{_fmt(d['vs_previous_mm'], 3)} "
             f"({d['vs_previous_frames']})") for d in diff]}
    view = rep.view
    if run.source == "none":
        rep.note = (f"{run.label}: no tracked keypoints in its episodes"
                    + ("" if track_missing else " (tracking off or the worker did not keep up: "
                                                "pass --track-missing to track it offline)"))
    else:
        from tdrecord import read_calibration
        from tracking.metrics import sequence_summary

        m = sequence_summary(np.asarray(run.abs_mm), np.asarray(run.cd_mm))
        g = np.asarray(run.gt_mm)
        g = g[np.isfinite(g)]
        view.update({k: _fmt(v, 1 if k.endswith("10") or k.endswith("5") else 2) for k, v in m.items()})
        view["GT"] = _fmt(float(np.sqrt(np.mean(g**2)))) if len(g) else "–"
        name = f"run{n:03d}_metrics.png"
        if not _FIG5:
            import matplotlib

            matplotlib.use("Agg")  # also in a worker process: files only, no display
            _FIG5.append(Fig5())
        _FIG5[0].save(run, out / IMAGES / name)
        view["plot"] = f"{IMAGES}/{name}"
        cal = read_calibration(run.episodes[0])
        for k in _thumbnail_frames(run, thumbnails):
            fn = run.frame_numbers[k]
            if fn not in run.log_times:
                continue
            path, log_time, key_time = run.log_times[fn]
            color = read_color_at(path, log_time, key_time)
            img = draw_thumbnail(color if color is not None else read_color(path, fn), run.keypoints[k],
                                 run.edges, cal.K, cal.T_world_cam, THUMB_WIDTH)
            tname = f"run{n:03d}_frame{fn}.png"
            cv2.imwrite(str(out / IMAGES / tname), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            view["thumbs"].append({"src": f"{IMAGES}/{tname}", "caption": f"frame {fn}, t = {run.t[k]:.1f} s"})
        idx = np.unique(np.linspace(0, len(run.keypoints) - 1, min(len(run.keypoints), TRAJECTORY_SAMPLES))
                        .round().astype(int))
        rep.trajectory = [run.keypoints[i] for i in idx]
        run.t_trajectory = [run.t[i] for i in idx]
    run.keypoints, run.frame_numbers, run.log_times = [], [], {}  # only the scalars go back to the page
    return rep


def _build_runs(runs: list[RunData], jobs: int, args: tuple[Any, ...], progress: Progress, files: int
                ) -> Iterator[RunReport]:
    """Every run's RunReport in page order: in this process (``jobs`` 1) or in ``jobs`` worker processes,
    the runs being independent (one Fig. 5 plot, thumbnails decoded from their own episodes)."""
    done = 0
    if jobs <= 1:
        try:
            for n, run in enumerate(runs):
                progress.update(f"{bar(done, files)} | {run.label}", force=True)
                yield build_run(n, run, *args, tick=lambda i, d=done, f=run.frames, lbl=run.label: progress.update(
                    f"{bar(d, files)} | {lbl}: tracking offline, frame {i}/{f}"))
                done += len(run.episodes)
        finally:
            while _FIG5:
                _FIG5.pop().close()
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    results: dict[int, RunReport] = {}
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(build_run, n, run, *args): n for n, run in enumerate(runs)}
        progress.update(f"{bar(0, files)} | {len(runs)} runs on {jobs} processes", force=True)
        nxt = 0
        from concurrent.futures import as_completed

        for fut in as_completed(futures):
            n = futures[fut]
            results[n] = fut.result()
            done += len(runs[n].episodes)
            progress.update(f"{bar(done, files)} | {runs[n].label}", force=True)
            while nxt in results:  # hand them on in page order, keeping only those not yet handed on
                yield results.pop(nxt)
                nxt += 1


def build_report(
    session: Path,
    out: Path,
    *,
    config: Any = None,
    track_missing: bool = False,
    thumbnails: int = 4,
    jobs: int | None = None,
    progress: Progress | None = None,
) -> Path:
    """Write ``out/report.html`` and ``out/images/*.png`` for a session folder; returns the page's path.

    track_missing: runs whose episodes hold no tracked keypoints (tracking off, or a worker that did not
    keep up) are tracked offline with ``config``'s tracking section (else they appear without metrics).
    jobs: processes building runs side by side (default: one per core, never more than the runs; 1 builds
    them in this process).
    """
    import jinja2
    import matplotlib

    matplotlib.use("Agg")
    session = Path(session)
    if not session.is_dir():
        raise ReportError(f"{session}: no such session folder")
    files, active = _episode_files(session)
    if not files:
        hint = f" ({len(active)} unfinished: run `trackdeform recover {session}`)" if active else ""
        raise ReportError(f"{session}: no episode_*.mcap files{hint}")
    out = Path(out)
    (out / IMAGES).mkdir(parents=True, exist_ok=True)
    progress = progress or Progress()
    t_start = time.monotonic()
    runs = group_runs(files)
    from orchestrator.retrack import list_versions

    versions = list_versions(session)
    jobs = max(1, min(len(runs), jobs if jobs is not None else (os.cpu_count() or 1)))
    per_object: dict[str, RunReport] = {}
    run_views, version_rows, notes = [], [], []
    built: list[RunData] = []
    args = (out, config, track_missing, thumbnails, bool(versions), session)
    for rep in _build_runs(runs, jobs, args, progress, len(files)):
        built.append(rep.run)
        run_views.append(rep.view)
        if rep.version_row is not None:
            version_rows.append(rep.version_row)
        if rep.note:
            notes.append(rep.note)
        if rep.trajectory and rep.run.object not in per_object:
            per_object[rep.run.object] = rep
        rep.trajectory = rep.trajectory if per_object.get(rep.run.object) is rep else []
    trajectories = []
    for o, rep in per_object.items():
        tname = f"trajectory_{_safe(o)}.png"
        plot_trajectory(replace(rep.run, keypoints=rep.trajectory, t=rep.run.t_trajectory), out / IMAGES / tname)
        trajectories.append({"object": o, "src": f"{IMAGES}/{tname}", "run": rep.run.label})
    progress.update(f"{bar(len(files), len(files))} | writing the page", force=True)
    env = jinja2.Environment(loader=jinja2.PackageLoader("orchestrator", "templates"),
                             autoescape=jinja2.select_autoescape(["html", "j2"]))
    html = env.get_template("report.html.j2").render(
        session=str(session.resolve()), generated=time.strftime("%Y-%m-%d %H:%M:%S"),
        quality=quality_rows(built), collection=collection_summary(session, built, active), runs=run_views,
        trajectories=trajectories, notes=notes, versions=versions, version_rows=version_rows,
        seconds=f"{time.monotonic() - t_start:.1f}",
    )
    page = out / "report.html"
    page.write_text(html, encoding="utf-8")
    progress.update(f"{bar(len(files), len(files))} | done in {time.monotonic() - t_start:.1f} s", force=True)
    progress.done()
    return page


def _thumbnail_frames(run: RunData, count: int, max_shift: int = 15) -> list[int]:
    """Indices into the run's tracked frames of ``count`` thumbnails spread over the run; each is moved to the
    nearest tracked colour keyframe at most ``max_shift`` tracked frames (and half the spacing) away, unless
    another thumbnail took it: a keyframe decodes alone (no earlier frame decoded, ~3x faster for H.264)."""
    want = np.unique(np.linspace(0, len(run.t) - 1, max(1, count)).round().astype(int)).tolist()
    max_shift = min(max_shift, (len(run.t) - 1) // max(1, 2 * (count - 1)))  # keep them spread over the run
    keys = np.array([k for k, fn in enumerate(run.frame_numbers)
                     if fn in run.log_times and run.log_times[fn][1] == run.log_times[fn][2]], dtype=int)
    picks: list[int] = []
    for k in want:
        near = keys[np.argsort(np.abs(keys - k), kind="stable")] if len(keys) else keys
        moved = next((int(j) for j in near if abs(int(j) - k) <= max_shift and int(j) not in picks), None)
        picks.append(moved if moved is not None and k not in picks else k)
    return sorted(set(picks))


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "object"


# ---------------------------------------------------------------------- CLI
def cmd_report(args: argparse.Namespace) -> int:
    """``trackdeform report SESSION [--out DIR]``."""
    from orchestrator.config import ConfigError, load_config

    try:
        config = load_config(args.config) if args.config else None
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path(args.session) / "report"
    try:
        page = build_report(Path(args.session), out, config=config, track_missing=args.track_missing,
                            thumbnails=args.thumbnails, jobs=args.jobs)
    except ReportError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(page)
    return 0


def register(sub: Any) -> None:
    """Add the ``report`` subcommand to the main parser."""
    p = sub.add_parser("report", help="the morning report of a session: HTML page + PNGs, opens offline")
    p.add_argument("session", help="session folder (episodes, session.journal.jsonl, summary.json)")
    p.add_argument("--out", help="output folder (default: SESSION/report)")
    p.add_argument("--track-missing", action="store_true",
                   help="track runs recorded without keypoints offline (slow: every frame is tracked)")
    p.add_argument("--config", help="tracking parameters for --track-missing (default: the mock config)")
    p.add_argument("--thumbnails", type=int, default=4, help="thumbnails per run")
    p.add_argument("--jobs", type=int, help="processes building runs side by side (default: one per core)")
    p.set_defaults(func=cmd_report)
