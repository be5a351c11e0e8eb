"""What ``trackdeform inspect`` measures in an episode file: rates, gaps, frame drops and keypoint coverage,
per file (:func:`episode_stats`) and over a folder (:func:`folder_summary`).

Camera rate and gaps come from the frames' device stamps (``/cam/<id>/frame_info``), drops from their frame
numbers; the joint-state rate from ``/arms/state`` stamps (host clock); coverage is the fraction of frames
with a keypoint message holding keypoints, live (``/keypoints``) and final (``/keypoints/final``).
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

GAP_FACTOR = 1.5  # an interval longer than this many nominal periods is a gap


def gt_errors_mm(frames: Sequence[tuple[np.ndarray, dict[str, Any]]]) -> list[float]:
    """Ground-truth error (mm, ``tracking.metrics.surface_error_mm``) of each (keypoints (N, 3) m, recorded
    ``/ground_truth/keypoints`` message) pair; nan without keypoints or true samples. Frames whose keypoints and
    samples have the same shapes go through ``surface_errors_mm`` together (one batch, not a loop of frames)."""
    from tdcommon.wire import ground_truth_from_json
    from tracking.metrics import surface_errors_mm

    out = [float("nan")] * len(frames)
    groups: dict[tuple, list[tuple[int, np.ndarray, np.ndarray]]] = {}
    for i, (X, d) in enumerate(frames):
        g = ground_truth_from_json(d)
        if len(g.centreline) and len(X):
            key = (X.shape, g.centreline.shape, g.radius, g.category != "cloth")
            groups.setdefault(key, []).append((i, X, g.centreline))
    for (_, _, radius, polyline), items in groups.items():
        e = surface_errors_mm(np.stack([x for _, x, _ in items]), np.stack([c for _, _, c in items]), radius,
                              polyline=polyline)
        for (i, _, _), v in zip(items, e, strict=True):
            out[i] = float(v)
    return out


def message_gt_errors_mm(pairs: Sequence[tuple[dict[str, Any], dict[str, Any]]]) -> list[float]:
    """:func:`gt_errors_mm` of (``/keypoints`` message, ground-truth message) pairs (an episode digest's)."""
    from tdcommon.wire import points_from_json

    return gt_errors_mm([(points_from_json(k.get("keypoints", [])), g) for k, g in pairs])


def expand_inputs(paths: Iterable[str]) -> list[Path]:
    """Files as given; a folder becomes its finished ``*.mcap`` files, in name order (unfinished ``.active``
    ones are ``trackdeform recover``'s)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted(p.glob("*.mcap"))
        else:
            out.append(p)
    return out


def _intervals(stamps: np.ndarray, nominal: float | None) -> dict[str, Any]:
    """Rate (Hz), longest interval (ms) and gaps (intervals over GAP_FACTOR nominal periods) of stamps (n,) s."""
    s = np.sort(stamps[np.isfinite(stamps)])
    if len(s) < 2:
        return {"rate_hz": None, "max_interval_ms": None, "gaps": 0}
    d = np.diff(s)
    period = 1.0 / nominal if nominal else float(np.median(d))
    return {"rate_hz": float((len(s) - 1) / (s[-1] - s[0])) if s[-1] > s[0] else None,
            "max_interval_ms": float(d.max() * 1e3), "gaps": int(np.count_nonzero(d > GAP_FACTOR * period))}


def _coverage(frames: np.ndarray, with_keypoints: set[int]) -> dict[str, Any]:
    """Fraction of frames (frame numbers (T,)) that have keypoints, and the longest run without, in frames."""
    have = np.isin(frames, np.fromiter(with_keypoints, dtype=np.int64, count=len(with_keypoints)))
    longest = 0
    if len(have) and not have.all():  # longest run of False, vectorised
        h = np.concatenate([[True], have, [True]]).astype(np.int8)
        d = np.diff(h)
        longest = int((np.flatnonzero(d == 1) - np.flatnonzero(d == -1)).max())
    return {"frames": int(have.sum()), "coverage": float(have.mean()) if len(have) else 0.0,
            "longest_gap_frames": longest}


def episode_stats(path: Path) -> dict[str, Any]:
    """Rates, gaps, drops and keypoint coverage of one finished episode file (reads every small channel)."""
    from mcap.reader import make_reader

    frames: list[tuple[int, float, float]] = []
    states: list[float] = []
    kp: dict[str, set[int]] = {"live": set(), "final": set()}
    kp_channels: set[str] = set()
    fps = None
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic for c in summary.channels.values()} if summary is not None else set()
        for m in reader.iter_metadata():
            if m.name == "episode" and "fps" in m.metadata:
                fps = float(json.loads(m.metadata["fps"]) or 0) or None
        wanted = [t for t in topics if t.endswith("/frame_info") or t in ("/arms/state", "/keypoints",
                                                                             "/keypoints/final")]
        for _, channel, msg in reader.iter_messages(topics=wanted):
            d = json.loads(msg.data)
            if channel.topic.endswith("/frame_info"):
                frames.append((int(d.get("frame_number", -1)), float(d.get("device_stamp", np.nan)),
                               float(d.get("host_stamp", np.nan))))
            elif channel.topic == "/arms/state":
                states.append(float(d.get("stamp", np.nan)))
            else:
                kind = "final" if channel.topic == "/keypoints/final" else "live"
                kp_channels.add(kind)
                if d.get("keypoints"):
                    kp[kind].add(int(d.get("frame_number", -1)))
    fn = np.array([f[0] for f in frames], dtype=np.int64)
    device = np.array([f[1] for f in frames], dtype=np.float64)
    host = np.array([f[2] for f in frames], dtype=np.float64)
    order = np.argsort(fn, kind="stable")
    fn, device, host = fn[order], device[order], host[order]
    steps = np.diff(fn)
    cam = _intervals(device, fps)
    out: dict[str, Any] = {
        "frames": int(len(fn)),
        "first_frame": int(fn[0]) if len(fn) else None,
        "last_frame": int(fn[-1]) if len(fn) else None,
        "nominal_fps": fps,
        "camera_fps": cam["rate_hz"],
        "camera_fps_host": _intervals(host, fps)["rate_hz"],
        "frame_drops": int(np.clip(steps - 1, 0, None).sum()),
        "frame_gaps": cam["gaps"],
        "max_frame_interval_ms": cam["max_interval_ms"],
        "joint_states": len(states),
    }
    js = _intervals(np.asarray(states, dtype=np.float64), None)
    out.update(joint_state_hz=js["rate_hz"], joint_state_gaps=js["gaps"],
               max_joint_state_interval_ms=js["max_interval_ms"])
    out["keypoints"] = {k: (_coverage(fn, kp[k]) if k in kp_channels or k == "live" else None) for k in kp}
    return out


def folder_summary(stats: list[dict[str, Any]], metadata: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """Totals over several files' :func:`episode_stats`; with their metadata, also the frames dropped between
    consecutive episodes of the same run (by frame number)."""
    frames = sum(s["frames"] for s in stats)

    def total(key: str) -> int:
        return int(sum(s.get(key) or 0 for s in stats))

    def weighted(key: str) -> float | None:
        vals = [(s[key], s["frames"]) for s in stats if s.get(key)]
        n = sum(w for _, w in vals)
        return float(sum(v * w for v, w in vals) / n) if n else None

    out: dict[str, Any] = {
        "files": len(stats), "frames": frames, "frame_drops": total("frame_drops"), "frame_gaps": total("frame_gaps"),
        "camera_fps": weighted("camera_fps"),
        "camera_fps_min": min((s["camera_fps"] for s in stats if s.get("camera_fps")), default=None),
        "max_frame_interval_ms": max((s["max_frame_interval_ms"] for s in stats if s.get("max_frame_interval_ms")),
                                     default=None),
        "joint_states": total("joint_states"), "joint_state_hz": weighted("joint_state_hz"),
        "joint_state_gaps": total("joint_state_gaps"),
    }
    for kind in ("live", "final"):
        have = [s["keypoints"][kind] for s in stats if s["keypoints"].get(kind) is not None]
        out[f"{kind}_keypoint_files"] = len(have)
        out[f"{kind}_keypoint_coverage"] = (sum(h["frames"] for h in have) / frames) if frames else 0.0
    if metadata is not None:
        run = ("session_started", "object", "program", "speed", "repeat", "attempt", "plan_pass")
        between = 0
        pairs = list(zip(stats, metadata, strict=True))
        for (a, ma), (b, mb) in zip(pairs, pairs[1:], strict=False):
            next_chunk = mb.get("chunk_index") == (ma.get("chunk_index") or 0) + 1
            same = next_chunk and all(ma.get(k) == mb.get(k) for k in run)
            if same and a["last_frame"] is not None and b["first_frame"] is not None:
                between += max(0, b["first_frame"] - a["last_frame"] - 1)
        out["frame_drops_between_episodes"] = between
    return out


def _fmt(v: float | None, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def format_stats(s: dict[str, Any]) -> list[str]:
    """The human lines of one file's stats."""
    lines = [
        f"  camera     {s['frames']} frames, {_fmt(s['camera_fps'], '.2f')} fps measured (host clock "
        f"{_fmt(s['camera_fps_host'], '.2f')}), {s['frame_drops']} dropped, {s['frame_gaps']} gap(s), "
        f"longest interval {_fmt(s['max_frame_interval_ms'], '.1f')} ms",
        f"  joints     {s['joint_states']} states, {_fmt(s['joint_state_hz'], '.1f')} Hz, {s['joint_state_gaps']} "
        f"gap(s), longest interval {_fmt(s['max_joint_state_interval_ms'], '.1f')} ms",
    ]
    parts = []
    for kind in ("live", "final"):
        c = s["keypoints"].get(kind)
        if c is None:
            parts.append(f"{kind} none")
        else:
            parts.append(f"{kind} {c['frames']}/{s['frames']} frames ({100 * c['coverage']:.1f} %"
                         + (f", longest gap {c['longest_gap_frames']} frames)" if c["longest_gap_frames"] else ")"))
    lines.append("  keypoints  " + "; ".join(parts))
    return lines


def format_summary(t: dict[str, Any]) -> str:
    """The human lines of :func:`folder_summary`."""
    lines = [
        f"summary: {t['files']} file(s), {t['frames']} frames, camera {_fmt(t['camera_fps'], '.2f')} fps "
        f"(lowest {_fmt(t['camera_fps_min'], '.2f')}), {t['frame_drops']} dropped in files"
        + (f" + {t['frame_drops_between_episodes']} between episodes" if "frame_drops_between_episodes" in t else "")
        + f", {t['frame_gaps']} gap(s), longest interval {_fmt(t['max_frame_interval_ms'], '.1f')} ms",
        f"  joints     {t['joint_states']} states, {_fmt(t['joint_state_hz'], '.1f')} Hz, "
        f"{t['joint_state_gaps']} gap(s)",
        f"  keypoints  live {100 * t['live_keypoint_coverage']:.1f} % of frames; final "
        f"{100 * t['final_keypoint_coverage']:.1f} % ({t['final_keypoint_files']} of {t['files']} file(s) have them)",
    ]
    return "\n".join(lines)


def pipe_safe(func: Callable[[Any], int]) -> Callable[[Any], int]:
    """Wrap a command so that output piped into ``head`` (the reader closing early) ends it quietly, rc 0."""

    def run(args: Any) -> int:  # noqa: ANN401 - argparse.Namespace
        try:
            rc = func(args)
            sys.stdout.flush()
            return rc
        except BrokenPipeError:
            devnull = os.open(os.devnull, os.O_WRONLY)  # the interpreter flushes stdout at exit: let it go nowhere
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
            return 0

    return run
