"""``trackdeform export SESSION --format paper|lerobot --out DIR``: a session's episodes in other layouts.

- ``paper``: one folder per episode in the layout of the paper's published code (``rgbd.npz``, per-arm TCP
  pose files, ``calibration/transform_ee_cam_world.npz``, ``joint_states.npz``) with its keypoints as
  ``3d_keypoints.npz`` (mm); ``trackdeform track`` and the paper's code read it back.
- ``lerobot``: a LeRobot dataset (format v3.0) per object, written through LeRobot's own
  ``LeRobotDataset`` writer (the optional extra ``lerobot``): one LeRobot episode per program run,
  colour as a video feature, depth as a lossless 16-bit PNG image feature (mm), keypoints plus joint
  states and gripper widths as ``observation.state``, the arm input u_t as ``action``. The 5 s episode
  files a run was recorded in stay visible: the per-frame feature ``trackdeform.episode_file`` and
  ``meta/trackdeform.json`` (each LeRobot episode's source files, frame ranges, run and calibration).

The recorded episodes are only read: an export is made from final files, after the night.
Keypoints are the episode's final keypoints where it holds them, else the live ones.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator.progress import Progress, bar
from tdrecord import RecordedRun, Sequence, read_episodes, recorded_runs, write_paper_layout, write_reference_npz

LEROBOT_EXTRA = "pip install 'trackdeform3d[lerobot]'"
RUN_FIELDS = ("object", "category", "program", "speed", "repeat", "attempt", "plan_pass", "session_started")


class ExportError(ValueError):
    """A session cannot be exported as asked; the message names the file or folder and what is wrong."""


@dataclass
class EpisodeKeypoints:
    """Keypoints of one episode per frame: X (T, N, 3) m world (NaN where a frame has none), edges (E, 2),
    rest lengths (E,) m, grasp indices (T, 2) (-1 none), the arm input u_t per frame (T, 12) and which
    keypoints they are ("final" or "live")."""

    X: np.ndarray
    edges: np.ndarray
    rest: np.ndarray
    grasp: np.ndarray
    u: np.ndarray
    source: str


def episode_keypoints(path: Path) -> EpisodeKeypoints | None:
    """An episode's final keypoints where it holds them, else its live ones; None when it has neither."""
    from tdrecord import load_episode

    ep = load_episode(path, images=False)
    X = ep.keypoints
    if X.size == 0 or not np.isfinite(X).any():
        return None
    return EpisodeKeypoints(X, ep.edges, ep.rest_lengths, ep.grasp_indices, ep.u_frame,
                            "final" if ep.keypoints_final is not None else "live")


def _session_runs(session: Path) -> list[RecordedRun]:
    if not session.is_dir():
        raise ExportError(f"{session}: no such session folder")
    files = sorted(session.glob("episode_*.mcap"))
    if not files:
        raise ExportError(f"{session}: no finished episode files (episode_*.mcap)")
    runs = recorded_runs(files)
    bad = [r for r in runs if "unreadable" in r.first]
    if bad:
        raise ExportError(f"{bad[0].episodes[0]}: unreadable episode ({bad[0].first['unreadable']})")
    return runs


def _require_poses(seq: Sequence, path: Path) -> None:
    if seq.tcp_left is None or seq.tcp_right is None or seq.T_world_base is None:
        raise ExportError(f"{path}: no arm states or arm bases recorded: the paper's layout needs the TCP poses")


# ---------------------------------------------------------------------- paper layout
def export_paper(session: Path, out: Path, progress: Progress) -> list[Path]:
    """One paper-layout folder per episode under ``out`` (named like the episode); returns the folders."""
    runs = _session_runs(session)
    files = [f for r in runs for f in r.episodes]
    written = []
    for k, path in enumerate(files):
        progress.update(f"{bar(k, len(files))} | {path.name}", force=True)
        seq = read_episodes(path)
        _require_poses(seq, path)
        folder = out / path.name.removesuffix(".mcap")
        write_paper_layout(folder, seq.frames, T_world_cam=seq.T_world_cam, T_world_base=seq.T_world_base,
                           tcp_left=seq.tcp_left, tcp_right=seq.tcp_right, q_left=seq.q_left, q_right=seq.q_right,
                           K=seq.K)
        kp = episode_keypoints(path)
        if kp is not None:
            write_reference_npz(folder, kp.X, kp.edges, kp.rest)
        meta = {"source": str(path), "keypoints": kp.source if kp is not None else None,
                "episode": (seq.metadata.get("episodes") or [{}])[0]}
        (folder / "meta.json").write_text(json.dumps(meta, indent=2, default=str))
        written.append(folder)
    progress.update(f"{bar(len(files), len(files))} | done", force=True)
    progress.done()
    return written


# ---------------------------------------------------------------------- LeRobot
def _lerobot() -> Any:  # noqa: ANN401 - the optional module
    try:
        from lerobot.datasets.lerobot_dataset import LeRobotDataset
    except ImportError as e:
        raise ExportError(f"--format lerobot needs LeRobot ({e}); install it with: {LEROBOT_EXTRA}") from None
    return LeRobotDataset


def _state_names(n_keypoints: int) -> list[str]:
    kp = [f"keypoint{i}.{c}" for i in range(n_keypoints) for c in "xyz"]
    q = [f"{a}.q{j}" for a in ("left", "right") for j in range(1, 8)]
    return kp + q + ["left.gripper_width", "right.gripper_width"]


def _features(h: int, w: int, n_keypoints: int) -> dict[str, dict[str, Any]]:
    names = _state_names(n_keypoints)
    return {
        "observation.images.color": {"dtype": "video", "shape": (h, w, 3), "names": ["height", "width", "channels"]},
        "observation.depth": {"dtype": "image", "shape": (h, w, 1), "names": ["height", "width", "channels"]},
        "observation.state": {"dtype": "float32", "shape": (len(names),), "names": names},
        "action": {"dtype": "float32", "shape": (12,), "names": [
            f"{a}.tcp.{c}" for a in ("left", "right") for c in ("x", "y", "z", "rx", "ry", "rz")]},
        "trackdeform.episode_file": {"dtype": "int64", "shape": (1,), "names": None},
    }


def export_lerobot(session: Path, out: Path, progress: Progress, *, vcodec: str = "h264") -> list[Path]:
    """One LeRobot dataset per object under ``out/<object>``, one LeRobot episode per program run."""
    from PIL import Image

    LeRobotDataset = _lerobot()
    runs = _session_runs(session)
    by_object: dict[str, list[RecordedRun]] = {}
    for r in runs:
        by_object.setdefault(str(r.first.get("object", "object")), []).append(r)
    total = sum(len(r.episodes) for r in runs)
    done = 0
    roots = []
    for obj, obj_runs in by_object.items():
        root = out / obj
        if root.exists():
            raise ExportError(f"{root}: already exists; export into an empty --out folder")
        dataset = None
        sidecar: dict[str, Any] = {"format": "trackdeform-lerobot-export/1", "session": str(session), "episodes": []}
        n_kp = None
        for run in obj_runs:
            files_info = []
            frames_in_run = 0
            for k, path in enumerate(run.episodes):
                progress.update(f"{bar(done, total)} | {obj}: {path.name}", force=True)
                seq = read_episodes(path)
                kp = episode_keypoints(path)
                if kp is None:
                    raise ExportError(f"{path}: no keypoints recorded (run `trackdeform track` on the session first)")
                if n_kp is None:
                    n_kp = kp.X.shape[1]
                    dataset = LeRobotDataset.create(
                        repo_id=f"trackdeform/{obj}", fps=int(round(float(run.first.get("fps", 30)))),
                        features=_features(seq.height, seq.width, n_kp), root=root, use_videos=True, vcodec=vcodec,
                    )
                elif kp.X.shape[1] != n_kp:
                    raise ExportError(f"{path}: {kp.X.shape[1]} keypoints, the dataset of {obj} has {n_kp}")
                u = kp.u
                q = [seq.q_left, seq.q_right]
                widths = [seq.gripper_width_left, seq.gripper_width_right]
                task = f"{obj}: {run.first.get('program')} at {run.first.get('speed')} speed"
                for i, frame in enumerate(seq.frames):
                    state = np.concatenate([
                        kp.X[i].reshape(-1),
                        *(qa[i] if qa is not None else np.full(7, np.nan) for qa in q),
                        [wa[i] if wa is not None else np.nan for wa in widths],
                    ]).astype(np.float32)
                    dataset.add_frame({
                        "observation.images.color": frame.color,
                        "observation.depth": Image.fromarray(frame.depth_mm().astype(np.uint16)),
                        "observation.state": state,
                        "action": u[i].astype(np.float32),
                        "trackdeform.episode_file": np.array([k], dtype=np.int64),
                        "task": task,
                    })
                files_info.append({"file": path.name, "from_frame": frames_in_run,
                                   "to_frame": frames_in_run + len(seq), "keypoints": kp.source})
                frames_in_run += len(seq)
                done += 1
            dataset.save_episode()
            cal = run.first.get("calibration", {})
            sidecar["episodes"].append({
                "episode_index": len(sidecar["episodes"]),
                "run": {key: run.first.get(key) for key in RUN_FIELDS},
                "files": files_info, "calibration": cal,
            })
        if dataset is not None:
            dataset.finalize()
            (root / "meta" / "trackdeform.json").write_text(json.dumps(sidecar, indent=2, default=str))
            roots.append(root)
    progress.update(f"{bar(total, total)} | done", force=True)
    progress.done()
    return roots


# ---------------------------------------------------------------------- command
def cmd_export(args: argparse.Namespace) -> int:
    """Export a session; one line per dataset or folder written, errors as one line with rc 2."""
    session, out = Path(args.session), Path(args.out)
    progress = Progress(enabled=not args.quiet)
    try:
        if args.format == "paper":
            written = export_paper(session, out, progress)
        else:
            written = export_lerobot(session, out, progress, vcodec=args.vcodec)
    except ExportError as e:
        progress.done()
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"exported {len(written)} {'folders' if args.format == 'paper' else 'datasets'} to {out}")
    return 0


def register(sub: Any) -> None:
    """Add ``export`` to the main parser."""
    e = sub.add_parser("export", help="export a session's episodes to the paper's layout or a LeRobot dataset")
    e.add_argument("session", help="session folder (episode_*.mcap)")
    e.add_argument("--format", choices=("paper", "lerobot"), required=True)
    e.add_argument("--out", required=True, help="output folder")
    e.add_argument("--vcodec", default="h264", choices=("h264", "hevc", "libsvtav1"),
                   help="LeRobot video codec (default h264)")
    e.add_argument("--quiet", action="store_true", help="no progress bar")
    e.set_defaults(func=cmd_export)
