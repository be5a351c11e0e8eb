"""What happens to an episode after its file is final: the folder's manifest lists it, and once its run's files
are all final the run goes to the background final tracking (:mod:`orchestrator.final`), journaled as ``final``.

``manifest.json`` (format: :mod:`tdrecord.api`) is rewritten atomically (``manifest.json.tmp``, fsynced,
renamed, folder fsynced) whenever episodes land or final tracking rewrites them, so a reader never sees a
torn manifest and every file it lists is finished.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

from orchestrator.fsutil import fsync_dir
from orchestrator.journal import Journal, now_iso
from orchestrator.progress import Progress
from orchestrator.summary import SessionSummary
from tdrecord import DatasetError
from tdrecord.api import MANIFEST_FORMAT, MANIFEST_NAME, manifest_entry, read_manifest

log = logging.getLogger(__name__)

RUN_FIELDS = ("object", "program", "speed", "repeat", "pass", "attempt")


class Manifest:
    """A session folder's ``manifest.json``: one entry per finished episode, written atomically."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = Path(out_dir)
        self.path = self.out_dir / MANIFEST_NAME
        try:
            entries = read_manifest(self.out_dir) or []
        except DatasetError as e:
            log.warning("%s; rebuilding it from the folder", e)
            entries = []
        self.entries: dict[str, dict[str, Any]] = {e["file"]: e for e in entries}

    def add(self, paths: list[Path], *, refresh: bool = False) -> None:
        """List these finished files (``refresh``: read their metadata again, e.g. after final tracking)."""
        changed = False
        for p in paths:
            p = Path(p)
            if (p.name in self.entries and not refresh) or not p.is_file():
                continue
            try:
                self.entries[p.name] = manifest_entry(p)
            except (ValueError, OSError) as e:
                log.warning("%s: not listed in the manifest (%s)", p, e)
                continue
            changed = True
        if changed:
            self.write()

    def sync_folder(self) -> None:
        """List the folder's finished episodes the manifest lacks (a folder from before manifests) and drop
        the entries of files that are gone."""
        files = sorted(self.out_dir.glob("episode_*.mcap"))
        gone = set(self.entries) - {p.name for p in files}
        for name in gone:
            del self.entries[name]
        before = len(self.entries)
        self.add(files)
        if gone and len(self.entries) == before:
            self.write()

    def write(self) -> None:
        """Write the manifest atomically: a temporary file, fsynced, renamed over it, the folder fsynced."""
        data = {"format": MANIFEST_FORMAT, "updated": now_iso(),
                "episodes": [self.entries[k] for k in sorted(self.entries)]}
        tmp = self.path.with_name(self.path.name + ".tmp")
        with open(tmp, "w") as f:
            f.write(json.dumps(data, indent=1))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)
        fsync_dir(self.out_dir)


class Landing:
    """The session's side of manifest and final tracking: ``run_ended`` per run, ``poll`` often (on the session
    thread: it journals), ``finish`` at the end."""

    def __init__(self, out_dir: Path, config: Any, journal: Journal, summary: SessionSummary,  # noqa: ANN401
                 progress: Progress, software: str = "") -> None:
        from orchestrator.final import FinalTracker, pending_runs

        self.out_dir = Path(out_dir)
        self.journal = journal
        self.summary = summary
        self.progress = progress
        self.manifest = Manifest(self.out_dir)
        self.manifest.sync_folder()
        self.enabled = bool(config.tracking.enabled and config.tracking.final)
        self._waiting: list[tuple[dict[str, Any], list[Path]]] = []  # runs whose files are not all final yet
        self._submitted: list[tuple[dict[str, Any], list[Path]]] = []
        self.tracker = FinalTracker(self.out_dir, config.tracking, software) if self.enabled else None
        self.summary.final_keypoints = {"enabled": self.enabled, "runs_done": 0, "runs_failed": 0,
                                        "runs_pending": 0, "episodes": 0, "frames": 0, "frames_with_final": 0,
                                        "tangled_frames": 0}
        if self.tracker is not None:
            resumed = pending_runs(journal.records, self.out_dir)
            for run, files in resumed:
                self._submit(run, files)
            if resumed:
                self.progress.message(f"final keypoints: {len(resumed)} run(s) of earlier sessions to track")

    def run_ended(self, run: dict[str, Any], episodes: list[Path]) -> None:
        """A run's capture ended (done, failed or cut short) with these episode files (finished later)."""
        if self.tracker is not None and episodes:
            self._waiting.append(({k: run.get(k) for k in RUN_FIELDS}, list(episodes)))

    def poll(self, finished: list[Path]) -> None:
        """List newly finished files, hand runs whose files are all final to the tracker, journal its results."""
        self.manifest.add(finished)
        done = set(finished)
        keep = []
        for run, files in self._waiting:
            if all(f in done for f in files):
                self._submit(run, files)
            else:
                keep.append((run, files))
        self._waiting = keep
        if self.tracker is None:
            return
        for job in self.tracker.poll():
            self._record(job.run, job.files, job.result or {"status": "failed", "reason": "no result"})

    def finish(self, finished: list[Path], stop_requested: bool) -> None:
        """At the end of the session: wait for the final tracking (unless a stop was requested: then the runs
        left are journaled as ``final_pending`` and the next session on the folder does them)."""
        self.poll(finished)
        if self.tracker is None:
            return
        waiting = [(r, [f for f in fs if f in set(finished)]) for r, fs in self._waiting]
        for run, files in waiting:  # files that never finished are left out (they are .active or quarantined)
            if files:
                self._submit(run, files)
        self._waiting = []
        if self.tracker.pending and not stop_requested:
            self.progress.message(f"final keypoints: waiting for {self.tracker.pending} run(s) to be tracked")
            try:
                while not self.tracker.wait(1.0):
                    self.poll(finished)
            except KeyboardInterrupt:
                stop_requested = True
        left = self.tracker.stop() if stop_requested else 0
        self.poll(finished)
        if left:
            todo = [(r, fs) for r, fs in self._submitted]
            self.journal.append({"type": "final_pending", "runs": [{**r, "episodes": [f.name for f in fs]}
                                                                   for r, fs in todo], "at": now_iso()})
            self.summary.final_keypoints["runs_pending"] = len(todo)
        else:
            self.tracker.stop()

    def _submit(self, run: dict[str, Any], files: list[Path]) -> None:
        assert self.tracker is not None
        self._submitted.append((run, files))
        self.tracker.submit(run, files)

    def _record(self, run: dict[str, Any], files: list[Path], result: dict[str, Any]) -> None:
        self._submitted = [(r, fs) for r, fs in self._submitted if fs != files]
        rec = {"type": "final", **run, "status": result.get("status", "failed"), "reason": result.get("reason"),
               "episodes": [f.name for f in files], "frames": result.get("frames", 0),
               "frames_with_final": result.get("frames_with_final", 0),
               "tangled_frames": result.get("tangled_frames", 0), "window": result.get("window"),
               "seconds": result.get("seconds"), "finished": now_iso()}
        self.journal.append(rec)
        fk = self.summary.final_keypoints
        if rec["status"] == "done":
            fk["runs_done"] += 1
            fk["episodes"] += len(files)
            fk["frames"] += int(rec["frames"] or 0)
            fk["frames_with_final"] += int(rec["frames_with_final"] or 0)
            fk["tangled_frames"] += int(rec["tangled_frames"] or 0)
            self.manifest.add(files, refresh=True)
        else:  # failed: never initialised (kept); error: tried again by the next session on the folder
            fk["runs_failed"] += 1
            msg = f"final keypoints of {', '.join(f.name for f in files)}: {rec['reason']}"
            self.progress.message(msg)
            fk.setdefault("failures", []).append(msg)
