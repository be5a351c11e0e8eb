"""The session journal: an append-only record of the plan position, so a session resumes where it stopped.

``<out>/session.journal.jsonl`` holds one JSON object a line: a ``header`` with the plan's
fingerprint, then ``session`` (a session started), ``start`` (a run item started), ``run`` (a
run item finished: done, failed or skipped) and ``live_init`` (an object's live initialisation before a
run: its attempts and outcome; not part of the plan position) records. Each line is written with one ``write()``
and fsynced before the session goes on, so a record that was written survives a SIGKILL or a
power cut; a torn last line (a crash mid-write) is ignored with a warning and cut off.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from orchestrator.config import Config
from orchestrator.fsutil import fsync_dir
from orchestrator.plan import RunItem, build_plan

log = logging.getLogger(__name__)

JOURNAL_NAME = "session.journal.jsonl"
FORMAT = "trackdeform-journal/1"
OUTCOMES = ("done", "failed", "skipped")

RunKey = tuple[str, str, str, int]  # object, program, speed, repeat: stable when the plan grows


class JournalError(ValueError):
    """A journal that cannot be used for this session; the message names the file and the way out."""


def run_key(item: RunItem) -> RunKey:
    """The identity of a run item across sessions (its list index changes when ``repeats`` changes)."""
    return (item.object.name, item.program, item.speed, item.repeat)


def key_fields(key: RunKey) -> dict[str, Any]:
    """A run key as the journal's record fields."""
    return {"object": key[0], "program": key[1], "speed": key[2], "repeat": key[3]}


def record_key(record: dict[str, Any]) -> RunKey:
    """The run key of a ``start`` or ``run`` record (KeyError / ValueError when it has none)."""
    return (str(record["object"]), str(record["program"]), str(record["speed"]), int(record["repeat"]))


def now_iso() -> str:
    """Wall-clock time now, UTC, ISO 8601 to the millisecond (journal and episode metadata)."""
    t = time.time()
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"


# ---------------------------------------------------------------------- plan fingerprint
def plan_description(config: Config) -> dict[str, Any]:
    """What makes a plan "the same plan": its ``plan`` section (without ``repeats``) and each program's bytes.

    ``repeats`` is left out on purpose: run items are keyed by (object, program, speed, repeat),
    which stay valid when the repeat count changes, so raising it collects more of the same plan.
    """
    from trajectories.program import ProgramError, resolve_program

    programs: dict[str, str] = {}
    for obj in config.plan.objects:
        for ref in obj.programs:
            try:
                programs[ref] = "sha256:" + hashlib.sha256(resolve_program(ref).read_bytes()).hexdigest()
            except (ProgramError, OSError):
                programs[ref] = "missing"  # the run fails (and is journaled) as it would without a journal
    return {"plan": config.plan.model_dump(mode="json", exclude={"repeats"}), "programs": programs}


def fingerprint(description: dict[str, Any]) -> str:
    """``sha256:<hex>`` of the canonical JSON of a plan description."""
    canonical = json.dumps(description, sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(canonical.encode()).hexdigest()


def _differences(a: Any, b: Any, path: str = "") -> list[str]:
    """Dotted paths where two JSON values differ (for the mismatch message)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for k in sorted(set(a) | set(b), key=str):
            out += _differences(a.get(k), b.get(k), f"{path}.{k}" if path else str(k))
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in _differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [path or "(everything)"]


# ---------------------------------------------------------------------- reading
@dataclass
class JournalContents:
    """A journal file as read: its header, its valid records and the byte length they take."""

    header: dict[str, Any] | None
    records: list[dict[str, Any]]
    valid_bytes: int
    torn_bytes: int = 0


def read_journal(path: Path) -> JournalContents:
    """Read a journal, skipping (with a warning) a torn last line and any line that is not a JSON object."""
    data = Path(path).read_bytes()
    end = data.rfind(b"\n") + 1  # bytes after the last newline are a line the writer did not finish
    torn = len(data) - end
    if torn:
        log.warning("%s: ignoring a torn last line (%d bytes; the session stopped while writing it)", path, torn)
    header: dict[str, Any] | None = None
    records: list[dict[str, Any]] = []
    for n, line in enumerate(data[:end].split(b"\n")[:-1], start=1):
        try:
            rec = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError):
            rec = None
        if not isinstance(rec, dict):
            log.warning("%s:%d: ignoring a line that is not a JSON object", path, n)
            continue
        if rec.get("type") == "header":
            if header is None:
                header = rec
            continue
        records.append(rec)
    return JournalContents(header, records, end, torn)


@dataclass
class JournalState:
    """What a journal says about its latest pass over the plan."""

    pass_index: int = 0
    done: dict[RunKey, dict[str, Any]] = field(default_factory=dict)  # key -> its "done" record
    attempts: dict[RunKey, int] = field(default_factory=dict)  # key -> starts in this pass
    interrupted: set[RunKey] = field(default_factory=set)  # last start has no run record after it
    sessions: int = 0

    @classmethod
    def of(cls, records: list[dict[str, Any]]) -> JournalState:
        """Fold the records; a record without a usable run key is ignored with a warning."""
        passes = [r.get("pass") for r in records if r.get("type") in ("start", "run")]
        st = cls(pass_index=max((p for p in passes if isinstance(p, int)), default=0))
        st.sessions = sum(1 for r in records if r.get("type") == "session")
        open_starts: set[RunKey] = set()
        for r in records:
            if r.get("type") not in ("start", "run") or r.get("pass") != st.pass_index:
                continue
            try:
                key = record_key(r)
            except (KeyError, TypeError, ValueError):
                log.warning("ignoring a journal record without object/program/speed/repeat: %s", r)
                continue
            if r["type"] == "start":
                st.attempts[key] = st.attempts.get(key, 0) + 1
                open_starts.add(key)
            else:
                open_starts.discard(key)
                if r.get("outcome") == "done":
                    st.done[key] = r
        st.interrupted = open_starts - set(st.done)
        return st


# ---------------------------------------------------------------------- writing
class Journal:
    """The open journal of an output folder; one session at a time (an exclusive lock on the file)."""

    def __init__(self, path: Path, fd: int, header: dict[str, Any], records: list[dict[str, Any]]) -> None:
        self.path = path
        self._fd: int | None = fd
        self.header = header
        self.records = records
        self.moved_aside: Path | None = None  # where --fresh put the previous journal
        self.created = False  # True when this open started a new journal

    @property
    def fingerprint(self) -> str:
        """The plan fingerprint the journal was written for."""
        return str(self.header["plan_fingerprint"])

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._fd is None

    @classmethod
    def open(cls, out_dir: Path, config: Config, *, fresh: bool = False) -> Journal:
        """Open (or start) ``out_dir``'s journal for ``config``'s plan.

        Raises JournalError when the folder's journal belongs to a different plan, or another
        session holds it. ``fresh`` first moves an existing journal aside (episodes are kept).
        """
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / JOURNAL_NAME
        description = plan_description(config)
        fp = fingerprint(description)
        moved: Path | None = None
        if fresh and path.exists():
            old = _lock(path)  # a live session's journal is never moved: it holds this lock
            try:
                moved = _move_aside(path)
            finally:
                os.close(old)
        fd = _lock(path)
        try:
            contents = read_journal(path)
            if contents.torn_bytes:
                os.ftruncate(fd, contents.valid_bytes)  # the next record must start on a line of its own
                os.fsync(fd)
            header = contents.header
            if header is None and contents.records:
                raise JournalError(
                    f"{path}: not a trackdeform journal (no header line with the plan fingerprint); "
                    "move it away, or pass --fresh to move it aside and start the plan over (episodes are kept)"
                )
            if header is not None:
                _check_header(path, header, description, fp)
            journal = cls(path, fd, header or {}, contents.records)
            if header is None:
                journal.header = {
                    "type": "header", "format": FORMAT, "plan_fingerprint": fp, "plan": description,
                    "created": now_iso(),
                }
                journal._write(journal.header)
                fsync_dir(out_dir)
                journal.created = True
            journal.moved_aside = moved
            return journal
        except BaseException:
            os.close(fd)
            raise

    def state(self) -> JournalState:
        """The latest plan pass as the records written so far describe it."""
        return JournalState.of(self.records)

    def append(self, record: dict[str, Any]) -> None:
        """Write one record and fsync it: when this returns, the record survives a crash."""
        self._write(record)
        self.records.append(record)

    def session_started(self, index: int, started: str, software: str, runs_planned: int, loop: bool) -> None:
        """Record that a session (the ``index``-th on this folder) starts on the plan."""
        self.append({"type": "session", "index": index, "started": started, "software": software,
                     "runs_planned": runs_planned, "loop": loop})

    def run_started(self, key: RunKey, *, plan_pass: int, attempt: int, session: int, first_episode: int) -> None:
        """Record that a run starts; a ``start`` without its ``run`` record is a run cut short."""
        self.append({"type": "start", "pass": plan_pass, **key_fields(key), "attempt": attempt,
                     "session": session, "first_episode": first_episode, "started": now_iso()})

    @staticmethod
    def run_record(key: RunKey, *, plan_pass: int, outcome: str, reason: str | None, attempt: int, session: int,
                   episodes: list[Path], wall_seconds: float) -> dict[str, Any]:
        """The ``run`` record of a finished run (written by :meth:`run_finished`, maybe later: a ``done``
        run is journaled once its episode files are final)."""
        if outcome not in OUTCOMES:
            raise ValueError(f"run outcome {outcome!r} is not one of {OUTCOMES}")
        return {"type": "run", "pass": plan_pass, **key_fields(key), "outcome": outcome, "reason": reason,
                "attempt": attempt, "session": session, "episodes": [p.name for p in episodes],
                "wall_seconds": round(wall_seconds, 3), "finished": now_iso()}

    def live_init(self, key: RunKey, *, plan_pass: int, session: int, outcome: str, reason: str | None,
                  attempts: list[dict[str, Any]], seconds: float, track_id: str | None) -> None:
        """Record an object's live initialisation (``orchestrator.liveinit``) before run ``key``: ``outcome``
        ok, failed or stopped, the last reason, every attempt (outcome, reason, metrics, seconds)."""
        self.append({"type": "live_init", "pass": plan_pass, **key_fields(key), "session": session,
                     "outcome": outcome, "reason": reason, "attempts": attempts, "seconds": round(seconds, 3),
                     "track_id": track_id, "finished": now_iso()})

    def run_finished(self, record: dict[str, Any], *, failed_reason: str | None = None) -> None:
        """Write a :meth:`run_record`; with ``failed_reason``, as a failed run with that reason instead."""
        if failed_reason is not None:
            record = {**record, "outcome": "failed", "reason": failed_reason}
        self.append(record)

    def _write(self, record: dict[str, Any]) -> None:
        if self._fd is None:
            raise JournalError(f"{self.path}: the journal is closed")
        data = (json.dumps(record, separators=(",", ":")) + "\n").encode()
        view = memoryview(data)
        start = os.lseek(self._fd, 0, os.SEEK_END)
        try:
            while view:  # one write() in practice; a short write continues where it stopped
                n = os.write(self._fd, view)
                view = view[n:]
            os.fsync(self._fd)
        except OSError as e:
            try:  # no torn line left behind: the next record starts on a line of its own
                os.ftruncate(self._fd, start)
            except OSError:
                pass
            raise OSError(e.errno, f"cannot write the journal: {e.strerror}", str(self.path)) from e

    def close(self) -> None:
        """Release the lock and close the file (idempotent)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


LOCKED_HINT = "wait for it to finish, or record to another folder with --out DIR"


def _flock_or_close(fd: int) -> bool:
    """Take the exclusive lock on ``fd`` without waiting; False (and ``fd`` closed) when another holds it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return False
    return True


def _lock(path: Path) -> int:
    """Open ``path`` (created if missing) and take its exclusive lock; JournalError when a session holds it."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
    if not _flock_or_close(fd):
        raise JournalError(
            f"{path}: another session is recording into this folder now (the journal is locked); {LOCKED_HINT}"
        ) from None
    return fd


class FolderLock:
    """The journal lock of an output folder, for a tool that writes there without a session (``recover``).

    ``with FolderLock(out_dir):`` raises JournalError while a live session holds the folder. A missing
    journal is not created: a session always locks one, so a folder without it has no live session.
    """

    def __init__(self, out_dir: Path) -> None:
        self.path = Path(out_dir) / JOURNAL_NAME
        self._fd: int | None = None

    def __enter__(self) -> FolderLock:
        try:
            fd = os.open(self.path, os.O_RDONLY)
        except FileNotFoundError:
            return self
        if not _flock_or_close(fd):
            raise JournalError(
                f"{self.path.parent}: a live session is recording into this folder (its journal is locked); "
                "its unfinished files are being written, not left by a crash. Run this after the session ends"
            ) from None
        self._fd = fd
        return self

    def __exit__(self, *exc: object) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _check_header(path: Path, header: dict[str, Any], description: dict[str, Any], fp: str) -> None:
    """Refuse a journal of another format or another plan, saying what differs and how to go on."""
    how = (
        "To keep this folder's episodes and start the plan over here, pass --fresh (the journal is moved "
        "aside, episode numbering continues); or record to a new folder with --out DIR."
    )
    if header.get("format") != FORMAT:
        raise JournalError(f"{path}: journal format {header.get('format')!r}, expected {FORMAT!r}. {how}")
    if header.get("plan_fingerprint") == fp:
        return
    diff = _differences(header.get("plan"), description)
    shown = ", ".join(diff[:6]) + (f" and {len(diff) - 6} more" if len(diff) > 6 else "")
    raise JournalError(
        f"{path}: this folder's journal was written for a different plan "
        f"(journal {str(header.get('plan_fingerprint'))[:19]}, this config {fp[:19]}; differs in: {shown}). "
        f"Its record of done runs does not apply to this plan. {how}"
    )


def _move_aside(path: Path) -> Path:
    """Rename a journal to ``session.journal.<time>.jsonl`` (never over an existing file)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    stem = path.name.removesuffix(".jsonl")
    target = path.with_name(f"{stem}.{stamp}.jsonl")
    n = 1
    while target.exists():
        target = path.with_name(f"{stem}.{stamp}-{n}.jsonl")
        n += 1
    os.rename(path, target)
    fsync_dir(path.parent)
    log.info("moved %s aside to %s", path, target.name)
    return target


def find_resumable(directory: Path, config: Config) -> Path | None:
    """The newest ``*_<station>`` folder in ``directory`` with this plan's journal, if its plan is unfinished.

    Lets ``trackdeform run CONFIG`` without ``--out`` (the nightly job after a reboot) go on in the
    session folder it was writing; folders of other plans are left alone.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return None
    fp = fingerprint(plan_description(config))
    planned = {run_key(it) for it in build_plan(config.plan)}
    candidates = sorted(directory.glob(f"*_{config.station.name}/{JOURNAL_NAME}"), reverse=True)
    for path in candidates:
        try:
            contents = read_journal(path)
        except OSError as e:
            log.warning("%s: cannot read (%s); not resuming there", path, e)
            continue
        if contents.header is None or contents.header.get("plan_fingerprint") != fp:
            continue
        # the newest folder of this plan decides: an older unfinished one was given up on by a --fresh start
        return None if planned <= set(JournalState.of(contents.records).done) else path.parent
    return None
