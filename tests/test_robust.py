"""A night alone (issue 12): a full disk, a second writer on a live folder, recovered metadata, clean errors.

Sessions run the small simulated-time mock station of tests/test_journal.py. The full-disk tests
mount a small tmpfs (root only; skipped with the reason otherwise) or inject OSError(ENOSPC).
One file (~550 lines) on purpose: the failure cases share the killed-writer and full-disk fixtures.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.clock import SimClock
from orchestrator import cli
from orchestrator import recorder as recorder_mod
from orchestrator import recovery as recovery_mod
from orchestrator.journal import JOURNAL_NAME, read_journal
from orchestrator.recorder import EpisodeWriter, Recorder
from orchestrator.recovery import recover_active
from orchestrator.session import Session
from tdrecord import read_episode_metadata, read_episodes
from tests.conftest import REPO, make_frame
from tests.test_journal import _write_config, make_config


def runs(out: Path) -> list[dict[str, Any]]:
    return [r for r in read_journal(out / JOURNAL_NAME).records if r["type"] == "run"]


def folder_state(out: Path) -> dict[str, tuple[int, int]]:
    """name -> (size, mtime ns) of every file under ``out``: what 'changes nothing' compares."""
    return {str(p.relative_to(out)): (p.stat().st_size, p.stat().st_mtime_ns) for p in out.rglob("*") if p.is_file()}


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 6 MiB tmpfs (root only), unmounted afterwards."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root; the ENOSPC injection tests cover the recorder")
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


# ---------------------------------------------------------------------- 1. nothing reported done that is not
def test_a_failed_close_stays_failed_and_is_never_finished(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The close of an episode in its grace period fails (ENOSPC): it is not finished, now or at stop."""
    real_finish = recorder_mod.Writer.finish

    def failing_finish(self: Any) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(recorder_mod.Writer, "finish", failing_finish)
    rec = Recorder("cam0", close_grace=2)
    rec.open_episode(tmp_path / "episode_000000.mcap", {"object": "rope"})
    rec.frame(make_frame(0), np.eye(4))
    rec.close_episode({"complete": True})
    rec.open_episode(tmp_path / "episode_000001.mcap", {"object": "rope"})
    for i in range(1, 5):  # the second frame ends episode 0's grace period: its close fails
        rec.frame(make_frame(i), np.eye(4))
    rec.close_episode({"complete": True})
    rec.open_episode(tmp_path / "episode_000002.mcap", {"object": "rope"})  # ignored: the recorder failed
    rec.stop()
    monkeypatch.setattr(recorder_mod.Writer, "finish", real_finish)
    assert rec.finished == []
    assert rec.failed is not None and "episode_000000.mcap" in rec.failed and "No space left" in rec.failed
    assert (tmp_path / "episode_000000.mcap.active").exists() and not (tmp_path / "episode_000000.mcap").exists()
    assert (tmp_path / "episode_000001.mcap.active").exists()  # left for recovery, not reported finished
    assert not list(tmp_path.glob("episode_000002*"))  # no episode opened after the failure
    assert rec.dropped_after_failure >= 4


def test_enospc_mid_episode_stops_the_recorder_with_one_log_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    calls = {"n": 0}
    real_write = EpisodeWriter.write_frame

    def write_frame(self: EpisodeWriter, frame: Any, T: np.ndarray) -> None:
        calls["n"] += 1
        if calls["n"] >= 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_write(self, frame, T)

    monkeypatch.setattr(EpisodeWriter, "write_frame", write_frame)
    rec = Recorder("cam0", close_grace=0)
    with caplog.at_level(logging.INFO, logger="orchestrator.recorder"):
        rec.open_episode(tmp_path / "episode_000000.mcap", {"object": "rope"})
        for i in range(50):
            rec.frame(make_frame(i), np.eye(4))
        rec.open_episode(tmp_path / "episode_000001.mcap", {"object": "rope"})
        rec.stop()
    assert rec.failed is not None and "Errno 28" in rec.failed
    assert rec.finished == [] and len(rec.errors) == 1
    assert [r.message for r in caplog.records] == [f"recording stopped: {rec.failed}"]
    assert not any(r.exc_info for r in caplog.records)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode_000000.mcap.active"]


def test_disk_full_mid_session_fails_the_run_and_keeps_what_is_readable(
    small_disk: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A real full disk (6 MiB tmpfs, min_free_gb 0): the run is journaled failed, one line says why,
    summary.json is whole, rc non-zero; recover on the full disk says why it cannot, then works."""
    cfg = make_config(repeats=6)
    data = cfg.model_dump()
    data["output"]["min_free_gb"] = 0.0
    cfg = type(cfg).model_validate(data)
    conf = _write_config(small_disk.parent, cfg)
    out = small_disk / "out"
    monkeypatch.setattr(cli, "_install_signal_handlers", lambda *a: None)
    rc = cli.main(["run", str(conf), "--out", str(out), "--no-tracking"])
    cap = capsys.readouterr()
    assert rc == 1
    assert "Traceback" not in cap.err + cap.out
    lines = [ln for ln in cap.err.splitlines() if ln.startswith("error: recording stopped:")]
    assert len(lines) == 1 and "No space left on device" in lines[0], cap.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped_early"].startswith("recording failed:")
    records = runs(out)
    assert records and records[-1]["outcome"] == "failed" and "No space left" in records[-1]["reason"]
    for r in records:  # nothing is journaled done that is not: a done run's files are all finished
        if r["outcome"] == "done":
            for name in r["episodes"]:
                assert (out / name).is_file() and read_episode_metadata(out / name)["complete"]
    assert [p for p in out.glob("*.active") if p.stat().st_size == 0] == []
    failed_files = {n.removesuffix(".mcap") for n in records[-1]["episodes"]}
    assert {p.name.removesuffix(".mcap.active") for p in out.glob("*.active")} <= failed_files
    assert not (out / ".trackdeform.reserve").exists()

    before = folder_state(out)
    rc = cli.main(["recover", str(out)])
    cap = capsys.readouterr()
    assert not list(out.glob("*.recovering"))
    if rc == 1:  # too little space: says so, touches nothing
        assert "not recovered" in cap.out and "MiB free" in cap.out
        assert folder_state(out) == before
        subprocess.run(["mount", "-o", "remount,size=40m", str(small_disk)], check=True)
        assert cli.main(["recover", str(out)]) == 0
        capsys.readouterr()
    else:
        assert rc == 0
    assert not list(out.glob("*.active")) and not list(out.glob("*.recovering"))
    for p in out.glob("episode_*.mcap"):
        meta = read_episode_metadata(p)
        assert meta["object"] == "rope" and "episode_index" in meta and isinstance(meta["complete"], bool)


def _killed_writer(tmp_path: Path, n: int = 40) -> Path:
    """An .active file with whole chunks in it, as a SIGKILL leaves one (the writer is just dropped)."""
    w = EpisodeWriter(tmp_path / "episode_000003.mcap", "cam0", metadata={"object": "rope"})
    w._w._Writer__chunk_size = 1  # type: ignore[attr-defined]  # a chunk per message: everything is readable
    for i in range(n):
        w.write_frame(make_frame(i), np.eye(4))
    w._file.flush()
    return w.active_path


def test_recover_on_a_nearly_full_disk_says_why_and_touches_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    active = _killed_writer(tmp_path)
    size = active.stat().st_size
    monkeypatch.setattr(recovery_mod, "free_bytes", lambda path: size // 2)
    assert cli.main(["recover", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert f"{active}: not recovered: {active}: needs about" in out and "MiB free" in out
    assert active.stat().st_size == size and not list(tmp_path.glob("*.recovering"))
    assert not (tmp_path / "episode_000003.mcap").exists()


def test_recover_that_hits_enospc_leaves_the_active_file_and_no_partial_copy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    active = _killed_writer(tmp_path)
    size = active.stat().st_size

    def failing_finish(self: Any) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(recovery_mod.Writer, "finish", failing_finish)
    [(path, outcome)] = recover_active(tmp_path)
    assert path == active and outcome.startswith("not recovered") and "No space left" in outcome
    assert active.stat().st_size == size
    assert sorted(p.name for p in tmp_path.iterdir()) == [active.name]  # no .recovering, no 0-byte .mcap


def test_a_journal_that_cannot_be_written_stops_the_session_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from orchestrator.journal import Journal
    from orchestrator.progress import Progress

    real_write = Journal._write

    def write(self: Journal, record: dict[str, Any]) -> None:
        if record.get("type") == "start" and record.get("repeat") == 1:
            raise OSError(errno.ENOSPC, "cannot write the journal: No space left on device", str(self.path))
        real_write(self, record)

    monkeypatch.setattr(Journal, "_write", write)
    lines: list[str] = []
    progress = Progress(enabled=False)
    monkeypatch.setattr(progress, "message", lines.append)
    summary = Session(make_config(repeats=3), tmp_path, SimClock(), progress=progress).run()
    assert summary.stopped_early == f"I/O error: {tmp_path / JOURNAL_NAME}: cannot write the journal: " \
                                    "No space left on device"
    assert [ln for ln in lines if ln.startswith("error:")] == [f"error: session stopped: {summary.stopped_early[11:]}"]
    assert [r["outcome"] for r in runs(tmp_path)] == ["done"]
    assert json.loads((tmp_path / "summary.json").read_text())["stopped_early"] == summary.stopped_early


def _free_sequence(values_gb: list[float]) -> Any:
    """A free_bytes stand-in returning ``values_gb`` in turn (then the last one) for the out folder."""
    seq = list(values_gb)

    def free_bytes(path: Path) -> int:
        v = seq.pop(0) if len(seq) > 1 else seq[0]
        return int(v * 2**30)

    return free_bytes


def _low_disk_config(on_low_disk: str, repeats: int = 1) -> Any:
    cfg = make_config(repeats=repeats)
    data = cfg.model_dump()
    data["output"].update(min_free_gb=1.0, on_low_disk=on_low_disk, disk_check_seconds=0.2,
                          low_disk_poll_seconds=0.01)
    return type(cfg).model_validate(data)


def test_low_disk_mid_episode_closes_it_incomplete_and_stops(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import orchestrator.capture as capture

    monkeypatch.setattr(capture, "free_bytes", _free_sequence([5.0] * 4 + [0.5]))
    summary = Session(_low_disk_config("stop", repeats=2), tmp_path, SimClock()).run()
    assert "only 0.50 GiB free" in (summary.stopped_early or "")
    files = sorted(tmp_path.glob("episode_*.mcap"))
    assert files and read_episode_metadata(files[-1])["complete"] is False
    assert [(r["outcome"], r["reason"].split(":")[0]) for r in runs(tmp_path)] == [("failed", "low disk space")]
    assert summary.runs_done == 0


def test_low_disk_pause_waits_for_space_then_runs_the_item_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import orchestrator.capture as capture

    monkeypatch.setattr(capture, "free_bytes", _free_sequence([5.0] * 4 + [0.5] * 5 + [5.0]))
    summary = Session(_low_disk_config("pause"), tmp_path, SimClock()).run()
    assert summary.low_disk_pauses == 1 and summary.stopped_early is None
    assert [r["outcome"] for r in runs(tmp_path)] == ["failed", "done"]
    assert runs(tmp_path)[1]["attempt"] == 2
    assert all((tmp_path / n).is_file() for n in runs(tmp_path)[1]["episodes"])


# ---------------------------------------------------------------------- 2. one writer per folder
HOLDER = textwrap.dedent("""
    import sys, numpy as np
    from pathlib import Path
    sys.path.insert(0, {repo!r})
    from orchestrator.config import load_config
    from orchestrator.journal import Journal
    from orchestrator.recorder import EpisodeWriter
    from tests.conftest import make_frame
    out = Path({out!r})
    journal = Journal.open(out, load_config({conf!r}))
    w = EpisodeWriter(out / "episode_000001.mcap", "cam0", metadata={{"object": "rope"}})
    for i in range(3):
        w.write_frame(make_frame(i), np.eye(4))
    w._file.flush()
    print("ready", flush=True)
    sys.stdin.read()  # hold the folder until the test closes stdin
    journal.close()
""")


def test_fresh_and_recover_are_refused_on_a_live_sessions_folder(tmp_path: Path) -> None:
    cfg = make_config()
    conf = _write_config(tmp_path, cfg)
    out = tmp_path / "out"
    out.mkdir()
    done = EpisodeWriter(out / "episode_000000.mcap", "cam0", metadata={"object": "rope"})
    done.write_frame(make_frame(0), np.eye(4))
    done.close({"complete": True})
    holder = subprocess.Popen([sys.executable, "-c", HOLDER.format(repo=str(REPO), out=str(out), conf=str(conf))],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "ready"
        before = folder_state(out)
        for argv in (["recover", str(out)], ["run", str(conf), "--out", str(out), "--fresh", "--no-tracking"]):
            proc = subprocess.run([sys.executable, "-m", "orchestrator.cli", *argv], cwd=REPO,
                                  capture_output=True, text=True, timeout=120)
            assert proc.returncode == 2, (argv, proc.stdout, proc.stderr)
            assert "Traceback" not in proc.stderr
            err = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
            assert len(err) == 1 and "locked" in err[0] and str(out) in err[0], proc.stderr
            assert folder_state(out) == before, argv  # nothing moved, recovered or created
    finally:
        holder.communicate("", timeout=30)
    assert cli.main(["recover", str(out)]) == 0  # the holder is gone: now it is a leftover (no whole chunk)
    assert not list(out.glob("*.active")) and (out / "quarantine" / "episode_000001.mcap.active").is_file()


# ---------------------------------------------------------------------- 4. recovered episodes keep their metadata
def test_an_episode_cut_by_a_kill_keeps_its_open_metadata(tmp_path: Path) -> None:
    script = textwrap.dedent(f"""
        import sys, os, signal, numpy as np
        from pathlib import Path
        sys.path.insert(0, {str(REPO)!r})
        from orchestrator.recorder import Recorder
        from tests.conftest import make_frame
        rec = Recorder("cam0")
        rec.open_episode(Path({str(tmp_path)!r}) / "episode_000007.mcap",
                         {{"object": "rope", "program": "rope_swing", "speed": "fast", "episode_index": 7,
                           "calibration": {{"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}}}})
        for i in range(300):
            rec.frame(make_frame(i, 320, 240), np.eye(4))
        import time
        while not rec._q.empty():
            time.sleep(0.01)
        time.sleep(0.2)
        rec._current._file.flush(); os.fsync(rec._current._file.fileno())
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    [(path, outcome)] = recover_active(tmp_path)
    assert outcome.startswith("recovered") and path.name == "episode_000007.mcap"
    meta = read_episode_metadata(path)
    assert meta["object"] == "rope" and meta["program"] == "rope_swing" and meta["speed"] == "fast"
    assert meta["episode_index"] == 7 and meta["calibration"]["K"][2] == [0, 0, 1]
    assert meta["complete"] is False and meta["fault"] is False and meta["recovered"] is True
    seq = read_episodes(path)
    assert seq.metadata["object"] == "rope" and seq.metadata["episodes"][0]["complete"] is False


def test_a_finished_episode_reads_open_and_close_metadata_merged(tmp_path: Path) -> None:
    w = EpisodeWriter(tmp_path / "episode_000000.mcap", "cam0", metadata={"object": "rope", "complete": None})
    w.write_frame(make_frame(0), np.eye(4))
    p = w.close({"complete": True, "fault": False})
    meta = read_episode_metadata(p)
    assert meta["object"] == "rope" and meta["complete"] is True and meta["n_frames"] == 1


# ---------------------------------------------------------------------- 7. clean errors
def _broken_mcaps(tmp_path: Path) -> tuple[Path, list[Path]]:
    w = EpisodeWriter(tmp_path / "episode_000000.mcap", "cam0", metadata={"object": "rope"})
    for i in range(3):
        w.write_frame(make_frame(i), np.eye(4))
    good = w.close({"complete": True})
    data = good.read_bytes()
    truncated, empty, noise = tmp_path / "truncated.mcap", tmp_path / "empty.mcap", tmp_path / "noise.mcap"
    truncated.write_bytes(data[: len(data) // 2])
    empty.write_bytes(b"")
    noise.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    return good, [truncated, empty, noise]


def test_inspect_reports_each_broken_file_in_one_line_and_goes_on(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good, bad = _broken_mcaps(tmp_path)
    assert cli.main(["inspect", str(bad[0]), str(good), *map(str, bad[1:])]) == 2
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err and '  object = "rope"' in cap.out
    errors = [ln for ln in cap.err.splitlines() if ln.startswith("error:")]
    assert [e.split(":")[1].strip() for e in errors[:3]] == [str(p) for p in bad]
    assert errors[3] == "error: 3 of 4 file(s) could not be read"


def test_inspect_into_head_exits_cleanly(tmp_path: Path) -> None:
    good, _ = _broken_mcaps(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "orchestrator.cli", "inspect", *[str(good)] * 300], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.readline()
    proc.stdout.close()  # like `head -1`
    err = proc.stderr.read().decode()
    assert proc.wait(60) == 0 and "Traceback" not in err and "BrokenPipe" not in err, err


def _paper_folder(tmp_path: Path) -> Path:
    from tdrecord import write_paper_layout

    frames = [make_frame(i) for i in range(4)]
    eye = np.tile(np.eye(4), (4, 1, 1))
    folder = tmp_path / "paper"
    write_paper_layout(folder, frames, T_world_cam=np.eye(4), T_world_base={"left": np.eye(4), "right": np.eye(4)},
                       tcp_left=eye, tcp_right=eye)
    return folder


@pytest.mark.parametrize("damage", ["bitflip", "truncate"])
def test_track_refuses_a_corrupt_rgbd_npz_before_tracking(
    tmp_path: Path, damage: str, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = _paper_folder(tmp_path)
    rgbd = folder / "rgbd.npz"
    data = bytearray(rgbd.read_bytes())
    if damage == "bitflip":
        data[len(data) // 2] ^= 0xFF  # inside the colour array: only its CRC notices
        rgbd.write_bytes(bytes(data))
    else:
        rgbd.write_bytes(bytes(data[: len(data) // 2]))
    assert cli.main(["track", str(folder), "--out", str(tmp_path / "o")]) == 2
    cap = capsys.readouterr()
    [line] = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert line.startswith(f"error: {rgbd}:") and ("CRC" in line or "zip" in line), line
    assert not (tmp_path / "o").exists()  # refused before anything was tracked or written


def test_non_utf8_config_and_program_name_the_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    conf = tmp_path / "station.yaml"
    conf.write_bytes(b"station:\n  name: st\xe9\xff\n")
    assert cli.main(["validate", str(conf)]) == 2
    prog = tmp_path / "prog.yaml"
    prog.write_bytes(b"name: \xff\xfe\n")
    assert cli.main(["program", "validate", str(prog)]) == 2
    err = capsys.readouterr().err
    assert f"error: {conf}: not UTF-8 text (byte 0xe9 at offset 19)" in err
    assert f"error: {prog}: not UTF-8 text (byte 0xff at offset 6)" in err
    assert "Traceback" not in err


def test_recover_on_a_missing_folder_fails(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["recover", str(tmp_path / "nope")]) == 2
    assert capsys.readouterr().err.strip() == f"error: {tmp_path / 'nope'}: no such folder"


def test_a_second_signal_during_the_last_flush_still_writes_the_summary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Both signals arrive while the recorder flushes its last episodes: they finish, summary.json is written."""
    stop, finishing = threading.Event(), threading.Event()
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    cli._install_signal_handlers(stop, finishing)
    real_stop = Recorder.stop

    def stop_with_signals(self: Recorder, timeout: float = 60.0) -> None:
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGTERM)
        real_stop(self, timeout)

    monkeypatch.setattr(Recorder, "stop", stop_with_signals)
    try:
        summary = Session(make_config(), tmp_path, SimClock(), stop_event=stop, finishing=finishing).run()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    assert stop.is_set() and summary.episodes
    written = json.loads((tmp_path / "summary.json").read_text())
    assert written["episodes"] == [str(p) for p in summary.episodes]
    assert [r["outcome"] for r in runs(tmp_path)] == ["done"]


def test_malformed_frame_messages_are_logged_once_per_kind(caplog: pytest.LogCaptureFixture) -> None:
    """The worker counts malformed frames and logs one line (no traceback); keypoint messages: tests/test_live.py."""
    from orchestrator.live import KindCounter
    from orchestrator.worker import Worker

    class Payload:
        def __init__(self, data: bytes) -> None:
            self.data = data

        def to_bytes(self) -> bytes:
            return self.data

    class Sample:
        def __init__(self, data: bytes) -> None:
            self.payload = Payload(data)

    class Sub:
        def __init__(self, items: list[bytes]) -> None:
            self.items = items

        def try_recv(self) -> Sample | None:
            return Sample(self.items.pop(0)) if self.items else None

    worker = object.__new__(Worker)  # only what step() touches before tracking: no bus needed
    worker.frame_sub = Sub([b"garbage"] * 20 + [b"TDF1\xff\xff\x00\x00{}"] * 20)
    worker.malformed = KindCounter("frame not tracked", logging.getLogger("trackdeform.worker"))
    with caplog.at_level(logging.WARNING):
        while worker.step():
            pass
    assert worker.malformed.total() == 40
    assert len(caplog.records) == len(worker.malformed.counts) and not any(r.exc_info for r in caplog.records)


@pytest.mark.slow
def test_a_real_live_session_is_not_touched_by_fresh_or_recover(tmp_path: Path) -> None:
    """A real-time session (own process) records; --fresh and recover from other processes are refused and the
    session's files and journal come out as if they had not been tried."""
    import time

    cfg = make_config(repeats=3)
    data = cfg.model_dump(mode="json")
    data["clock"] = "real"
    conf = _write_config(tmp_path, type(cfg).model_validate(data))
    out = tmp_path / "out"
    session = subprocess.Popen([sys.executable, "-m", "orchestrator.cli", "run", str(conf), "--out", str(out),
                                "--no-tracking"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (list(out.glob("episode_*.mcap")) and list(out.glob("*.active"))):
            time.sleep(0.05)
        assert session.poll() is None, "the session ended before the test could try a second writer"
        finished = {p.name: p.read_bytes() for p in out.glob("episode_*.mcap")}
        journal = (out / JOURNAL_NAME).read_bytes()
        for argv in (["recover", str(out)], ["run", str(conf), "--out", str(out), "--fresh", "--no-tracking"]):
            proc = subprocess.run([sys.executable, "-m", "orchestrator.cli", *argv], cwd=REPO,
                                  capture_output=True, text=True, timeout=120)
            assert proc.returncode == 2 and "locked" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert {n: (out / n).read_bytes() for n in finished} == finished
        assert (out / JOURNAL_NAME).read_bytes().startswith(journal)  # only the session appended
        _, err = session.communicate(timeout=120)
    finally:
        if session.poll() is None:
            session.kill()
            session.wait()
    assert session.returncode == 0, err
    records = runs(out)
    assert [r["outcome"] for r in records] == ["done"] * 3
    for r in records:
        for name in r["episodes"]:
            assert read_episode_metadata(out / name)["complete"] is True
    assert not list(out.glob("*.active")) and not list(out.glob("session.journal.*.jsonl"))
