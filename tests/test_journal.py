"""The session journal: round trip, torn lines, plan mismatch, and sessions resuming where they stopped.

Sessions run the mock station in simulated time (rope only, fast, 10 fps, 1 s episodes: about a
second a run), like tests/test_execution.py.
"""

from __future__ import annotations

import io
import json
import logging
import os
from pathlib import Path
from typing import Any

import pytest
import yaml

from drivers.clock import SimClock
from orchestrator import cli
from orchestrator.config import DEFAULT_CONFIG, Config, load_config
from orchestrator.journal import JOURNAL_NAME, Journal, JournalError, JournalState, read_journal
from orchestrator.plan import build_plan
from orchestrator.progress import Progress
from orchestrator.session import Session, Station
from tdrecord import read_episode_metadata
from trajectories.program import library_path


def make_config(repeats: int = 1, speeds: tuple[str, ...] = ("fast",), program: str = "rope_swing") -> Config:
    """The small simulated-time mock config of the execution tests, with ``repeats`` and ``speeds``."""
    cfg = load_config(DEFAULT_CONFIG, {
        "clock": "sim", "station.camera.width": 160, "station.camera.height": 120,
        "tracking.enabled": False, "bus.enabled": False,
        "station.camera.fps": 10, "plan.speeds": list(speeds), "plan.episode_seconds": 1.0,
        "plan.repeats": repeats,
    })
    data = cfg.model_dump()
    data["plan"]["objects"] = [o for o in data["plan"]["objects"] if o["name"] == "rope"]
    data["plan"]["objects"][0]["programs"] = [program]
    return Config.model_validate(data)


def records(out: Path, kind: str) -> list[dict[str, Any]]:
    """The journal's records of one type, in file order."""
    return [r for r in read_journal(out / JOURNAL_NAME).records if r["type"] == kind]


def episode_files(out: Path) -> list[Path]:
    return sorted(out.glob("episode_*.mcap"))


def index_of(path: Path) -> int:
    return int(path.name.split("_")[1].split(".")[0])


class CrashOnStart:
    """``on_station`` hook: the ``n``-th motion start (counted over the session) raises, like a crash mid-run."""

    def __init__(self, n: int | None) -> None:
        self.n, self.starts = n, 0

    def __call__(self, station: Station) -> None:
        arm = station.arms["left"]
        start = arm.start_motion

        def counted(motion: Any) -> None:  # noqa: ANN401
            self.starts += 1
            if self.n is not None and self.starts == self.n:
                raise RuntimeError("simulated crash")
            start(motion)

        arm.start_motion = counted  # type: ignore[method-assign]


def session(cfg: Config, out: Path, hook: CrashOnStart | None = None, progress: Progress | None = None) -> Session:
    return Session(cfg, out, SimClock(), on_station=hook, progress=progress)


# ---------------------------------------------------------------------- the file
def test_round_trip_and_every_record_is_fsynced(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = make_config()
    synced: list[int] = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd))[1])
    j = Journal.open(tmp_path, cfg)
    assert j.created and j.header["format"] == "trackdeform-journal/1"
    key = {"object": "rope", "program": "rope_swing", "speed": "fast", "repeat": 0}
    n_before = len(synced)
    j.append({"type": "start", "pass": 0, **key, "attempt": 1})
    assert len(synced) == n_before + 1  # fsynced before append returns
    j.append({"type": "run", "pass": 0, **key, "outcome": "done", "episodes": ["episode_000000.mcap"]})
    j.close()

    again = Journal.open(tmp_path, cfg)
    try:
        assert not again.created and again.fingerprint == j.fingerprint
        assert [r["type"] for r in again.records] == ["start", "run"]
        st = again.state()
        key0 = ("rope", "rope_swing", "fast", 0)
        assert set(st.done) == {key0} and st.attempts == {key0: 1}
        assert st.interrupted == set()
    finally:
        again.close()
    lines = (tmp_path / JOURNAL_NAME).read_text().splitlines()
    assert len(lines) == 3 and all(isinstance(json.loads(x), dict) for x in lines)


def test_a_second_session_on_the_same_folder_is_refused_while_the_first_runs(tmp_path: Path) -> None:
    first = Journal.open(tmp_path, make_config())
    try:
        with pytest.raises(JournalError, match="another session is recording into this folder"):
            Journal.open(tmp_path, make_config())
    finally:
        first.close()
    Journal.open(tmp_path, make_config()).close()  # free again


def test_torn_last_line_is_ignored_with_a_warning_and_cut_off(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    cfg = make_config()
    j = Journal.open(tmp_path, cfg)
    key = {"object": "rope", "program": "rope_swing", "speed": "fast", "repeat": 0}
    j.append({"type": "run", "pass": 0, **key, "outcome": "done"})
    j.close()
    path = tmp_path / JOURNAL_NAME
    with open(path, "ab") as f:  # a crash in the middle of writing the next record
        f.write(b'{"type":"run","pass":0,"object":"rope","prog')
    with caplog.at_level(logging.WARNING, logger="orchestrator.journal"):
        j = Journal.open(tmp_path, cfg)
    assert "torn last line" in caplog.text and JOURNAL_NAME in caplog.text
    assert set(j.state().done) == {("rope", "rope_swing", "fast", 0)}
    j.append({"type": "run", "pass": 0, **{**key, "repeat": 1}, "outcome": "failed"})
    j.close()
    lines = path.read_bytes().split(b"\n")
    assert lines[-1] == b"" and all(json.loads(x) for x in lines[:-1])  # the new record did not glue onto the tear
    assert [r.get("outcome") for r in read_journal(path).records] == ["done", "failed"]


def test_a_journal_of_another_plan_is_refused_naming_the_file(tmp_path: Path) -> None:
    Journal.open(tmp_path, make_config(speeds=("fast",))).close()
    before = (tmp_path / JOURNAL_NAME).read_bytes()
    with pytest.raises(JournalError) as err:
        Journal.open(tmp_path, make_config(speeds=("slow", "fast")))
    msg = str(err.value)
    assert str(tmp_path / JOURNAL_NAME) in msg and "different plan" in msg
    assert "plan.speeds" in msg and "--fresh" in msg and "--out" in msg
    assert (tmp_path / JOURNAL_NAME).read_bytes() == before  # nothing changed, nothing deleted
    # a session refuses before it touches the folder
    with pytest.raises(JournalError):
        session(make_config(speeds=("slow", "fast")), tmp_path).run()
    assert not list(tmp_path.glob("episode_*")) and not (tmp_path / "summary.json").exists()


def test_a_changed_program_file_is_another_plan_but_more_repeats_are_not(tmp_path: Path) -> None:
    prog = tmp_path / "swing.yaml"
    prog.write_bytes(library_path("rope_swing").read_bytes())
    out = tmp_path / "out"
    Journal.open(out, make_config(program=str(prog))).close()
    Journal.open(out, make_config(program=str(prog), repeats=3)).close()  # repeats extend the same plan
    prog.write_bytes(prog.read_bytes() + b"\n# edited\n")
    with pytest.raises(JournalError, match=r"differs in: programs\."):
        Journal.open(out, make_config(program=str(prog)))


# ---------------------------------------------------------------------- sessions
def test_a_crashed_session_resumes_with_the_rest_only(tmp_path: Path) -> None:
    out = tmp_path / "out"
    cfg = make_config(repeats=3)
    crash = CrashOnStart(2)  # run 0 completes; run 1 crashes once its settle episode is recorded
    with pytest.raises(RuntimeError, match="simulated crash"):
        session(cfg, out, crash).run()
    first_files = {p: p.read_bytes() for p in episode_files(out)}
    done = records(out, "run")
    assert [(r["repeat"], r["outcome"]) for r in done] == [(0, "done")]
    assert sorted(done[0]["episodes"]) == done[0]["episodes"] and len(done[0]["episodes"]) >= 2
    assert {p.name for p in first_files} > set(done[0]["episodes"])  # plus the crashed run's partial episode
    st = JournalState.of(read_journal(out / JOURNAL_NAME).records)
    assert st.interrupted == {("rope", "rope_swing", "fast", 1)}

    log = io.StringIO()
    again = CrashOnStart(None)
    summary = session(cfg, out, again, Progress(stream=log)).run()
    expected = "resuming: 1 of 3 runs already done, continuing with rope · rope_swing · fast · #2 (attempt 2"
    assert expected in log.getvalue()
    assert again.starts == 2  # only runs 1 and 2 ran
    assert summary.runs_already_done == 1 and summary.runs_done == 2 and not summary.runs_failed, summary.text()
    assert summary.plan_runs_done == 3 and "resumed          : 1 of 3 runs" in summary.text()
    assert [(r["repeat"], r["outcome"]) for r in records(out, "run")] == [(0, "done"), (1, "done"), (2, "done")]

    # numbering went on after the crashed session's files, which are untouched
    new = [p for p in episode_files(out) if p not in first_files]
    assert min(index_of(p) for p in new) == max(index_of(p) for p in first_files) + 1
    assert [index_of(p) for p in episode_files(out)] == list(range(len(episode_files(out))))
    assert all(p.read_bytes() == data for p, data in first_files.items())
    assert summary.episodes == new

    # the cut-short attempt and the re-run of repeat 1 tell themselves apart
    meta = {p.name: read_episode_metadata(p) for p in episode_files(out)}
    rep1 = [m for m in meta.values() if m["repeat"] == 1]
    assert {m["attempt"] for m in rep1} == {1, 2}
    first_try = [m for m in rep1 if m["attempt"] == 1]
    assert all(m["complete"] is False or m["chunk_index"] == 0 for m in first_try)
    assert len({m["session_started"] for m in rep1}) == 2
    assert all(m["attempt"] == 1 for m in meta.values() if m["repeat"] != 1)


def test_a_stop_cuts_a_run_short_and_resume_reruns_it_from_its_start(tmp_path: Path) -> None:
    out = tmp_path / "out"
    cfg = make_config(repeats=2)
    one_run = session(make_config(), tmp_path / "probe").run().recorded_seconds  # how long one run records

    stopped = session(cfg, out).run(max_seconds=one_run + 2.0)  # two episodes into the second run
    assert len(stopped.runs_cut_short) == 1 and "#2" in stopped.runs_cut_short[0], stopped.text()
    assert "cut short        : rope · rope_swing · fast · #2" in stopped.text()
    assert stopped.plan_runs_done == 1 and "plan progress    : 1 of 2 runs done" in stopped.text()
    assert [r["repeat"] for r in records(out, "run")] == [0]  # the cut-short run has no record
    n_stopped = len(episode_files(out))

    resumed = session(cfg, out).run()
    assert resumed.runs_already_done == 1 and resumed.runs_done == 1 and not resumed.runs_cut_short
    assert resumed.recorded_seconds == pytest.approx(one_run)  # the whole run again, from its start
    rerun = [read_episode_metadata(p) for p in resumed.episodes]
    assert [m["chunk_index"] for m in rerun] == list(range(len(rerun)))
    assert all(m["repeat"] == 1 and m["attempt"] == 2 for m in rerun)
    assert min(index_of(p) for p in resumed.episodes) == n_stopped


def test_failed_runs_are_retried_on_resume_and_a_finished_plan_has_nothing_left(tmp_path: Path) -> None:
    out = tmp_path / "out"
    cfg = make_config(repeats=2)

    def broken(station: Station) -> None:
        station.arms["right"].inject_fault(station.clock.now() + 2.35, recoverable=False)  # type: ignore[attr-defined]

    failed = Session(cfg, out, SimClock(), on_station=broken).run()
    assert failed.runs_done == 0 and len(failed.runs_failed) == 2
    assert [r["outcome"] for r in records(out, "run")] == ["failed", "skipped"]
    assert "device fault" in records(out, "run")[0]["reason"]

    ok = session(cfg, out).run()  # next night: the arm was repaired
    assert ok.runs_already_done == 0 and ok.runs_done == 2 and not ok.runs_failed, ok.text()

    log = io.StringIO()
    nothing = session(cfg, out, progress=Progress(stream=log)).run()
    assert "all 2 run(s) of the plan are already done" in log.getvalue()
    assert nothing.runs_already_done == 2 and nothing.episodes == [] and nothing.frames_captured == 0
    assert nothing.plan_runs_done == 2


def test_a_larger_repeat_count_continues_the_same_plan(tmp_path: Path) -> None:
    out = tmp_path / "out"
    first = session(make_config(repeats=1), out).run()
    more = session(make_config(repeats=2), out).run()
    assert more.runs_already_done == 1 and more.runs_done == 1 and more.plan_runs_done == 2
    assert {read_episode_metadata(p)["repeat"] for p in more.episodes} == {1}
    assert not set(first.episodes) & set(more.episodes)


def test_loop_mode_starts_another_pass_when_the_plan_is_done(tmp_path: Path) -> None:
    out = tmp_path / "out"
    cfg = make_config()
    one = session(cfg, out).run()
    looped = session(cfg, out).run(max_seconds=one.recorded_seconds, loop=True)
    assert looped.runs_done == 1 and looped.plan_pass == 1 and looped.runs_already_done == 0
    assert {read_episode_metadata(p)["plan_pass"] for p in looped.episodes} == {1}
    assert [(r["pass"], r["outcome"]) for r in records(out, "run")] == [(0, "done"), (1, "done")]


# ---------------------------------------------------------------------- command line
def _write_config(tmp_path: Path, cfg: Config, name: str = "station.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    return path


def _run_cli(argv: list[str], monkeypatch: pytest.MonkeyPatch) -> int:
    monkeypatch.setattr(cli, "_install_signal_handlers", lambda *a: None)  # keep pytest's Ctrl-C
    return cli.main(argv)


def test_cli_resumes_by_default_and_fresh_moves_the_journal_aside(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    conf = _write_config(tmp_path, make_config(repeats=2))
    out = tmp_path / "out"
    base = ["run", str(conf), "--out", str(out), "--no-tracking"]
    assert _run_cli(base, monkeypatch) == 0
    n_first = len(episode_files(out))
    capsys.readouterr()

    assert _run_cli(base, monkeypatch) == 0  # nothing left to do is not a failure
    text = capsys.readouterr()
    assert "nothing left to do" in text.err and "resumed          : 2 of 2 runs" in text.out
    assert len(episode_files(out)) == n_first

    assert _run_cli([*base, "--fresh"], monkeypatch) == 0
    text = capsys.readouterr()
    aside = list(out.glob("session.journal.*.jsonl"))
    assert len(aside) == 1 and aside[0].name in text.err
    assert [r["outcome"] for r in read_journal(aside[0]).records if r["type"] == "run"] == ["done", "done"]
    assert [r["outcome"] for r in records(out, "run")] == ["done", "done"]  # the plan recorded again
    files = episode_files(out)
    assert len(files) == 2 * n_first and [index_of(p) for p in files] == list(range(len(files)))

    other = _write_config(tmp_path, make_config(repeats=2, speeds=("medium",)), "other.yaml")
    assert _run_cli(["run", str(other), "--out", str(out), "--no-tracking"], monkeypatch) == 2
    err = capsys.readouterr().err
    assert f"error: {out / JOURNAL_NAME}: this folder's journal was written for a different plan" in err
    assert len(episode_files(out)) == len(files)


def test_cli_run_without_out_resumes_the_unfinished_session_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    data = make_config(repeats=2).model_dump(mode="json")
    data["output"]["directory"] = str(tmp_path / "runs")
    conf = _write_config(tmp_path, Config.model_validate(data))
    assert _run_cli(["run", str(conf), "--no-tracking", "--seconds", "3"], monkeypatch) == 0
    folders = list((tmp_path / "runs").iterdir())
    assert len(folders) == 1 and len(build_plan(Config.model_validate(data).plan)) == 2
    capsys.readouterr()

    assert _run_cli(["run", str(conf), "--no-tracking"], monkeypatch) == 0
    err = capsys.readouterr().err
    assert f"resuming the unfinished session in {folders[0]}" in err
    assert list((tmp_path / "runs").iterdir()) == folders
    assert [r["outcome"] for r in records(folders[0], "run")] == ["done", "done"]


@pytest.mark.slow
def test_sigkill_mid_session_then_resume_records_every_run_once(tmp_path: Path) -> None:
    """A real SIGKILL (no cleanup at all) after the first journaled run; the next session does the rest."""
    import signal
    import subprocess
    import sys
    import time

    from tests.conftest import REPO

    cfg = make_config(repeats=3)
    conf = _write_config(tmp_path, cfg)
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "orchestrator.cli", "run", str(conf), "--out", str(out),
                             "--no-tracking"], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if (out / JOURNAL_NAME).exists() and records(out, "run"):
                break
            time.sleep(0.01)
        assert proc.poll() is None, "the session ended before it could be killed"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(30)
    done_before = {r["repeat"] for r in records(out, "run") if r["outcome"] == "done"}
    assert 1 <= len(done_before) < 3

    summary = session(cfg, out).run()  # recovers the killed session's .active file, then the rest of the plan
    assert summary.runs_already_done == len(done_before) and summary.runs_done == 3 - len(done_before)
    done = [r["repeat"] for r in records(out, "run") if r["outcome"] == "done"]
    assert sorted(done) == [0, 1, 2]  # every run recorded as done exactly once
    files = episode_files(out)
    assert not list(out.glob("*.active"))
    # numbered on without reuse, past any empty .active file the kill left (quarantined by the recovery)
    numbers = sorted(index_of(p) for p in [*files, *out.glob("quarantine/episode_*")])
    assert numbers == list(range(len(numbers)))
    metas = [read_episode_metadata(p) for p in files]
    for r in records(out, "run"):  # a done run's files are all there, finished
        assert all((out / name).exists() for name in r["episodes"])
    assert {m["repeat"] for m in metas} == {0, 1, 2}
