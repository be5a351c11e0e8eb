"""A collection session: the plan loop over the station's objects, journaled so it resumes after a crash.

Each run item is recorded by :class:`orchestrator.capture.RunCapture` between a ``start`` and a ``run``
record of the folder's journal (:mod:`orchestrator.journal`); a ``done`` run is journaled only once its
episode files are final. The summary (:mod:`orchestrator.summary`) is written at the end.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable
from itertools import groupby
from pathlib import Path
from typing import Any

from drivers.base import DeviceError
from drivers.clock import Clock
from orchestrator import __version__
from orchestrator.bus import Bus
from orchestrator.capture import EpisodeStream, RunCapture, RunContext
from orchestrator.config import Config
from orchestrator.fsutil import SpaceReserve
from orchestrator.health import SessionMonitor
from orchestrator.journal import Journal, RunKey, key_fields, now_iso, record_key, run_key
from orchestrator.landing import Landing
from orchestrator.live import KeypointGate
from orchestrator.liveinit import InitOutcome, LiveInit
from orchestrator.plan import RunItem, build_plan
from orchestrator.progress import Progress
from orchestrator.recorder import Recorder
from orchestrator.recovery import recover_active
from orchestrator.station import Station
from orchestrator.summary import SessionSummary
from orchestrator.supervisor import WorkerSupervisor

__all__ = ["Session", "SessionSummary", "Station"]

log = logging.getLogger(__name__)


class Session:
    """Runs a plan: ``Session(config, out_dir, clock).run()``."""

    def __init__(
        self,
        config: Config,
        out_dir: Path,
        clock: Clock,
        *,
        bus: Bus | None = None,
        progress: Progress | None = None,
        stop_event: threading.Event | None = None,
        state_rate: float = 250.0,
        on_station: Callable[[Station], None] | None = None,
        journal: Journal | None = None,
        with_worker: bool = False,
        finishing: threading.Event | None = None,
    ) -> None:
        self.config = config
        self.out_dir = Path(out_dir)
        self.clock = clock
        self.sim_time = config.clock == "sim"
        self.bus = bus
        self.progress = progress or Progress(enabled=False)
        self.stop_event = stop_event or threading.Event()
        self.state_rate = state_rate
        self.on_station = on_station  # called with each station right after it connects (tests inject faults)
        self.summary = SessionSummary(self.out_dir)
        self._recorder: Recorder | None = None
        self._stream: EpisodeStream | None = None
        self._max_seconds: float | None = None
        self._journal = journal  # opened by the caller (the CLI checks it early), else by run(); closed by run()
        self._pass = 0
        self._session_index = 0
        self._session_started = ""
        self._attempts: dict[RunKey, int] = {}
        self._pending: list[tuple[dict[str, Any], list[Path]]] = []  # "done" records waiting for their files
        self._done_keys: set[RunKey] = set()
        self.with_worker = with_worker  # start and supervise the tracking worker (needs the bus)
        self.session_id = uuid.uuid4().hex[:16]  # in the run announcements; keypoints must carry it
        self.monitor: SessionMonitor | None = None
        self.gate: KeypointGate | None = None
        self.supervisor: WorkerSupervisor | None = None
        self._runs_done_here = 0
        self._reserve: SpaceReserve | None = None
        self.finishing = finishing or threading.Event()  # set once the last files and the summary are written
        self._landing: Landing | None = None  # manifest + final keypoints of the runs (orchestrator.landing)
        self._live: LiveInit | None = None  # the per-object live initialisation (with the session's worker)
        self._last_status: str | None = None  # status of the newest keypoints recorded in the current run

    # ------------------------------------------------------------------ public
    def run(self, max_seconds: float | None = None, loop: bool = False) -> SessionSummary:
        """Run the plan once (or repeatedly with ``loop``) until done, stopped or ``max_seconds`` recorded.

        The folder's journal says which runs earlier sessions finished: those are skipped, the
        rest run in plan order. Raises JournalError (before touching the folder) for another plan's journal.
        """
        t_wall = time.monotonic()
        self._max_seconds = max_seconds
        self.out_dir.mkdir(parents=True, exist_ok=True)
        journal = self._journal
        if journal is None or journal.closed:
            journal = self._journal = Journal.open(self.out_dir, self.config)
        try:
            self._reserve = SpaceReserve(self.out_dir)
            monitor = self._start_monitor(max_seconds)
            if any(self.out_dir.glob("*.mcap.active")):
                monitor.set_state("recovering", "unfinished episodes of an earlier session")
            for path, outcome in recover_active(self.out_dir):
                self.progress.message(f"found an unfinished episode from an earlier run: {path.name}: {outcome}")
                monitor.incident("recovered_episode", f"{path.name}: {outcome}")
            monitor.set_state("initialising")
            cam = self.config.station.camera
            out = self.config.output
            self._recorder = Recorder(cam.id, out.compression, color=out.color, depth=out.depth)
            self._stream = EpisodeStream(
                self.out_dir, self._recorder, self.bus, cam.id, self.summary,
                min_free_gb=out.min_free_gb, stop_event=self.stop_event,
                before_open=lambda: self._flush_pending(final=False),
                disk_check_seconds=self.config.output.disk_check_seconds,
                sync=self.config.sync,
            )
            self._stream.monitor = monitor
            self._start_tracking(cam.fps)
            self._landing = Landing(self.out_dir, self.config, journal, self.summary, self.progress, __version__)
            items = build_plan(self.config.plan)
            try:
                self._run_plan(items, journal, loop)
            except OSError as e:  # the journal could not be written (a full disk): stop, say where
                msg = f"{e.filename or self.out_dir}: {e.strerror or e}"
                self.summary.errors.append(f"session stopped: {msg}")
                self.summary.stopped_early = f"I/O error: {msg}"
                self.progress.message(f"error: session stopped: {msg}")
                self.stop_event.set()
        finally:
            self._finish(journal, t_wall)
        return self.summary

    def _run_plan(self, items: list[RunItem], journal: Journal, loop: bool) -> None:
        """Run the plan's items the journal does not list as done, pass after pass with ``loop``."""
        state = journal.state()
        self._pass, self._attempts, self._done_keys = state.pass_index, dict(state.attempts), set(state.done)
        self._session_index, self._session_started = state.sessions, now_iso()
        planned = {run_key(it) for it in items}
        self.summary.runs_planned = len(items)
        self.summary.journal = journal.path.name
        journal.session_started(self._session_index, self._session_started, __version__, len(items), loop)
        all_done = planned <= self._done_keys
        msg = ""
        if all_done and loop:
            msg = (f"resuming: pass {self._pass + 1} over the plan is complete ({len(items)} run(s)); "
                   f"starting pass {self._pass + 2}")
            self._next_pass()
        elif all_done:
            self.summary.runs_already_done = len(items)
            msg = (f"resuming: all {len(items)} run(s) of the plan are already done in {self.out_dir} "
                   f"(journal {journal.path.name}); nothing left to do. --fresh records the plan again")
        elif self._done_keys & planned or state.interrupted & planned:
            self.summary.runs_already_done = len(self._done_keys & planned)
            first = next(it for it in items if run_key(it) not in self._done_keys)
            again = ""
            if run_key(first) in state.interrupted:
                again = (f" (attempt {self._attempts.get(run_key(first), 0) + 1}: an earlier attempt was cut short; "
                         "its episodes stay and this one starts the run over)")
            msg = (f"resuming: {self.summary.runs_already_done} of {len(items)} runs already done, "
                   f"continuing with {first.label}{again}")
        if msg:
            log.info(msg)
            self.progress.message(msg)
        if all_done and not loop:
            return
        try:
            while not self._should_stop():
                todo = [it for it in items if run_key(it) not in self._done_keys]
                recorded_before = self.summary.recorded_seconds
                for _name, group in groupby(todo, key=lambda it: it.object.name):
                    if self._should_stop():
                        break
                    self._run_object(list(group))
                if not loop:
                    break
                if self.summary.recorded_seconds == recorded_before and not self._should_stop():
                    self.summary.stopped_early = "a whole pass over the plan recorded nothing"
                    break
                if not self._should_stop():
                    self._next_pass()
        except KeyboardInterrupt:
            self.summary.stopped_early = "interrupted"

    def _next_pass(self) -> None:
        """Start another pass over the plan (``loop``): every item is to do again, attempts count from 1."""
        self._flush_pending(final=False)
        self._pass += 1
        self._attempts, self._done_keys = {}, set()

    def _start_monitor(self, max_seconds: float | None) -> SessionMonitor:
        """State, health and control (``orchestrator.health``); ``events.jsonl`` in the output folder."""
        planned = len(build_plan(self.config.plan))
        self.monitor = SessionMonitor(
            self.out_dir, self.summary, self.stop_event, bus=self.bus, session_id=self.session_id,
            period=self.config.bus.health_period, min_free_gb=self.config.output.min_free_gb,
            progress=lambda: {"runs_done": len(self._done_keys), "runs_planned": planned, "plan_pass": self._pass,
                              "runs_done_here": self._runs_done_here},
            worker=lambda: self.supervisor.status() if self.supervisor is not None else None,
            keypoints=lambda: {"recorded": self._recorder.keypoints_written if self._recorder else 0,
                               "rejected": dict(self.gate.rejected.counts) if self.gate else {}},
        )
        self.monitor.max_seconds = max_seconds
        self.monitor.start()
        return self.monitor

    def _start_tracking(self, fps: float) -> None:
        """With a bus and tracking on: check incoming keypoints; with ``with_worker``, start and supervise it."""
        if self.bus is None or not self.config.tracking.enabled:
            return
        monitor = self.monitor
        assert monitor is not None and self._stream is not None
        self.gate = KeypointGate(self.session_id, fps, self.config.tracking.gap_seconds)
        self.gate.rejected.on_first = lambda kind, detail: monitor.incident("keypoints_rejected", f"{kind}: {detail}")
        self._stream.gate = self.gate
        self.bus.subscribe(self.bus.key("keypoints"), callback=self._on_keypoints)
        if self.with_worker:
            self.supervisor = WorkerSupervisor(self.config, self.out_dir, self.bus, self.session_id, self.gate,
                                               report=monitor.incident)
            self.supervisor.start()
            timeout = self.config.tracking.worker_start_timeout
            self.progress.message("waiting for the tracking worker")
            if not self.supervisor.wait_ready(timeout, self.stop_event) and not self.stop_event.is_set():
                monitor.incident("worker_not_ready", f"the tracking worker was not up after {timeout:.0f} s; "
                                 "recording without live keypoints until it is")
            if self.config.tracking.live_init.enabled:
                self._live = LiveInit(self.config, self.clock, self._stream, self.gate, self.stop_event,
                                      self.progress, self.state_rate, set_state=monitor.set_state)

    def _finish(self, journal: Journal, t_wall: float) -> None:
        """Finish the episodes, journal the runs whose files are now final, fill and write the summary.

        The summary is written whatever happens on the way (a second signal, a full disk): the space
        reserve is released first, and a summary that cannot be written is reported in one line.
        """
        self.finishing.set()
        monitor = self.monitor
        try:
            if monitor is not None and self.stop_event.is_set():
                monitor.set_state("stopping", self.summary.stopped_early or "stop requested")
            if self._recorder is not None:
                self._recorder.stop()
                self._with_space(lambda: self._flush_pending(final=True))
                if self._landing is not None:
                    self._landing.finish(list(self._recorder.finished), self.stop_event.is_set())
        finally:
            journal.close()
            if self._reserve is not None:
                self._reserve.release()
            if self._recorder is not None:
                self.summary.episodes = sorted(self._recorder.finished)
                self.summary.keypoints_recorded = self._recorder.keypoints_written
                self.summary.errors.extend(self._recorder.errors)
            if self.supervisor is not None:
                self.supervisor.stop()
                self.summary.worker_restarts = self.supervisor.restarts
                if self.supervisor.given_up:
                    self.summary.errors.append(self.supervisor.given_up)
            if self.gate is not None:
                self.summary.keypoints_rejected = dict(self.gate.rejected.counts)
            if monitor is not None:
                monitor.close("failed" if self.summary.runs_failed or self.summary.errors else "done")
            planned = {run_key(it) for it in build_plan(self.config.plan)}
            self.summary.plan_runs_done = len(self._done_keys & planned)
            self.summary.plan_pass = self._pass
            self.summary.wall_seconds = time.monotonic() - t_wall
            self.progress.done()
            try:
                self.summary.write(self.out_dir / "summary.json")
            except OSError as e:
                self.summary.errors.append(f"{self.out_dir / 'summary.json'}: could not be written: {e}")
                self.progress.message(f"error: {self.out_dir / 'summary.json'}: could not be written: {e}")

    # ------------------------------------------------------------------ internals
    def _should_stop(self) -> bool:
        if self.stop_event.is_set():
            self.summary.stopped_early = self.summary.stopped_early or "stop requested"
            return True
        if self._max_seconds is not None and self.summary.recorded_seconds >= self._max_seconds - 1e-6:
            return True
        return False

    def _on_keypoints(self, sample: Any) -> None:
        """Record a keypoint message that passes the gate (checked, this session, a run and frame it recorded)."""
        if self.gate is None or self._recorder is None:
            return
        msg = self.gate.accept(sample.payload.to_bytes())
        if msg is not None:
            self._last_status = str(msg["status"])
            self._recorder.keypoints(msg)

    def _run_object(self, items: list[RunItem]) -> None:
        obj = items[0].object
        station = Station(self.config, obj, self.clock)
        if self.monitor is not None:
            self.monitor.set_state("initialising", f"connecting the station for {obj.name}")
        try:
            station.connect()
        except DeviceError as e:
            if self.monitor is not None:
                self.monitor.incident("station_not_ready", f"{obj.name}: {e}")
            self.summary.errors.append(f"{obj.name}: station not ready: {e}")
            self.progress.message(f"error: {obj.name}: {e}")
            station.close()
            for item in items:  # journaled so the record says why; retried on resume like a failed run
                self._journal_run(item, "skipped", f"station not ready: {e}", [], 0.0)
            return
        try:
            if self.on_station is not None:
                self.on_station(station)
            init: InitOutcome | None = None
            for n, item in enumerate(items):
                if self._should_stop():
                    break
                if station.broken:
                    reason = f"skipped, the station needs attention ({station.broken})"
                    self.summary.runs_failed.append(f"{item.label}: {reason}")
                    self._journal_run(item, "skipped", reason, [], 0.0)
                    continue
                if self._live is not None and self._needs_init(init):
                    init = self._live_initialise(station, item)
                    if init.stopped:
                        break
                    if not init.ok and self.config.tracking.live_init.on_failure == "skip":
                        reason = f"live initialisation failed after {len(init.attempts)} attempt(s): {init.reason}"
                        for rest in items[n:]:  # journaled so the record says why; retried on resume
                            self.summary.runs_skipped.append(f"{rest.label}: {reason}")
                            self._journal_run(rest, "skipped", reason, [], 0.0)
                        break
                self._run_journaled(item, station, init)
        finally:
            station.close()

    def _needs_init(self, init: InitOutcome | None) -> bool:
        """Whether the object's next run needs a (new) live initialisation: none yet, or (``reinitialise``) the
        worker restarted since, or the previous run's newest recorded keypoints were not tracking."""
        if init is None:
            return True
        if not init.ok or not self.config.tracking.live_init.reinitialise:
            return False
        restarts = self.supervisor.restarts if self.supervisor is not None else 0
        return restarts != init.worker_restarts or self._last_status not in ("init", "tracking", "degraded")

    def _live_initialise(self, station: Station, item: RunItem) -> InitOutcome:
        """Run the live initialisation before ``item``; journal it, put it in the summary and the health."""
        assert self._live is not None and self._journal is not None
        journal = self._journal
        supervisor = self.supervisor
        self.progress.message(f"{item.object.name}: live initialisation (reference, a short move, check)")
        init = self._live.run(station, item, lambda: supervisor.restarts if supervisor is not None else 0)
        outcome = "stopped" if init.stopped else ("ok" if init.ok else "failed")
        self._with_space(lambda: journal.live_init(
            run_key(item), plan_pass=self._pass, session=self._session_index, outcome=outcome, reason=init.reason,
            attempts=init.attempts, seconds=init.seconds, track_id=init.track_id))
        if not init.stopped:
            line = init.summary_line()
            self.summary.live_init.append({"object": item.object.name, **init.meta(False), "line": line})
            self.progress.message(f"{'' if init.ok else 'warning: '}live initialisation {line}")
            if not init.ok and self.monitor is not None:
                self.monitor.incident("live_init_failed", line)
        return init

    def _run_journaled(self, item: RunItem, station: Station, init: InitOutcome | None = None) -> None:
        """Run an item between a ``start`` and a ``run`` journal record (none when a stop cuts it short).

        Low disk space ends the attempt (journaled failed, with the reason); with ``output.on_low_disk:
        pause`` the item runs again once space returns, else the session stops. A recorder that failed
        on an I/O error stops the session: the run is journaled failed with the reason.
        """
        while self._run_attempt(item, station, init):
            pass

    def _run_attempt(self, item: RunItem, station: Station, init: InitOutcome | None = None) -> bool:
        """One attempt at an item; True when it is to be attempted again (space came back after a pause).

        After a successful live initialisation ``init`` the run is announced with its track (the worker keeps
        tracking) and every episode's metadata has ``live_init``."""
        key = run_key(item)
        self._flush_pending(final=False)
        monitor = self.monitor
        if monitor is not None and monitor.pause_requested():  # a pause asked for at the end of the last run
            monitor.hold()
            if self._should_stop():
                return False
        attempt = self._attempts[key] = self._attempts.get(key, 0) + 1
        assert self._journal is not None and self._stream is not None
        journal, stream = self._journal, self._stream
        self._with_space(lambda: journal.run_started(key, plan_pass=self._pass, attempt=attempt,
                                                     session=self._session_index, first_episode=stream.next_index))
        run_meta: dict[str, Any] = {
            "attempt": attempt,  # 1 + earlier starts of this run in this plan pass (journal)
            "plan_pass": self._pass,
            "session_started": self._session_started,  # UTC: tells a re-run's episodes from the cut-short ones
        }
        if init is not None:
            run_meta["live_init"] = init.meta(carried=init.for_run != item.label)
        ctx = RunContext(
            config=self.config, clock=self.clock, stream=self._stream, summary=self.summary, progress=self.progress,
            stop_event=self.stop_event, should_stop=self._should_stop, max_seconds=self._max_seconds,
            state_rate=self.state_rate, run_meta=run_meta, control=monitor,
            announce={"track_id": init.track_id} if init is not None and init.ok else {},
        )
        self._last_status = None
        capture = RunCapture(ctx, item, station)
        if monitor is not None:
            monitor.set_state("running", item.label)
        t0 = time.monotonic()
        outcome, reason = capture.run()
        episodes, wall = list(capture.episodes), time.monotonic() - t0
        self._stream.begin_run("", {}, "")  # between runs: the tracker holds
        if monitor is not None:
            if outcome == "failed":
                monitor.incident("run_failed", reason or item.label)
            elif outcome == "skipped":
                monitor.incident("run_skipped", f"{item.label}: {reason}")
            if not self.stop_event.is_set():
                monitor.set_state("idle", f"{item.label}: {outcome}")
        if outcome == "done":
            self._runs_done_here += 1
        if self._landing is not None:
            self._landing.run_ended({**key_fields(key), "pass": self._pass, "attempt": attempt}, episodes)
        if outcome == "low_disk":
            assert reason is not None
            self._journal_run(item, "failed", f"low disk space: {reason}", episodes, wall)
            self.progress.message(f"warning: {reason}")
            if self.config.output.on_low_disk == "pause" and self._wait_for_disk():
                return True
            self.summary.stopped_early = self.summary.stopped_early or reason
            self.stop_event.set()
            return False
        if outcome == "failed" and self._recorder is not None and self._recorder.failed is not None:
            self._with_space(lambda: self._journal_run(item, outcome, reason, episodes, wall))
            self.summary.stopped_early = f"recording failed: {self._recorder.failed}"
            self.progress.message(
                f"error: recording stopped: {self._recorder.failed}; unfinished files stay .active "
                f"(run `trackdeform recover {self.out_dir}` once there is space)"
            )
            self.stop_event.set()
            return False
        if outcome == "stopped":
            self.summary.runs_cut_short.append(
                f"{item.label}: stopped after {len(episodes)} episode(s); runs again from its start on resume"
            )
        elif outcome == "done":  # journaled once its files are final (the recorder closes them behind capture)
            self._done_keys.add(key)
            self._pending.append((self._run_record(item, "done", None, episodes, wall), episodes))
        else:
            self._journal_run(item, outcome, reason, episodes, wall)
        return False

    def _with_space(self, write: Callable[[], None]) -> None:
        """Run a journal write; on an OSError (a full disk) release the space reserve and try once more."""
        try:
            write()
        except OSError:
            if self._reserve is None or not self._reserve.held:
                raise
            self._reserve.release()
            write()

    def _wait_for_disk(self) -> bool:
        """Pause (arms stopped, nothing recorded) until free space is back above ``min_free_gb``.

        True when it is; False when a stop came first.
        """
        assert self._stream is not None
        poll = self.config.output.low_disk_poll_seconds
        self.summary.low_disk_pauses += 1
        self.progress.message(f"paused: waiting for free space in {self.out_dir} (checked every {poll:g} s)")
        while not self.stop_event.is_set():
            if self._stream.disk_low() is None:
                self.progress.message("free space is back: resuming")
                return True
            self.stop_event.wait(poll)
        return False

    def _run_record(
        self, item: RunItem, outcome: str, reason: str | None, episodes: list[Path], wall: float
    ) -> dict[str, Any]:
        """The ``run`` journal record of a finished item."""
        key = run_key(item)
        return Journal.run_record(key, plan_pass=self._pass, outcome=outcome, reason=reason,
                                  attempt=self._attempts.get(key, 0), session=self._session_index,
                                  episodes=episodes, wall_seconds=wall)

    def _journal_run(self, item: RunItem, outcome: str, reason: str | None, episodes: list[Path],
                     wall: float) -> None:
        """Journal a failed or skipped item now (it is retried on resume whatever its files' state)."""
        journal = self._journal
        assert journal is not None
        record = self._run_record(item, outcome, reason, episodes, wall)
        self._with_space(lambda: journal.run_finished(record))

    def _flush_pending(self, final: bool) -> None:
        """Journal the "done" runs whose episode files are all final; with ``final``, the rest as failed."""
        if self._landing is not None and self._recorder is not None:
            self._landing.poll(list(self._recorder.finished))
        if not self._pending or self._recorder is None or self._journal is None:
            return
        finished = set(self._recorder.finished)
        keep = []
        for record, episodes in self._pending:
            missing = [p.name for p in episodes if p not in finished]
            if not missing:
                self._journal.run_finished(record)
            elif final:
                self._journal.run_finished(record, failed_reason=f"episode file(s) not finished: {', '.join(missing)}")
                self._done_keys.discard(record_key(record))
            else:
                keep.append((record, episodes))
        self._pending = keep
