"""What a session did: counted as it runs, printed at the end and written atomically as ``summary.json``."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class SessionSummary:
    """What a session did; printed at the end and written as ``summary.json``."""

    out_dir: Path
    episodes: list[Path] = field(default_factory=list)
    frames_captured: int = 0
    frames_dropped: int = 0
    state_samples: int = 0
    keypoints_recorded: int = 0
    keypoints_rejected: dict[str, int] = field(default_factory=dict)  # by kind: not recorded (live.KeypointGate)
    tracking_gaps: int = 0  # stretches >= tracking.gap_seconds of frames without keypoints, over the episodes
    tracking_gap_frames: int = 0
    worker_restarts: int = 0
    incidents: list[str] = field(default_factory=list)  # "time kind: message", also in events.jsonl
    runs_skipped: list[str] = field(default_factory=list)  # by `trackdeform ctl skip`
    runs_done: int = 0
    runs_failed: list[str] = field(default_factory=list)
    runs_cut_short: list[str] = field(default_factory=list)  # counted in runs_done; not journaled, so re-run
    runs_planned: int = 0  # run items in one pass over the plan
    runs_already_done: int = 0  # skipped: done in an earlier session (the journal says so)
    plan_runs_done: int = 0  # runs of the current pass done by the end, earlier sessions included
    plan_pass: int = 0
    journal: str | None = None
    faults_recovered: int = 0
    low_disk_pauses: int = 0  # times the session paused for free space (output.on_low_disk: pause)
    start_skew_s: float = 0.0  # largest delay between the two arms' motion starts over the runs, s
    errors: list[str] = field(default_factory=list)
    recorded_seconds: float = 0.0
    wall_seconds: float = 0.0
    stopped_early: str | None = None
    final_keypoints: dict[str, Any] = field(default_factory=dict)  # orchestrator.landing: offline final tracking
    live_init: list[dict[str, Any]] = field(default_factory=list)  # orchestrator.liveinit: one per initialisation

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict."""
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        d["episodes"] = [str(p) for p in self.episodes]
        return d

    def text(self) -> str:
        """The human summary printed at the end of a session."""
        lines = [
            f"episodes written : {len(self.episodes)}",
            f"frames captured  : {self.frames_captured}",
            f"frames dropped   : {self.frames_dropped}",
            f"joint states     : {self.state_samples}",
            f"keypoint sets    : {self.keypoints_recorded}"
            + (f" ({sum(self.keypoints_rejected.values())} rejected: "
               + ", ".join(f"{k} {n}" for k, n in sorted(self.keypoints_rejected.items())) + ")"
               if self.keypoints_rejected else ""),
            f"program runs     : {self.runs_done} done, {len(self.runs_failed)} failed"
            + (f" ({len(self.runs_cut_short)} of the done cut short by the stop: re-run from the start on resume)"
               if self.runs_cut_short else ""),
            f"arm start skew   : {self.start_skew_s * 1e3:.3f} ms (largest over the runs)",
            f"recorded         : {self.recorded_seconds:.1f} s in {self.wall_seconds:.1f} s",
            f"output           : {self.out_dir}",
        ]
        if self.runs_already_done:
            lines.append(f"resumed          : {self.runs_already_done} of {self.runs_planned} runs were done "
                         f"by earlier sessions (journal {self.journal}); not run again")
        if self.runs_planned:
            pass_txt = f" (pass {self.plan_pass + 1})" if self.plan_pass else ""
            lines.append(f"plan progress    : {self.plan_runs_done} of {self.runs_planned} runs done{pass_txt}")
        fk = self.final_keypoints
        if fk.get("enabled"):
            lines.append(f"final keypoints  : {fk['runs_done']} run(s), {fk['frames_with_final']} of {fk['frames']} "
                         f"frames of {fk['episodes']} episode(s)"
                         + (f"; {fk['tangled_frames']} frame(s) flagged tangled (a grid folded over itself or a "
                            f"chain turned back: `tangled` in /keypoints/final)" if fk.get("tangled_frames") else "")
                         + (f"; {fk['runs_failed']} run(s) failed" if fk["runs_failed"] else "")
                         + (f"; {fk['runs_pending']} run(s) pending (the next session on the folder tracks them)"
                            if fk["runs_pending"] else ""))
        for init in self.live_init:
            lines.append(f"live init        : {init['line']}")
        for label in self.runs_cut_short:
            lines.append(f"cut short        : {label}")
        if self.keypoints_recorded or self.tracking_gaps:
            lines.append(f"tracking gaps    : {self.tracking_gaps} ({self.tracking_gap_frames} frames in them)")
        if self.worker_restarts:
            lines.append(f"worker restarts  : {self.worker_restarts}")
        for label in self.runs_skipped:
            lines.append(f"skipped          : {label}")
        for inc in self.incidents[-10:]:
            lines.append(f"incident         : {inc}")
        if self.faults_recovered:
            lines.append(f"faults recovered : {self.faults_recovered}")
        if self.low_disk_pauses:
            lines.append(f"low-disk pauses  : {self.low_disk_pauses}")
        if self.stopped_early:
            lines.append(f"stopped early    : {self.stopped_early}")
        for e in self.errors + self.runs_failed:
            lines.append(f"problem          : {e}")
        return "\n".join(lines)

    def write(self, path: Path) -> None:
        """Write the summary as JSON to ``path`` atomically (a temporary file, fsynced, renamed over it).

        On an error (a full disk) the temporary file is removed and an earlier ``path`` stays as it was.
        """
        tmp = path.with_name(path.name + ".tmp")
        try:
            with open(tmp, "w") as f:
                f.write(json.dumps(self.to_dict(), indent=2))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
