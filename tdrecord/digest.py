"""A per-episode digest: the small JSON channels of an episode in a file beside it, readable without its images.

MCAP chunks hold every channel together, so reading an episode's ``/keypoints`` or ``frame_info`` decompresses
every image chunk too (~130 MB per 5 s episode at 1280x720). The recorder therefore also writes, when it has
finished an episode, ``episode_NNNNNN.digest.json.gz`` beside ``episode_NNNNNN.mcap``: the exact JSON payloads
of the episode's ``/cam/<id>/frame_info``, ``/keypoints`` and ``/ground_truth/keypoints`` messages with their
log times. The MCAP file stays the source of truth: a digest is written only after its episode is final and
renamed, and a reader falls back to the MCAP file when the digest is missing (a recovered file) or unusable.
"""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path
from typing import Any

import orjson

DIGEST_SUFFIX = ".digest.json.gz"
DIGEST_FORMAT = "trackdeform-digest/1"


def digest_path(episode: Path) -> Path:
    """``episode_NNNNNN.digest.json.gz`` beside ``episode_NNNNNN.mcap``."""
    episode = Path(episode)
    return episode.with_name(episode.name.removesuffix(".mcap") + DIGEST_SUFFIX)


def digest_topic(topic: str) -> bool:
    """Whether a channel goes into the digest: frame info, keypoints, ground truth (not the 250 Hz arm states)."""
    return topic.endswith("/frame_info") or topic in ("/keypoints", "/ground_truth/keypoints")


class DigestWriter:
    """Collects the digest's messages while an episode is written (JSON text as recorded, log time ns)."""

    def __init__(self) -> None:
        self.messages: list[tuple[str, int, str]] = []

    def add(self, topic: str, log_time_ns: int, text: str) -> None:
        """Keep one JSON message if its channel belongs in the digest."""
        if digest_topic(topic):
            self.messages.append((topic, int(log_time_ns), text))

    def write(self, episode: Path, n_frames: int) -> Path:
        """Write the digest of the finished ``episode`` (temporary name, fsync, rename); returns its path."""
        out = digest_path(episode)
        body = ('{"format":' + json.dumps(DIGEST_FORMAT) + ',"episode":' + json.dumps(Path(episode).name)
                + f',"n_frames":{int(n_frames)},"messages":['
                + ",".join(f"[{json.dumps(t)},{lt},{text}]" for t, lt, text in self.messages) + "]}")
        tmp = out.with_name(out.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(gzip.compress(body.encode(), compresslevel=1))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, out)
        return out


def read_digest(episode: Path) -> list[tuple[str, int, dict[str, Any]]] | None:
    """The digest of ``episode`` as (topic, log time ns, decoded JSON) in recorded order, or None when there is
    none or it does not belong to this episode / cannot be read (then read the MCAP file instead)."""
    path = digest_path(episode)
    try:
        d = orjson.loads(gzip.decompress(path.read_bytes()))  # ~4x json's speed: digests are mostly ground truth
    except (OSError, EOFError, ValueError):  # orjson.JSONDecodeError is a ValueError
        return None
    if not isinstance(d, dict) or d.get("format") != DIGEST_FORMAT or d.get("episode") != Path(episode).name:
        return None
    try:
        return [(str(t), int(lt), msg) for t, lt, msg in d["messages"]]
    except (KeyError, TypeError, ValueError):
        return None
