"""Final keypoints for every frame: after a run, its recorded frames are tracked offline and stored per episode.

A run's episode files are tracked as one clip by the same pipeline as ``trackdeform track``
(:func:`orchestrator.cli_tracking.track_sequence`: forward pass, then the frames before initialisation
backwards from it), smoothed with the paper's symmetric moving average (``tracking.final_window`` frames,
over the whole run), and each episode file is rewritten atomically (``episode_NNNNNN.mcap.final-tmp``,
fsynced, renamed over the original) with every record copied verbatim plus two channels:

- ``/keypoints/final``  JSON Schema ``trackdeform.Keypoints`` (tdrecord.channels), one message per frame at
  the frame's log time: ``frame_number``, ``stamp`` (s, the frame's device stamp), ``keypoints`` [{x,y,z}] m
  world, ``edges`` [{i,j}], ``rest_lengths`` m, ``grasp_indices`` {left,right}, ``object``, ``category``,
  ``status`` "final", ``window``, ``tangled`` (the frame's tangled grid cells or keypoints where a chain turns
  back on itself, ``tracking.tangle.clip_tangles``: 0 for a good frame; such a frame is flagged, not hidden);
- ``/keypoints/final/scene``  foxglove.SceneUpdate: the same as spheres and edge lines (entity
  ``keypoints_final``);

and the ``episode`` metadata gains ``keypoints: ["live", "final"]`` and ``final_keypoints: {tracker, params,
window, created, frames, tangled_frames, run_files, software}``.

The work runs in a child process at nice 10 (:class:`FinalTracker`, one run at a time, ``python -m
orchestrator.final`` reading its job as JSON on stdin and printing its result as the last line of stdout), so
the capture loop never waits for it; the session journals a ``final`` record per run when it is done.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator.fsutil import fsync_dir
from orchestrator.procutil import popen_nice

log = logging.getLogger(__name__)

TMP_SUFFIX = ".final-tmp"
LOCK_NAME = "final.lock"
TRACKER_NAME = "trackdeform3d offline (forward + backward fill, symmetric moving average)"


# ---------------------------------------------------------------------- tracking one run
@dataclass
class FinalKeypoints:
    """The final keypoints of one run. keypoints: (T, N, 3) m world; grasp: (T, 2) int64 (-1 none);
    frame_numbers: (T,); edges (E, 2); rest (E,) m; files: the run's episodes in order with frames_per_file
    their frame counts."""

    keypoints: np.ndarray
    grasp: np.ndarray
    frame_numbers: np.ndarray
    edges: np.ndarray
    rest: np.ndarray
    files: list[Path]
    frames_per_file: list[int]
    object: str
    category: str
    window: int
    params: dict[str, Any]
    metrics: dict[str, Any] = field(default_factory=dict)
    tangled: np.ndarray | None = None  # (T,) int64 each frame's tangled cells / turned-back keypoints, 0: none


def track_run(files: list[Path], tracking: Any) -> FinalKeypoints:  # noqa: ANN401 - TrackingConfig
    """Track one run's episode files (in order) as one clip and smooth it; RuntimeError when never initialised."""
    from orchestrator.cli_tracking import track_sequence
    from orchestrator.worker import tracking_params
    from tdcommon.objects import DIMENSION
    from tdrecord import read_episodes
    from tracking.tangle import clip_tangles
    from tracking.tracker import final_keypoints

    seq = read_episodes(list(files))
    category = str(seq.metadata.get("category") or "")
    params = tracking_params(tracking, category or None, seq.metadata.get("n_keypoints"))
    result = track_sequence(seq, params, DIMENSION.get(category), progress=False)
    raw, topo = result["raw"], result["topology"]
    final = final_keypoints(raw, topo, params)
    tangled = clip_tangles(final, topo, params.fold_cos)
    grasp = np.full((len(raw), 2), -1, dtype=np.int64)
    for i, g in enumerate(result.get("grasp") or []):
        if g is not None and len(g):
            grasp[i, : min(2, len(g))] = np.asarray(g, dtype=np.int64)[:2]
    return FinalKeypoints(
        keypoints=final, grasp=grasp, frame_numbers=np.asarray(seq.frame_numbers),
        edges=np.asarray(topo.edges, dtype=np.int64), rest=np.asarray(topo.reference_lengths, dtype=np.float64),
        files=[Path(f) for f in files], frames_per_file=list(seq.metadata["frames_per_file"]),
        object=str(seq.metadata.get("object") or ""), category=category, window=int(params.symmetric_window),
        params=_jsonable(asdict(params)), metrics=_jsonable(result["metrics"]), tangled=tangled,
    )


def _jsonable(obj: Any) -> Any:  # noqa: ANN401 - any value
    """Numpy scalars / arrays and tuples as plain JSON values."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


# ---------------------------------------------------------------------- rewriting one episode file
def final_message(fk: FinalKeypoints, i: int, stamp: float) -> dict[str, Any]:
    """The ``/keypoints/final`` message of frame ``i`` of the run (points as nested lists, as live ones are);
    stamp: the frame's device stamp, s."""
    return {
        "schema": "trackdeform.Keypoints/1", "frame_number": int(fk.frame_numbers[i]), "stamp": float(stamp),
        "keypoints": np.round(fk.keypoints[i], 6).tolist(),
        "edges": fk.edges.tolist(), "rest_lengths": np.round(fk.rest, 6).tolist(),
        "grasp_indices": {"left": int(fk.grasp[i, 0]), "right": int(fk.grasp[i, 1])},
        "object": fk.object, "category": fk.category, "status": "final", "window": fk.window,
        "tangled": 0 if fk.tangled is None else int(fk.tangled[i]),
    }


def rewrite_episode(path: Path, fk: FinalKeypoints, meta_update: dict[str, Any]) -> int:
    """Rewrite ``path`` with the final keypoints of its frames added; returns how many frames got them.

    Every record of the original is copied verbatim (message bytes, log and publish times, sequence numbers;
    schemas, channels, attachments, metadata) except an earlier run's ``/keypoints/final*`` channels, which are
    replaced. The new file is ``<name>.final-tmp``, fsynced and renamed over the original: a crash leaves
    either the original or the new file, never a mix.
    """
    path = Path(path)
    by_frame = {int(n): i for i, n in enumerate(fk.frame_numbers.tolist())}
    tmp = path.with_name(path.name + TMP_SUFFIX)
    try:
        written = _copy_with_final(path, tmp, fk, meta_update, by_frame)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)
    return written


def _copy_with_final(path: Path, tmp: Path, fk: FinalKeypoints, meta_update: dict[str, Any],
                     by_frame: dict[int, int]) -> int:
    """The copy of :func:`rewrite_episode` into ``tmp`` (fsynced); returns the frames given final keypoints."""
    from foxglove_schemas_protobuf.Color_pb2 import Color
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer
    from mcap_protobuf.schema import build_file_descriptor_set

    from orchestrator.recorder import _finite_or_null, _scene_update
    from tdrecord.api import FINAL_SCENE_TOPIC, FINAL_TOPIC
    from tdrecord.channels import SCHEMAS, keypoints_record

    written = 0
    with open(path, "rb") as src, open(tmp, "wb") as out:
        w = Writer(out, compression=CompressionType.ZSTD, chunk_size=4 << 20)
        schemas: dict[int, int] = {}  # original id -> new id
        schema_recs: dict[int, Schema] = {}
        channels: dict[int, int] = {}
        skip: set[int] = set()
        frame_info: set[int] = set()  # original channel ids of /cam/<id>/frame_info
        final_ids: tuple[int, int] | None = None
        started = False

        def final_channels() -> tuple[int, int]:
            """Register the two final channels (once, after the original ones), reusing identical schemas."""
            kp_data = json.dumps(SCHEMAS["trackdeform.Keypoints"]).encode()
            kp_sid = next((schemas[i] for i, s in schema_recs.items()
                           if s.name == "trackdeform.Keypoints" and s.encoding == "jsonschema" and s.data == kp_data),
                          None)
            if kp_sid is None:
                kp_sid = w.register_schema("trackdeform.Keypoints", "jsonschema", kp_data)
            sc_sid = next((schemas[i] for i, s in schema_recs.items()
                           if s.name == "foxglove.SceneUpdate" and s.encoding == "protobuf"), None)
            if sc_sid is None:
                fds = build_file_descriptor_set(SceneUpdate).SerializeToString()
                sc_sid = w.register_schema("foxglove.SceneUpdate", "protobuf", fds)
            return w.register_channel(FINAL_TOPIC, "json", kp_sid), w.register_channel(FINAL_SCENE_TOPIC, "protobuf",
                                                                                       sc_sid)

        seq = 0
        for rec in StreamReader(src, skip_magic=False).records:
            if isinstance(rec, Header):
                w.start(profile=rec.profile, library=rec.library)
                started = True
            elif isinstance(rec, Schema):
                if rec.id not in schemas:
                    schemas[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                    schema_recs[rec.id] = rec
            elif isinstance(rec, Channel):
                if rec.id in channels or rec.id in skip:
                    continue
                if rec.topic in (FINAL_TOPIC, FINAL_SCENE_TOPIC):
                    skip.add(rec.id)
                    continue
                channels[rec.id] = w.register_channel(rec.topic, rec.message_encoding, schemas.get(rec.schema_id, 0),
                                                      dict(rec.metadata))
                if rec.topic.startswith("/cam/") and rec.topic.endswith("/frame_info"):
                    frame_info.add(rec.id)
            elif isinstance(rec, Message):
                if rec.channel_id in skip:
                    continue
                w.add_message(channels[rec.channel_id], rec.log_time, rec.data, rec.publish_time, rec.sequence)
                if rec.channel_id not in frame_info:
                    continue
                info = json.loads(rec.data)
                i = by_frame.get(int(info.get("frame_number", -1)))
                if i is None or not np.isfinite(fk.keypoints[i]).all():
                    continue
                if final_ids is None:
                    final_ids = final_channels()
                msg = final_message(fk, i, float(info.get("device_stamp", rec.log_time * 1e-9)))
                text = json.dumps(_finite_or_null(keypoints_record(msg)), separators=(",", ":"), allow_nan=False)
                w.add_message(final_ids[0], rec.log_time, text.encode(), rec.log_time, seq)
                scene = _scene_update(SceneUpdate, msg, rec.log_time * 1e-9)
                for ent in scene.entities:
                    ent.id = "keypoints_final"
                    for s in ent.spheres:
                        s.color.CopyFrom(Color(r=1.0, g=0.3, b=0.8, a=1.0))
                w.add_message(final_ids[1], rec.log_time, scene.SerializeToString(), rec.log_time, seq)
                seq += 1
                written += 1
            elif isinstance(rec, Attachment):
                w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            elif isinstance(rec, Metadata):
                data = dict(rec.metadata)
                if rec.name == "episode":
                    data.update({k: json.dumps(v) for k, v in meta_update.items()})
                w.add_metadata(rec.name, data)
        if not started:
            raise ValueError(f"{path}: no MCAP header")
        w.finish()
        out.flush()
        os.fsync(out.fileno())
    return written


def finalize_run(files: list[Path], tracking: Any, software: str = "") -> dict[str, Any]:  # noqa: ANN401
    """Track one run and rewrite each of its episodes; the result the journal's ``final`` record holds.

    Holds an exclusive lock on the folder's ``final.lock`` throughout, so two finalisers (a session and an
    orphan of a killed one) never write the same ``.final-tmp``; the second waits, then redoes the run.
    """
    import fcntl

    files = [Path(f) for f in files]
    if not files:
        return {"status": "failed", "reason": "no episode files", "episodes": [], "frames": 0, "frames_with_final": 0}
    with open(files[0].parent / LOCK_NAME, "a") as lock:
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        return _finalize_locked(files, tracking, software)


def _finalize_locked(files: list[Path], tracking: Any, software: str) -> dict[str, Any]:  # noqa: ANN401
    """:func:`finalize_run` under the folder's lock."""
    t0 = time.monotonic()
    for f in files:  # a crash mid-rewrite left these; the originals are intact
        stale = f.with_name(f.name + TMP_SUFFIX)
        if stale.exists():
            stale.unlink()
    try:
        fk = track_run(files, tracking)
    except RuntimeError as e:
        return {"status": "failed", "reason": str(e), "episodes": [f.name for f in files], "frames": 0,
                "frames_with_final": 0, "seconds": round(time.monotonic() - t0, 2)}
    created = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    n_tangled = 0 if fk.tangled is None else int((fk.tangled > 0).sum())
    info = {"tracker": TRACKER_NAME, "params": fk.params, "window": fk.window, "created": created,
            "frames": len(fk.keypoints), "tangled_frames": n_tangled, "run_files": [f.name for f in files],
            "software": software}
    done = 0
    offsets = np.concatenate([[0], np.cumsum(fk.frames_per_file)]).astype(int)
    per_file = []
    for k, f in enumerate(files):
        n = rewrite_episode(f, fk, {"keypoints": ["live", "final"], "final_keypoints": info})
        per_file.append({"file": f.name, "frames": int(offsets[k + 1] - offsets[k]), "final": n})
        done += n
    return {"status": "done", "episodes": [f.name for f in files], "frames": int(offsets[-1]),
            "frames_with_final": done, "tangled_frames": n_tangled, "per_file": per_file, "window": fk.window,
            "created": created,
            "metrics": {k: v for k, v in fk.metrics.items() if k != "statuses"},
            "seconds": round(time.monotonic() - t0, 2)}


def main(argv: list[str] | None = None) -> int:
    """``python -m orchestrator.final``: a job ``{"files": [...], "tracking": {...}, "software": "..."}`` on stdin;
    the result as one JSON line on stdout (the last line)."""
    from orchestrator import __version__
    from orchestrator.config import TrackingConfig

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    job = json.loads(sys.stdin.read())
    tracking = TrackingConfig.model_validate(job.get("tracking") or {})
    try:
        result = finalize_run([Path(f) for f in job["files"]], tracking, job.get("software") or __version__)
    except Exception as e:  # reported to the session, which journals it; "error" is retried by the next session
        log.exception("final tracking of %s failed", job.get("files"))
        result = {"status": "error", "reason": f"{type(e).__name__}: {e}",
                  "episodes": [Path(f).name for f in job.get("files", [])], "frames": 0, "frames_with_final": 0}
    sys.stdout.write(json.dumps(result) + "\n")
    sys.stdout.flush()
    return 0 if result["status"] == "done" else 1


# ---------------------------------------------------------------------- the session's background worker
@dataclass
class FinalJob:
    """One run to finalise: its run key fields (object, program, speed, repeat, pass, attempt) and files."""

    run: dict[str, Any]
    files: list[Path]
    result: dict[str, Any] | None = None


class FinalTracker:
    """Finalises runs one at a time in a nice-10 child process, on a thread of the session.

    ``submit`` queues a run; ``poll`` returns the jobs finished since the last call (the session journals
    them); ``wait`` blocks until every queued job is done; ``stop`` terminates the running child and drops
    the queue (those runs have no ``final`` record, so the next session on the folder does them).
    """

    def __init__(self, out_dir: Path, tracking: Any, software: str = "") -> None:  # noqa: ANN401
        self.out_dir = Path(out_dir)
        self.tracking = tracking
        self.software = software
        self._q: queue.Queue[FinalJob | None] = queue.Queue()
        self._done: list[FinalJob] = []
        self._lock = threading.Lock()
        self._pending = 0
        self._idle = threading.Condition(self._lock)
        self._proc: subprocess.Popen | None = None
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="final-tracking", daemon=True)
        self._thread.start()

    @property
    def pending(self) -> int:
        """Jobs queued or running."""
        with self._lock:
            return self._pending

    def submit(self, run: dict[str, Any], files: Iterable[Path]) -> None:
        """Queue one run's finished episode files (in order)."""
        with self._lock:
            self._pending += 1
        self._q.put(FinalJob(dict(run), [Path(f) for f in files]))

    def poll(self) -> list[FinalJob]:
        """The jobs finished since the last call."""
        with self._lock:
            out, self._done = self._done, []
        return out

    def wait(self, timeout: float | None = None) -> bool:
        """Block until no job is queued or running (or ``timeout`` s); True when idle."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            while self._pending:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._idle.wait(left if left is not None else 1.0)
            return True

    def stop(self) -> int:
        """Terminate the running child (its files stay intact: rename-or-nothing), drop the queue; returns
        how many jobs were left undone."""
        with self._lock:
            self._stopped = True
            left = self._pending
            proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self._q.put(None)
        self._thread.join(15)
        return left

    def _run(self) -> None:
        while True:
            job = self._q.get()
            if job is None:
                return
            with self._lock:
                stopped = self._stopped
            if not stopped:
                job.result = self._execute(job)
            with self._lock:
                self._pending -= 1
                if not stopped and not self._stopped:
                    self._done.append(job)
                self._idle.notify_all()

    def _execute(self, job: FinalJob) -> dict[str, Any]:
        spec = {"files": [str(f) for f in job.files], "tracking": self.tracking.model_dump(mode="json"),
                "software": self.software}
        with open(self.out_dir / "final.log", "ab") as logf:
            try:
                proc = popen_nice([sys.executable, "-m", "orchestrator.final"], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, stderr=logf,
                                  start_new_session=True)  # signals reach the session, which stops this
            except OSError as e:
                return {"status": "error", "reason": f"could not start: {e}", "episodes": [f.name for f in job.files]}
            with self._lock:
                self._proc = proc
            stdout, _ = proc.communicate(json.dumps(spec).encode())
            with self._lock:
                self._proc = None
        lines = stdout.decode(errors="replace").strip().splitlines()
        try:
            return json.loads(lines[-1])
        except (IndexError, json.JSONDecodeError):
            return {"status": "error", "reason": f"the final-tracking process exited {proc.returncode} without a "
                    f"result (see {self.out_dir / 'final.log'})", "episodes": [f.name for f in job.files]}


def pending_runs(records: list[dict[str, Any]], out_dir: Path) -> list[tuple[dict[str, Any], list[Path]]]:
    """Runs of a journal whose episodes have no ``final`` record yet: (run key fields, existing files in order).

    A ``final`` record counts when its status is ``done`` or ``failed`` (the object was never initialised: doing
    it again gives the same); ``error`` (the process died, a disk error) is tried again.

    ``run`` records (done or failed) name their episodes; episodes a cut-short run left (a ``start`` without a
    ``run`` record) are found from the next ``start``'s ``first_episode`` (or the folder's last file).
    """
    finalised = {e for r in records if r.get("type") == "final" and r.get("status") in ("done", "failed")
                 for e in r.get("episodes", [])}
    runs: list[tuple[dict[str, Any], list[str]]] = []
    starts = [r for r in records if r.get("type") == "start"]
    named: set[str] = set()
    for r in records:
        if r.get("type") == "run" and r.get("episodes"):
            runs.append((r, list(r["episodes"])))
            named.update(r["episodes"])
    existing = sorted(p.name for p in Path(out_dir).glob("episode_*.mcap"))
    for k, s in enumerate(starts):  # a start's episodes: from its first_episode to the next start's
        first = s.get("first_episode")
        if not isinstance(first, int):
            continue
        nxt = next((t.get("first_episode") for t in starts[k + 1:] if isinstance(t.get("first_episode"), int)), None)
        names = [n for n in existing if first <= int(n.split("_")[1].split(".")[0]) < (nxt if nxt is not None
                                                                                          else 1 << 62)]
        orphans = [n for n in names if n not in named]
        if orphans and orphans == names:
            runs.append((s, orphans))
    out = []
    for r, names in runs:
        files = [Path(out_dir) / n for n in names if (Path(out_dir) / n).is_file()]
        if files and not all(f.name in finalised for f in files):
            keys = ("object", "program", "speed", "repeat", "pass", "attempt")
            out.append(({k: r.get(k) for k in keys}, files))
    return out


if __name__ == "__main__":
    sys.exit(main())
