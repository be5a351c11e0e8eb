"""``trackdeform retrack SESSION``: track a recorded session again with the current tracker, in parallel.

Each program run (its episodes in order, grouped by the episodes' run metadata) is one task, tracked like
``trackdeform track`` does (forward pass with one pipeline across the run's episodes, so the warm start
carries over; then the backward pass ``tracking.offline.fill_missing``; the paper's symmetric moving
average). Tasks run in local worker processes (spawn) or, with ``--ray-address``, as Ray tasks.

Results are a new keypoint *version* beside the episodes, which are only read::

    SESSION/keypoints/<version>/version.json           tracker version, tracking settings, created
    SESSION/keypoints/<version>/episode_NNNNNN.npz     one per episode (keys in NPZ_KEYS, and ``tangled``)
    SESSION/keypoints/<version>/retrack.jsonl          progress journal: one record per run tracked

Every file is written to a temporary name, fsynced and renamed, so a killed retrack leaves only whole
files; rerunning the same command skips the runs whose files are all present and complete.

One module (~650 lines) on purpose: the command, its local and Ray executors and the version files share
one task description and one set of resume rules.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator.fsutil import fsync_dir
from orchestrator.progress import Progress
from tracking.params import TrackingParams

VERSIONS_DIR = "keypoints"
VERSION_FILE = "version.json"
JOURNAL_FILE = "retrack.jsonl"
FORMAT = "trackdeform-keypoints/1"
NPZ_KEYS = ("frame_numbers", "keypoints", "raw", "edges", "rest_lengths", "grasp_indices", "episode_bytes")
VERSION_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,79}$")
PROGRESS_EVERY = 15  # frames between progress messages from a worker


class RetrackError(ValueError):
    """The session or the version folder cannot be used; the message names the path and the way out."""


@dataclass(frozen=True)
class RunTask:
    """One program run to track: its episode files in order, the object, and the tracking parameters.

    frames: the run's frame count from the episode metadata (0 where it does not say), for the progress bar.
    """

    index: int
    label: str
    episodes: tuple[str, ...]
    category: str | None
    params: TrackingParams
    frames: int = 0


# ---------------------------------------------------------------------- what to track
def _run_key(meta: dict[str, Any]) -> tuple:
    """A program run (one attempt of one pass) as the recorder names it in each episode's metadata."""
    return (meta.get("session_started"), meta.get("plan_pass", 0), meta.get("run_index"), meta.get("object"),
            meta.get("program"), meta.get("speed"), meta.get("repeat", 0), meta.get("attempt", 1))


def session_runs(session: Path, tracking: Any) -> list[RunTask]:
    """The session's episode files grouped into runs (in file order), each with its TrackingParams from the
    config's ``tracking`` section, the run's category and keypoint count (metadata)."""
    from orchestrator.worker import tracking_params
    from tdrecord import ACTIVE_SUFFIX, read_episode_metadata

    if not session.is_dir():
        raise RetrackError(f"{session}: no such session folder")
    files = sorted(session.glob("episode_*.mcap"))
    if not files:
        active = sorted(session.glob(f"*{ACTIVE_SUFFIX}"))
        hint = f" ({len(active)} unfinished: run `trackdeform recover {session}`)" if active else ""
        raise RetrackError(f"{session}: no episode_*.mcap files{hint}")
    groups: dict[tuple, list[tuple[Path, dict[str, Any]]]] = {}
    for f in files:
        try:
            meta = read_episode_metadata(f)
        except Exception as e:  # noqa: BLE001 - any unreadable file is named, not a traceback
            raise RetrackError(f"{f}: cannot read its 'episode' metadata ({type(e).__name__}: {e})") from e
        groups.setdefault(_run_key(meta), []).append((f, meta))
    tasks = []
    for i, members in enumerate(groups.values()):
        meta = members[0][1]
        category = meta.get("category")
        label = (f"{meta.get('object', '?')} · {meta.get('program', '?')} · {meta.get('speed', '?')} · "
                 f"#{int(meta.get('repeat', 0) or 0) + 1} (pass {meta.get('plan_pass', 0)}, "
                 f"attempt {meta.get('attempt', 1)}, from {members[0][0].stem})")
        tasks.append(RunTask(
            index=i, label=label, episodes=tuple(str(f) for f, _ in members), category=category,
            params=tracking_params(tracking, category, meta.get("n_keypoints")),
            frames=sum(int(m.get("n_frames") or 0) for _, m in members),
        ))
    return tasks


def concat_sequences(seqs: list[Any]) -> Any:
    """Episodes read one by one (``tdrecord.read_episodes`` per file) as one ``tdrecord.Sequence``, as reading
    their folder would give: per-frame arrays concatenated (NaN / False rows for a file without arm
    states), frames decoded lazily file after file; the calibration must agree."""
    from tdrecord import DatasetError, FrameSource, Sequence

    first = seqs[0]
    for s in seqs[1:]:
        if not (np.allclose(s.K, first.K) and np.allclose(s.T_world_cam, first.T_world_cam, atol=1e-9)):
            raise DatasetError(f"{s.source}: calibration (K or T_world_cam) differs from {first.source}")
    lengths = [len(s) for s in seqs]
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(int)

    def frames(start: int) -> Iterator[Any]:
        for k, s in enumerate(seqs):
            if start < offsets[k + 1]:
                yield from s.frames.iter_from(max(0, start - int(offsets[k])))

    def cat(name: str, fill: float | bool) -> np.ndarray | None:
        parts = [getattr(s, name) for s in seqs]
        like = next((p for p in parts if p is not None), None)
        if like is None:
            return None
        return np.concatenate([p if p is not None else np.full((n, *like.shape[1:]), fill, like.dtype)
                               for p, n in zip(parts, lengths, strict=True)])

    arrays: dict[str, Any] = {n: cat(n, np.nan) for n in ("q_left", "q_right", "tcp_left", "tcp_right", "stamps",
                                                           "gripper_width_left", "gripper_width_right")}
    arrays.update({n: cat(n, False) for n in ("grasped_left", "grasped_right")})
    arrays["frame_numbers"] = cat("frame_numbers", -1)
    gts = [g for s, n in zip(seqs, lengths, strict=True) for g in (s.ground_truth or [None] * n)]
    meta = dict(first.metadata)
    meta.update(files=[str(s.source) for s in seqs], frames_per_file=lengths,
                episodes=[s.metadata.get("episodes", [s.metadata])[0] for s in seqs])
    return Sequence(
        frames=FrameSource(frames, int(offsets[-1])), T_world_cam=first.T_world_cam, K=first.K, width=first.width,
        height=first.height, T_world_base=first.T_world_base,
        ground_truth=gts if any(g is not None for g in gts) else None, metadata=meta, source=first.source, **arrays,
    )


# ---------------------------------------------------------------------- one task
def track_run(task: RunTask, progress: Any = None) -> dict[str, Any]:
    """Track one run (in a worker process or a Ray task): returns per episode its name, frame_numbers (T,),
    final keypoints (T, N, 3) m (symmetric moving average over the whole run), raw (T, N, 3) m and grasp
    indices (T, 2) int64 (-1: none), with the run's edges (E, 2), rest lengths (E,) m and metrics.

    progress: a queue taking (task index, frames done) every PROGRESS_EVERY frames, or None.
    """
    from orchestrator.cli_tracking import track_sequence
    from tdcommon.objects import DIMENSION
    from tdrecord import read_episodes
    from tracking.tangle import clip_tangles
    from tracking.tracker import final_keypoints

    t0, c0 = time.monotonic(), time.process_time()
    seqs = [read_episodes(p) for p in task.episodes]
    seq = concat_sequences(seqs)

    def tick(i: int) -> None:
        if progress is not None and (i + 1) % PROGRESS_EVERY == 0:
            progress.put((task.index, i + 1))

    result = track_sequence(seq, task.params, DIMENSION.get(task.category or ""), progress=False, on_frame=tick)
    raw, topo = result["raw"], result["topology"]
    final = final_keypoints(raw, topo, task.params)
    tangled = clip_tangles(final, topo, task.params.fold_cos)
    grasp = np.full((len(raw), 2), -1, np.int64)
    for i, g in enumerate(result["grasp"]):
        if g is not None and len(g):
            grasp[i, : min(2, len(g))] = np.asarray(g, np.int64)[:2]
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in seqs])]).astype(int)
    episodes = []
    for k, s in enumerate(seqs):
        a, b = offsets[k], offsets[k + 1]
        episodes.append({"name": Path(s.source).name, "frame_numbers": np.asarray(s.frame_numbers, np.int64),
                         "keypoints": final[a:b], "raw": raw[a:b], "grasp_indices": grasp[a:b],
                         "tangled": tangled[a:b]})
    return {"episodes": episodes, "edges": np.asarray(topo.edges, np.int64),
            "rest_lengths": np.asarray(topo.reference_lengths), "metrics": result["metrics"],
            "frames": int(len(raw)), "wall_s": time.monotonic() - t0,
            "cpu_s": time.process_time() - c0}


# ---------------------------------------------------------------------- the version folder
def software_version() -> dict[str, Any]:
    """The tracker's version: the package version and, in a git checkout, ``git describe --always --dirty``."""
    import importlib.metadata

    try:
        package = importlib.metadata.version("trackdeform3d")
    except importlib.metadata.PackageNotFoundError:
        from orchestrator import __version__ as package
    describe = None
    try:
        r = subprocess.run(["git", "describe", "--always", "--dirty", "--tags"], capture_output=True, text=True,
                           timeout=10, cwd=Path(__file__).resolve().parent.parent)
        describe = (r.stdout.strip() or None) if r.returncode == 0 else None
    except (OSError, subprocess.TimeoutExpired):
        pass
    return {"package": package, "git": describe}


def default_version_name(software: dict[str, Any]) -> str:
    """``<package version>-<git describe>`` (or the package version alone): rerunning the same code resumes."""
    return "-".join(str(x) for x in (software["package"], software["git"]) if x)


def _write_atomic(path: Path, write: Any) -> None:
    """Write ``path`` through ``write(binary file)`` to a temporary name, fsync, rename over, fsync the folder."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


def open_version(session: Path, name: str, tracking: dict[str, Any], software: dict[str, Any]) -> Path:
    """The folder of version ``name`` (created with its version.json), or an error when it exists and was
    made with another tracker version or other tracking settings."""
    if not VERSION_NAME.match(name):
        raise RetrackError(f"--version {name!r}: use letters, digits and . _ + - (at most 80, not starting "
                           "with a punctuation mark)")
    folder = session / VERSIONS_DIR / name
    path = folder / VERSION_FILE
    if path.is_file():
        try:
            have = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise RetrackError(f"{path}: unreadable ({e}); move the folder aside or pick another --version") from e
        diff = [k for k in ("software", "tracking") if have.get(k) != {"software": software, "tracking": tracking}[k]]
        if diff:
            raise RetrackError(
                f"{folder}: made with another {' and '.join(diff)} ({', '.join(f'{k}: {have.get(k)}' for k in diff)}); "
                "pass another --version, or delete that folder to track it again"
            )
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    info = {"format": FORMAT, "version": name, "software": software, "tracking": tracking,
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "npz_keys": {"frame_numbers": "(T,) int64", "keypoints": "(T, N, 3) m world, symmetric moving average",
                         "raw": "(T, N, 3) m world, per-frame solve", "edges": "(E, 2) int64",
                         "rest_lengths": "(E,) m", "grasp_indices": "(T, 2) int64 left, right (-1: none)",
                         "episode_bytes": "size of the episode file tracked"}}
    _write_atomic(path, lambda f: f.write(json.dumps(info, indent=2).encode()))
    return folder


def read_complete_npz(path: Path, episode: Path) -> dict[str, np.ndarray] | None:
    """The arrays of ``path`` when it is a whole result for ``episode`` (every key, consistent shapes, made from
    an episode file of the same size: a recovered or re-recorded episode is tracked again), else None."""
    try:
        with np.load(path) as z:
            if not set(NPZ_KEYS) <= set(z.files):
                return None
            a = {k: z[k] for k in NPZ_KEYS}
        fn, kp, raw = a["frame_numbers"], a["keypoints"], a["raw"]
        whole = (kp.ndim == 3 and kp.shape == raw.shape and len(fn) == len(kp) == len(a["grasp_indices"])
                 and int(a["episode_bytes"]) == episode.stat().st_size)
    except (OSError, ValueError, KeyError, EOFError):
        return None
    except Exception:  # noqa: BLE001 - a torn zip raises zipfile.BadZipFile and others
        return None
    return a if whole else None


def npz_complete(path: Path, episode: Path) -> bool:
    """Whether ``path`` is a whole result for ``episode`` (``read_complete_npz``)."""
    return read_complete_npz(path, episode) is not None


def run_done(folder: Path, task: RunTask) -> bool:
    """Whether every episode of the run has a complete result in the version folder."""
    return all(npz_complete(folder / (Path(e).stem + ".npz"), Path(e)) for e in task.episodes)


def write_result(folder: Path, task: RunTask, result: dict[str, Any]) -> list[str]:
    """Write the run's per-episode npz files atomically; returns their names."""
    names = []
    for ep_path, ep in zip(task.episodes, result["episodes"], strict=True):
        arrays = {"frame_numbers": ep["frame_numbers"], "keypoints": ep["keypoints"], "raw": ep["raw"],
                  "edges": result["edges"], "rest_lengths": result["rest_lengths"],
                  "grasp_indices": ep["grasp_indices"], "episode_bytes": np.int64(Path(ep_path).stat().st_size),
                  "tangled": ep["tangled"]}
        out = folder / (Path(ep_path).stem + ".npz")
        _write_atomic(out, lambda f, a=arrays: np.savez_compressed(f, **a))
        names.append(out.name)
    return names


def _append(journal: Path, record: dict[str, Any]) -> None:
    """One JSON line, written with one write() and fsynced (a torn last line is skipped when read)."""
    with open(journal, "a") as f:
        f.write(json.dumps(record, default=str) + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_progress_journal(path: Path) -> list[dict[str, Any]]:
    """The records of a retrack.jsonl (lines that do not parse, e.g. torn by a kill, are skipped)."""
    out = []
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return out


# ---------------------------------------------------------------------- running the tasks
def _thread_env(workers: int) -> dict[str, str]:
    """Numeric-library thread counts so ``workers`` processes share the cores instead of oversubscribing."""
    n = str(max(1, (os.cpu_count() or 1) // max(1, workers)))
    return {k: os.environ.get(k, n) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def _ignore_sigint() -> None:
    """In worker and manager processes: Ctrl-C is the parent's to handle (it ends them)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


class _LocalBackend:
    """Worker processes (spawn context): one task per run, progress through a manager queue."""

    name = "local"

    def __init__(self, workers: int) -> None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing.managers import SyncManager

        ctx = multiprocessing.get_context("spawn")
        os.environ.update(_thread_env(workers))  # inherited by the spawned workers
        self.manager = SyncManager(ctx=ctx)
        self.manager.start(_ignore_sigint)  # Ctrl-C reaches the whole process group: only this process acts on it
        self.queue = self.manager.Queue()
        self.pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_ignore_sigint)
        self.workers = workers

    def submit(self, task: RunTask) -> Any:
        return self.pool.submit(track_run, task, self.queue)

    def wait(self, pending: list[Any], timeout: float) -> list[tuple[Any, Any, BaseException | None]]:
        from concurrent.futures import FIRST_COMPLETED, wait

        done, _ = wait(pending, timeout=timeout, return_when=FIRST_COMPLETED)
        return [(f, None if f.exception() else f.result(), f.exception()) for f in done]

    def progress(self) -> list[tuple[int, int]]:
        import queue

        items = []
        while True:
            try:
                items.append(self.queue.get_nowait())
            except (queue.Empty, EOFError, OSError):
                return items

    def close(self, cancel: bool = False) -> None:
        """Wait for the workers; with ``cancel`` (Ctrl-C) drop the queued runs and end the running ones."""
        procs = list((getattr(self.pool, "_processes", None) or {}).values()) if cancel else []
        self.pool.shutdown(wait=not cancel, cancel_futures=cancel)
        for p in procs:  # the pool's own worker processes (its runs are tracked again on the next retrack)
            p.terminate()
        for p in procs:
            p.join(10)
        self.manager.shutdown()


class _RayBackend:
    """Ray tasks (one CPU each) on the cluster at ``address``: ``auto``, ``ray://host:port``, ``host:port``,
    or ``local`` for a one-machine cluster started here (``ray.init()``). The workers must be able to import
    this package and to read the session folder at the same path (a shared file system)."""

    name = "ray"

    def __init__(self, address: str, workers: int | None) -> None:
        try:
            import ray
            from ray.util.queue import Queue
        except ModuleNotFoundError as e:
            raise RetrackError("--ray-address needs Ray: pip install 'trackdeform3d[cluster]'") from e
        self.ray = ray
        env = _thread_env(workers or 1)
        if address == "local":
            os.environ.update(env)  # the local raylet and its workers inherit it
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, runtime_env={"env_vars": env}, log_to_driver=False)
        self.queue = Queue()
        self.remote = ray.remote(num_cpus=1, max_retries=0)(track_run)
        self.workers = int(ray.cluster_resources().get("CPU", 1))

    def submit(self, task: RunTask) -> Any:
        return self.remote.remote(task, self.queue)

    def wait(self, pending: list[Any], timeout: float) -> list[tuple[Any, Any, BaseException | None]]:
        ready, _ = self.ray.wait(pending, num_returns=1, timeout=timeout)
        out = []
        for ref in ready:
            try:
                out.append((ref, self.ray.get(ref), None))
            except self.ray.exceptions.RayTaskError as e:  # the task raised: report its own exception
                cause = getattr(e, "cause", None)
                out.append((ref, None, cause if isinstance(cause, BaseException) else e))
            except self.ray.exceptions.RayError as e:  # the worker died, the task was cancelled, ...
                out.append((ref, None, e))
        return out

    def progress(self) -> list[tuple[int, int]]:
        items = []
        while not self.queue.empty():
            try:
                items.append(self.queue.get_nowait())
            except Exception:  # noqa: BLE001 - ray.util.queue.Empty
                break
        return items

    def close(self, cancel: bool = False) -> None:
        self.queue.shutdown()
        self.ray.shutdown()


@dataclass
class RetrackSummary:
    """What a retrack did: runs tracked now, already done before, failed (label -> reason); frames tracked now,
    wall time s (the whole call, and from the first task submitted to the last result), the tasks' CPU s."""

    folder: Path
    version: str
    backend: str
    workers: int
    runs: int
    tracked: int
    already_done: int
    failed: dict[str, str]
    frames: int
    wall_s: float
    tracking_s: float
    cpu_s: float = 0.0


def _bar(done: int, total: int, width: int = 24) -> str:
    n = int(round(width * min(done, total) / max(1, total)))
    return "[" + "#" * n + "-" * (width - n) + "]"


def retrack(
    session: Path,
    config: Any,
    *,
    version: str | None = None,
    workers: int = 2,
    ray_address: str | None = None,
    progress: Progress | None = None,
) -> RetrackSummary:
    """Track every run of ``session`` not yet done in version ``version`` (default: the tracker's version) and
    write the results beside the episodes (see the module docstring)."""
    t_start = time.monotonic()
    session = Path(session)
    progress = progress or Progress()
    software = software_version()
    name = version or default_version_name(software)
    tracking = config.tracking.model_dump(mode="json")
    tasks = session_runs(session, config.tracking)
    from tdrecord import ACTIVE_SUFFIX

    for a in sorted(session.glob(f"*{ACTIVE_SUFFIX}")):
        print(f"warning: {a.name}: unfinished episode skipped (run `trackdeform recover {session}` first)",
              file=sys.stderr)
    folder = open_version(session, name, tracking, software)
    journal = folder / JOURNAL_FILE
    todo = [t for t in tasks if not run_done(folder, t)]
    if len(todo) < len(tasks):
        progress.message(f"resuming {folder}: {len(tasks) - len(todo)} of {len(tasks)} runs already done")
    summary = RetrackSummary(folder, name, "ray" if ray_address else "local", workers, len(tasks), 0,
                             len(tasks) - len(todo), {}, 0, 0.0, 0.0)
    if not todo:
        summary.wall_s = time.monotonic() - t_start
        return summary
    backend: _LocalBackend | _RayBackend = (_RayBackend(ray_address, workers) if ray_address
                                            else _LocalBackend(max(1, workers)))
    summary.workers = backend.workers
    _append(journal, {"type": "start", "version": name, "backend": backend.name, "workers": backend.workers,
                      "runs": len(tasks), "todo": len(todo), "software": software,
                      "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
    total = sum(t.frames for t in todo) or len(todo)
    seen: dict[int, int] = {}
    finished_frames = 0
    t_track = time.monotonic()
    # longest runs first: the last task to finish is a short one, so the workers stay busy
    handles = {backend.submit(t): t for t in sorted(todo, key=lambda t: -t.frames)}
    pending = list(handles)
    cancelled = False
    try:
        while pending:
            for ref, result, error in backend.wait(pending, 0.25):
                pending.remove(ref)
                task = handles[ref]
                seen.pop(task.index, None)
                record: dict[str, Any] = {"type": "run", "run": task.label, "index": task.index,
                                          "episodes": [Path(e).name for e in task.episodes],
                                          "params": asdict(task.params)}
                if error is not None:
                    reason = f"{type(error).__name__}: {error}"
                    summary.failed[task.label] = reason
                    record.update(outcome="failed", reason=reason)
                    progress.message(f"failed: {task.label}: {reason}")
                else:
                    files = write_result(folder, task, result)
                    summary.tracked += 1
                    summary.frames += result["frames"]
                    summary.cpu_s += result["cpu_s"]
                    finished_frames += task.frames or result["frames"]
                    record.update(outcome="done", files=files, frames=result["frames"], metrics=result["metrics"],
                                  wall_s=round(result["wall_s"], 3), cpu_s=round(result["cpu_s"], 3))
                record["finished"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
                _append(journal, record)
            for index, n in backend.progress():
                seen[index] = max(seen.get(index, 0), n)
            done = finished_frames + sum(seen.values())
            elapsed = time.monotonic() - t_track
            rate = done / elapsed if elapsed > 0 else 0.0
            eta = f"{(total - done) / rate:.0f} s" if rate > 0 and done < total else "–"
            finished = summary.tracked + len(summary.failed)
            progress.update(f"retrack {_bar(done, total)} {done}/{total} frames | runs {finished}/{len(todo)}"
                            f"{f' ({len(summary.failed)} failed)' if summary.failed else ''} | {rate:.1f} frames/s"
                            f" | {backend.workers} {backend.name} worker(s) | ETA {eta}")
    except KeyboardInterrupt:
        cancelled = True
        progress.message(f"interrupted: {summary.tracked} run(s) written; rerun the same command to continue")
        raise
    finally:
        progress.done()
        backend.close(cancel=cancelled)
    summary.tracking_s = time.monotonic() - t_track
    summary.wall_s = time.monotonic() - t_start
    return summary


# ---------------------------------------------------------------------- reading versions (the report)
def list_versions(session: Path) -> list[str]:
    """The keypoint versions of a session, oldest first (by version.json's ``created``)."""
    root = Path(session) / VERSIONS_DIR
    found = []
    for v in root.glob(f"*/{VERSION_FILE}") if root.is_dir() else []:
        try:
            created = str(json.loads(v.read_text()).get("created", ""))
        except (OSError, json.JSONDecodeError):
            continue
        found.append((created, v.parent.name))
    return [n for _, n in sorted(found)]


def read_version(session: Path, version: str, episodes: list[Path]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """frame number -> (final (N, 3), raw (N, 3)) m of the episodes' files in a version; missing and incomplete
    files (a retrack killed mid-write, a disk that filled up: retrack tracks them again) are left out."""
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for e in episodes:
        path = Path(session) / VERSIONS_DIR / version / (Path(e).stem + ".npz")
        z = read_complete_npz(path, Path(session) / Path(e).name)
        if z is None:
            continue
        fn, kp, raw = z["frame_numbers"], z["keypoints"], z["raw"]
        out.update({int(n): (kp[i], raw[i]) for i, n in enumerate(fn)})
    return out


def mean_distance_mm(a: dict[int, np.ndarray], b: dict[int, np.ndarray]) -> tuple[float, int]:
    """Mean keypoint distance, mm, over the frames both have with the same keypoint count (and that count)."""
    common = [n for n in a if n in b and a[n].shape == b[n].shape]
    if not common:
        return float("nan"), 0
    A = np.stack([a[n] for n in common])
    B = np.stack([b[n] for n in common])
    d = np.linalg.norm(A - B, axis=-1)
    d = d[np.isfinite(d)]
    return (float(d.mean()) * 1e3 if len(d) else float("nan")), len(common)


def version_differences(session: Path, episodes: list[Path], live_frames: list[int],
                        live_keypoints: list[np.ndarray]) -> dict[str, Any]:
    """Per version of the session: the mean distance (mm) of its raw keypoints to the run's live keypoints
    (recorded /keypoints, raw too), and of its final keypoints to the previous version's; with frame counts."""
    versions = list_versions(session)
    live = dict(zip(live_frames, live_keypoints, strict=True))
    rows = []
    prev: dict[int, np.ndarray] | None = None
    for v in versions:
        data = read_version(session, v, episodes)
        final = {n: f for n, (f, _) in data.items()}
        raw = {n: r for n, (_, r) in data.items()}
        d_live, n_live = mean_distance_mm(raw, live) if live else (float("nan"), 0)
        d_prev, n_prev = mean_distance_mm(final, prev) if prev is not None else (float("nan"), 0)
        rows.append({"version": v, "frames": len(data), "vs_live_mm": d_live, "vs_live_frames": n_live,
                     "vs_previous_mm": d_prev, "vs_previous_frames": n_prev})
        prev = final
    return {"versions": versions, "rows": rows}


# ---------------------------------------------------------------------- CLI
def cmd_retrack(args: argparse.Namespace) -> int:
    """``trackdeform retrack SESSION [--workers N] [--ray-address ADDR] [--version NAME]``."""
    from orchestrator.config import DEFAULT_CONFIG, ConfigError, load_config
    from tdrecord import DatasetError

    try:
        config = load_config(args.config or DEFAULT_CONFIG)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.workers < 1:
        print(f"error: --workers {args.workers}: need at least 1", file=sys.stderr)
        return 2
    try:
        s = retrack(Path(args.session), config, version=args.version, workers=args.workers,
                    ray_address=args.ray_address, progress=Progress(enabled=not args.json))
    except (RetrackError, DatasetError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    fps = s.frames / s.tracking_s if s.tracking_s > 0 else 0.0
    figures = {"version": s.version, "folder": str(s.folder), "backend": s.backend, "workers": s.workers,
               "runs": s.runs, "tracked": s.tracked, "already_done": s.already_done, "failed": s.failed,
               "frames": s.frames, "tracking_s": round(s.tracking_s, 2), "wall_s": round(s.wall_s, 2),
               "cpu_s": round(s.cpu_s, 2),
               "frames_per_s": round(fps, 2)}
    if args.json:
        print(json.dumps(figures))
    else:
        print(f"{s.folder}: {s.tracked} run(s) tracked now, {s.already_done} already done, {len(s.failed)} failed"
              f"; {s.frames} frames in {s.tracking_s:.1f} s ({fps:.1f} frames/s, {s.workers} {s.backend} "
              f"worker(s))")
        for label, reason in s.failed.items():
            print(f"  failed: {label}: {reason}")
    return 1 if s.failed else 0


def register(sub: Any) -> None:
    """Add the ``retrack`` subcommand to the main parser."""
    p = sub.add_parser("retrack", help="track a recorded session again with the current tracker (parallel, "
                                       "resumable); results go to SESSION/keypoints/<version>/")
    p.add_argument("session", help="session folder (episode_*.mcap)")
    p.add_argument("--workers", type=int, default=2, help="local worker processes (default 2); with --ray-address "
                                                         "local: the local cluster's CPUs")
    p.add_argument("--ray-address", help="run the runs as Ray tasks: auto, HOST:PORT, ray://HOST:PORT, or local "
                                         "(a one-machine cluster started here); needs the 'cluster' extra")
    p.add_argument("--version", help="name of the keypoint version (default: <package version>-<git describe>); "
                                     "an existing one is resumed")
    p.add_argument("--config", help="tracking settings from this config (default: the mock config)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON (no progress bar)")
    p.set_defaults(func=cmd_retrack)
