"""The reader API: one episode file as numpy arrays (:func:`load_episode`), a session folder walked through its
manifest (:func:`iter_episodes`).

A session folder holds ``episode_NNNNNN.mcap`` files and ``manifest.json`` (:data:`MANIFEST_NAME`), which the
session rewrites atomically as each episode lands: ``{"format": "trackdeform-manifest/1", "updated": ISO time,
"episodes": [entry, ...]}`` with one entry per finished file (:func:`manifest_entry`: the file name, its size
and a summary of its ``episode`` metadata). Without a manifest (or for files it does not list yet) the folder
is scanned and each file's metadata read.

Keypoints: ``/keypoints`` holds the live tracker's keypoints (frames it skipped have none) and, once the
session's final tracking has run, ``/keypoints/final`` (:data:`FINAL_TOPIC`) holds the offline, smoothed
keypoints of every frame; the episode metadata ``keypoints`` lists which of the two a file holds.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tdcommon.types import GroundTruth
from tdcommon.wire import edges_from_json, points_from_json
from tdrecord.episodes import ACTIVE_SUFFIX, _index_episode, _iter_episode_frames, read_episode_metadata
from tdrecord.sequence import DEPTH_SCALE_MM, DatasetError, nearest_index

log = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "trackdeform-manifest/1"
LIVE_TOPIC = "/keypoints"
FINAL_TOPIC = "/keypoints/final"
FINAL_SCENE_TOPIC = "/keypoints/final/scene"
ARMS = ("left", "right")
# episode metadata copied into a manifest entry (the filters of iter_episodes and what a listing shows)
MANIFEST_FIELDS = (
    "object", "category", "program", "speed", "repeat", "episode_index", "chunk_index", "attempt", "plan_pass",
    "session_started", "complete", "fault", "n_frames", "first_frame", "last_frame", "fps", "keypoints",
)


@dataclass
class Episode:
    """One episode file as arrays. T frames, S joint-state samples, N keypoints, E edges.

    colour: (T, H, W, 3) uint8 RGB, depth: (T, H, W) uint16 (× depth_scale m: mm), both None with images=False.
    log_times: (T,) int64 ns, the frames' MCAP log times; device_stamps / host_stamps: (T,) s on the camera and
    host clocks; frame_numbers: (T,) int64.
    state_stamps: (S,) s host clock; q / dq: arm -> (S, 7) rad, rad/s; u: (S, 12) the arm input (per arm TCP
    position m and rotation vector rad, world, left then right); gripper_width: arm -> (S,) m; grasped: arm ->
    (S,) bool. q_frame: arm -> (T, 7), u_frame: (T, 12): the sample nearest each frame's host stamp.
    keypoints_live: (T, N, 3) m world, NaN where the live tracker gave none; keypoints_final: (T, N, 3) or None
    when the episode has no final keypoints; edges: (E, 2) int64; rest_lengths: (E,) m (empty when unknown);
    grasp_indices: (T, 2) int64 keypoint held by the left / right gripper, -1 none (final where present, else
    live). K: (3, 3); T_world_cam: (4, 4); T_world_base: arm -> (4, 4) or None.
    """

    path: Path
    metadata: dict[str, Any]
    colour: np.ndarray | None
    depth: np.ndarray | None
    depth_scale: float
    log_times: np.ndarray
    device_stamps: np.ndarray
    host_stamps: np.ndarray
    frame_numbers: np.ndarray
    state_stamps: np.ndarray
    q: dict[str, np.ndarray]
    dq: dict[str, np.ndarray]
    u: np.ndarray
    gripper_width: dict[str, np.ndarray]
    grasped: dict[str, np.ndarray]
    q_frame: dict[str, np.ndarray]
    u_frame: np.ndarray
    keypoints_live: np.ndarray
    keypoints_final: np.ndarray | None
    edges: np.ndarray
    rest_lengths: np.ndarray
    grasp_indices: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    T_world_base: dict[str, np.ndarray] | None
    width: int
    height: int
    ground_truth: list[GroundTruth | None] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        """T."""
        return len(self.frame_numbers)

    @property
    def keypoints(self) -> np.ndarray:
        """The best keypoints the file holds: final (every frame) if present, else live (NaN gaps)."""
        return self.keypoints_final if self.keypoints_final is not None else self.keypoints_live


def _keypoint_frames(records: list[dict[str, Any]], frame_numbers: np.ndarray) -> tuple[
        np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Keypoint messages -> (T, N, 3) m (NaN for frames without), (T,) bool had keypoints, (T, 2) grasp indices,
    edges (E, 2) and rest lengths (E,), N being the most common non-zero keypoint count among the messages."""
    T = len(frame_numbers)
    pts = [(r, points_from_json(r.get("keypoints") or [])) for r in records]
    counts = Counter(len(p) for _, p in pts if len(p))
    N = counts.most_common(1)[0][0] if counts else 0
    out = np.full((T, N, 3), np.nan)
    have = np.zeros(T, dtype=bool)
    grasp = np.full((T, 2), -1, dtype=np.int64)
    row = {int(n): i for i, n in enumerate(frame_numbers.tolist())}
    edges = np.zeros((0, 2), dtype=np.int64)
    rest = np.zeros(0)
    for r, p in pts:
        i = row.get(int(r.get("frame_number", -1)))
        if i is None or len(p) != N or N == 0:
            continue
        out[i], have[i] = p, True
        g = r.get("grasp_indices") or {}
        grasp[i] = [int(g.get(a, -1)) for a in ARMS]
        if not len(edges) and r.get("edges"):
            edges = edges_from_json(r["edges"]).astype(np.int64).reshape(-1, 2)
        if not len(rest) and r.get("rest_lengths"):
            rest = np.asarray(r["rest_lengths"], dtype=np.float64)
    return out, have, grasp, edges, rest


def load_episode(path: str | Path, *, images: bool = True, camera_id: str | None = None) -> Episode:
    """Read one finished episode file into an :class:`Episode` (images decoded only with ``images``).

    Raises DatasetError for an unfinished (``.active``) or unreadable file, FileNotFoundError when missing.
    """
    from mcap.reader import make_reader

    path = Path(path)
    ep = _index_episode(path, camera_id)
    T, S = len(ep.times), len(ep.state_stamps)
    dq_rows: list[dict[str, Any]] = []
    live: list[dict[str, Any]] = []
    final: list[dict[str, Any]] = []
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic for c in summary.channels.values()} if summary is not None else set()
        wanted = [t for t in ("/arms/state", LIVE_TOPIC, FINAL_TOPIC) if t in topics]
        for _, channel, msg in reader.iter_messages(topics=wanted):
            d = json.loads(msg.data)
            {"/arms/state": dq_rows, LIVE_TOPIC: live, FINAL_TOPIC: final}[channel.topic].append(d)
    nan7 = [np.nan] * 7
    dq = {a: np.array([(s.get(a) or {}).get("dq") or nan7 for s in dq_rows], dtype=np.float64).reshape(-1, 7)
          for a in ARMS}
    if len(dq_rows) != S:  # both passes read the same channel in log-time order
        raise DatasetError(f"{path}: /arms/state read {S} then {len(dq_rows)} samples")
    kp_live, _, grasp_live, edges, rest = _keypoint_frames(live, ep.frame_numbers)
    kp_final = None
    grasp = grasp_live
    if final:
        kp_final, have, grasp_final, edges_f, rest_f = _keypoint_frames(final, ep.frame_numbers)
        if not have.all():
            log.warning("%s: %s has keypoints for %d of %d frames", path, FINAL_TOPIC, int(have.sum()), T)
        grasp = np.where(have[:, None], grasp_final, grasp_live)
        edges = edges_f if len(edges_f) else edges
        rest = rest_f if len(rest_f) else rest
    ok = np.isfinite(ep.state_stamps)
    if ok.any():
        idx = np.flatnonzero(ok)[nearest_index(ep.state_stamps[ok], ep.host_stamps)]
        q_frame = {a: ep.q[a][idx] for a in ARMS}
        u_frame = ep.u[idx]
    else:
        q_frame = {a: np.full((T, 7), np.nan) for a in ARMS}
        u_frame = np.full((T, 12), np.nan)
    colour = depth = None
    width, height = ep.width, ep.height
    if images:
        n = 0
        for i, frame in enumerate(_iter_episode_frames(ep)):
            if colour is None or depth is None:
                height, width = frame.depth.shape
                colour = np.empty((T, height, width, 3), dtype=np.uint8)
                depth = np.empty((T, height, width), dtype=np.uint16)
            colour[i], depth[i] = frame.color, frame.depth
            n = i + 1
        if n != T:
            raise DatasetError(f"{path}: decoded {n} of {T} frames")
    return Episode(
        path=path, metadata=ep.metadata, colour=colour, depth=depth, depth_scale=DEPTH_SCALE_MM,
        log_times=ep.times, device_stamps=ep.device_stamps, host_stamps=ep.host_stamps,
        frame_numbers=ep.frame_numbers, state_stamps=ep.state_stamps, q=ep.q, dq=dq, u=ep.u,
        gripper_width=ep.gripper_width, grasped=ep.grasped, q_frame=q_frame, u_frame=u_frame,
        keypoints_live=kp_live, keypoints_final=kp_final, edges=edges, rest_lengths=rest, grasp_indices=grasp,
        K=ep.K, T_world_cam=ep.T_world_cam, T_world_base=ep.T_world_base, width=width, height=height,
        ground_truth=ep.ground_truth,
    )


# ---------------------------------------------------------------------- manifest
def manifest_entry(path: Path, metadata: dict[str, Any] | None = None) -> dict[str, Any]:
    """The manifest entry of a finished episode file: ``file`` (name), ``bytes`` and :data:`MANIFEST_FIELDS`
    of its metadata (``keypoints`` defaults to ``["live"]`` for files written before final tracking)."""
    path = Path(path)
    meta = read_episode_metadata(path) if metadata is None else metadata
    entry: dict[str, Any] = {"file": path.name, "bytes": path.stat().st_size}
    entry.update({k: meta[k] for k in MANIFEST_FIELDS if k in meta})
    entry.setdefault("keypoints", ["live"])
    return entry


def read_manifest(folder: str | Path) -> list[dict[str, Any]] | None:
    """The entries of ``folder``'s manifest, or None when it has none. Raises DatasetError for a bad one."""
    path = Path(folder) / MANIFEST_NAME
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise DatasetError(f"{path}: unreadable manifest ({e}); delete it to scan the folder instead") from e
    episodes = data.get("episodes") if isinstance(data, dict) else None
    if not isinstance(episodes, list) or data.get("format") != MANIFEST_FORMAT:
        raise DatasetError(f"{path}: not a {MANIFEST_FORMAT} manifest (expected an object with 'format' and "
                           "'episodes'); delete it to scan the folder instead")
    return [e for e in episodes if isinstance(e, dict) and isinstance(e.get("file"), str)]


def episode_entries(folder: str | Path) -> list[dict[str, Any]]:
    """Every finished episode of a session folder as a manifest entry, in file-name order: the manifest's,
    plus those of files it does not list yet (their metadata read); listed files that are gone are dropped."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such session folder")
    listed = {e["file"]: e for e in (read_manifest(folder) or [])}
    out = []
    for p in sorted(folder.glob("episode_*.mcap")):
        entry = listed.get(p.name)
        if entry is None:
            try:
                entry = manifest_entry(p)
            except (ValueError, OSError) as e:
                log.warning("%s: skipped (%s)", p, e)
                continue
        out.append(entry)
    gone = set(listed) - {e["file"] for e in out}
    if gone:
        log.warning("%s: %d file(s) listed in the manifest are missing: %s", folder, len(gone), sorted(gone)[:5])
    return out


def _matches(value: Any, wanted: Any) -> bool:  # noqa: ANN401 - a JSON value and a filter
    if wanted is None:
        return True
    if isinstance(wanted, (list, tuple, set, frozenset)):
        return value in wanted
    return value == wanted


def iter_episodes(
    folder: str | Path,
    *,
    object: str | Iterable[str] | None = None,  # noqa: A002 - the metadata's name
    speed: str | Iterable[str] | None = None,
    program: str | Iterable[str] | None = None,
    category: str | Iterable[str] | None = None,
    complete: bool | None = None,
    keypoints: str | None = None,
    images: bool = True,
) -> Iterator[Episode]:
    """Load the episodes of a session folder that match every filter given, one at a time, in file order.

    A filter is a value or a collection of values of the episode metadata field of that name; ``keypoints``
    ("live" or "final") keeps episodes that hold that kind. Filters are applied to the manifest entries, so
    files that do not match are never opened. ``.active`` files (unfinished) are never listed.
    """
    filters = {"object": object, "speed": speed, "program": program, "category": category, "complete": complete}
    for f, v in filters.items():
        if isinstance(v, Iterable) and not isinstance(v, str):
            filters[f] = list(v)
    for entry in episode_entries(folder):
        if not all(_matches(entry.get(k), v) for k, v in filters.items()):
            continue
        if keypoints is not None and keypoints not in (entry.get("keypoints") or []):
            continue
        path = Path(folder) / entry["file"]
        if path.name.endswith(ACTIVE_SUFFIX):
            continue
        yield load_episode(path, images=images)
