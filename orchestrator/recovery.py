"""Recovery of episode files left unfinished by a crash: every readable record rewritten into a valid file.

After SIGKILL the indexed MCAP reader refuses a ``*.mcap.active`` file, but a stream reader returns
every record up to the last complete chunk; rewriting those gives a valid ``*.mcap`` with the open-time
metadata kept and ``complete: false``. What cannot be read is moved to ``quarantine/``. Run at the
start of every session and by ``trackdeform recover``, both under the folder's journal lock.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from mcap.writer import CompressionType, Writer

from orchestrator.fsutil import free_bytes, fsync_dir
from tdrecord.episodes import ACTIVE_SUFFIX, CLOSE_METADATA, OPEN_METADATA

log = logging.getLogger(__name__)

RECOVERY_MARGIN = 1 << 20  # bytes kept free beyond a recovered copy's size


class RecoveryError(RuntimeError):
    """An unfinished file that cannot be recovered now (e.g. too little free space); it is left untouched."""


def recover_active(directory: Path, quarantine: str = "quarantine") -> list[tuple[Path, str]]:
    """Turn leftover ``*.mcap.active`` files into valid ``*.mcap`` files, or quarantine them.

    Every record the stream reader can still read (up to the last complete chunk) is rewritten
    into a new file. Its ``episode`` metadata is the open-time ``episode_open`` record merged with
    the ``episode`` record if the writer got that far, plus ``recovered: true`` and, when the
    episode never closed, ``complete: false``. A file with no readable message is moved to
    ``<directory>/<quarantine>/``. A finished file is never replaced. When the disk has too little
    space for the copy (its size plus 1 MiB), or writing it fails, the ``.active`` file is left as
    it was and the outcome says why. The caller must hold the folder's journal lock (a live session's
    open file is not to be touched). Returns ``(path, outcome)`` pairs.
    """
    results = []
    for active in sorted(Path(directory).glob(f"*{ACTIVE_SUFFIX}")):
        try:
            results.append(_recover_one(active, Path(directory), quarantine))
        except RecoveryError as e:
            log.warning("%s", e)
            results.append((active, f"not recovered: {e}"))
    return results


def _recover_one(active: Path, directory: Path, quarantine: str) -> tuple[Path, str]:
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    final = active.with_name(active.name.removesuffix(ACTIVE_SUFFIX) + ".mcap")
    tmp = final.with_name(final.name + ".recovering")
    tmp.unlink(missing_ok=True)  # left by an earlier recovery that was cut short
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    messages: list[Message] = []
    opened: dict[str, str] = {}
    closed: dict[str, str] = {}
    error = ""
    try:
        with open(active, "rb") as f:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    messages.append(rec)
                elif isinstance(rec, Metadata):
                    if rec.name == OPEN_METADATA:
                        opened.update(rec.metadata)
                    elif rec.name == CLOSE_METADATA:
                        closed.update(rec.metadata)
    except FileNotFoundError:
        raise RecoveryError(f"{active}: vanished while being read (another process is writing this folder)") from None
    except Exception as e:  # truncated tail: keep what was read
        error = f"{type(e).__name__}: {e}"
    messages = [m for m in messages if m.channel_id in channels]
    if not messages or final.exists():
        qdir = directory / quarantine
        qdir.mkdir(exist_ok=True)
        os.replace(active, qdir / active.name)
        reason = "a finished file of that name exists" if final.exists() else "no readable message"
        log.warning("quarantined %s (%s)", active, reason)
        return qdir / active.name, f"quarantined: {reason}"
    need = active.stat().st_size + RECOVERY_MARGIN
    free = free_bytes(directory)
    if free < need:
        raise RecoveryError(
            f"{active}: needs about {need / 2**20:.1f} MiB free for the recovered copy, {directory} has "
            f"{free / 2**20:.1f} MiB; free some space and run `trackdeform recover {directory}` again "
            "(the file is left as it is)"
        )
    meta: dict[str, str] = {**opened, **closed}
    if not closed:
        meta.update(complete=json.dumps(False), fault=json.dumps(False))
    meta.update(recovered=json.dumps(True), recovery_note=json.dumps(error or "complete stream"))
    try:
        with open(tmp, "wb") as out:
            w = Writer(out, compression=CompressionType.ZSTD)
            w.start(profile="", library="trackdeform3d (recovered)")
            sid_map = {sid: w.register_schema(s.name, s.encoding, s.data) for sid, s in schemas.items()}
            cid_map = {
                cid: w.register_channel(c.topic, c.message_encoding, sid_map.get(c.schema_id, 0), c.metadata)
                for cid, c in channels.items()
            }
            for m in messages:
                w.add_message(cid_map[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence)
            if opened:
                w.add_metadata(OPEN_METADATA, opened)
            w.add_metadata(CLOSE_METADATA, meta)
            w.finish()
            out.flush()
            os.fsync(out.fileno())
        os.link(tmp, final)  # fails if a finished file of that name appeared: never replaced
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise RecoveryError(f"{active}: could not write the recovered copy ({e}); the file is left as it is") from e
    tmp.unlink()
    active.unlink(missing_ok=True)
    fsync_dir(final.parent)
    log.warning("recovered %s (%d messages)", final, len(messages))
    return final, f"recovered {len(messages)} messages"
