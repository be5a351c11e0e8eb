"""A per-episode digest: the small JSON channels of an episode in a file beside it, readable without its images.

MCAP chunks hold every channel together, so reading an episode's ``/keypoints`` or ``frame_info`` decompresses
every image chunk too (~130 MB per 5 s episode at 1280x720). The recorder therefore also writes, when it has
finished an episode, ``episode_NNNNNN.digest.json.gz`` beside ``episode_NNNNNN.mcap``: the exact JSON payloads
of the episode's ``/cam/<id>/frame_info`` and ``/keypoints`` messages with their log times and, in mock mode,
each live keypoint set's ground-truth error (mm), computed by the writer from ``/ground_truth/keypoints``
(whose dense samples were most of a digest and of the report's time: format 1 held them instead). The MCAP
file stays the source of truth: a digest is written only after its episode is final and renamed, and a
reader falls back to the MCAP file when the digest is missing (a recovered file) or unusable.
"""

from __future__ import annotations

import gzip
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import orjson

from tdcommon.wire import points_from_json

DIGEST_SUFFIX = ".digest.json.gz"
DIGEST_FORMAT = "trackdeform-digest/2"
_READ_FORMATS = ("trackdeform-digest/1", DIGEST_FORMAT)  # 1: ground-truth messages in place of the errors
GROUND_TRUTH_TOPIC = "/ground_truth/keypoints"
KEYPOINTS_TOPIC = "/keypoints"
# (keypoint message, ground-truth message) pairs of frames -> the ground-truth error of each keypoint set, mm
GtErrors = Callable[[list[tuple[dict[str, Any], dict[str, Any]]]], list[float]]


def digest_path(episode: Path) -> Path:
    """``episode_NNNNNN.digest.json.gz`` beside ``episode_NNNNNN.mcap``."""
    episode = Path(episode)
    return episode.with_name(episode.name.removesuffix(".mcap") + DIGEST_SUFFIX)


def digest_topic(topic: str) -> bool:
    """Whether a channel goes into the digest: frame info, keypoints, ground truth (not the 250 Hz arm states)."""
    return topic.endswith("/frame_info") or topic in (KEYPOINTS_TOPIC, GROUND_TRUTH_TOPIC)


@dataclass
class Digest:
    """A read digest: messages (topic, log time ns, decoded JSON) in recorded order, and frame number ->
    ground-truth error (mm) of its keypoints (None: not computed, the ground truth is among the messages)."""

    messages: list[tuple[str, int, dict[str, Any]]]
    gt_error_mm: dict[int, float] | None


class DigestWriter:
    """Collects the digest's messages while an episode is written (JSON text as recorded, log time ns).

    ``gt_errors`` turns the frames' (keypoints, ground truth) message pairs into errors when the digest is
    written; the ground-truth messages are then not kept in it. Without it they are, as recorded.
    """

    def __init__(self, gt_errors: GtErrors | None = None) -> None:
        self.messages: list[tuple[str, int, str]] = []
        self.gt_errors = gt_errors
        self._keypoints: dict[int, dict[str, Any]] = {}  # frame number -> its last keypoint message
        self._truth: dict[int, dict[str, Any]] = {}  # frame number -> its ground-truth message

    def add(self, topic: str, log_time_ns: int, text: str, obj: dict[str, Any] | None = None) -> None:
        """Keep one JSON message (``obj``: the same message decoded, if at hand) if its channel belongs in it."""
        if not digest_topic(topic):
            return
        if self.gt_errors is not None and topic in (KEYPOINTS_TOPIC, GROUND_TRUTH_TOPIC):
            d = obj if obj is not None else orjson.loads(text)
            fn = int(d.get("frame_number", -1))
            if topic == GROUND_TRUTH_TOPIC:  # kept to the episode's end: its samples as one array, not many dicts
                self._truth[fn] = {**d, "centreline": points_from_json(d.get("centreline"))}
                return
            self._keypoints[fn] = d
        self.messages.append((topic, int(log_time_ns), text))

    def write(self, episode: Path, n_frames: int) -> Path:
        """Write the digest of the finished ``episode`` (temporary name, fsync, rename); returns its path."""
        out = digest_path(episode)
        errors = ""
        if self.gt_errors is not None:
            frames = sorted(set(self._keypoints) & set(self._truth))
            values = self.gt_errors([(self._keypoints[f], self._truth[f]) for f in frames])
            cells = (f"[{f},{json.dumps(float(v) if math.isfinite(v) else None)}]"
                     for f, v in zip(frames, values, strict=True))
            errors = ',"gt_error_mm":[' + ",".join(cells) + "]"
        body = ('{"format":' + json.dumps(DIGEST_FORMAT) + ',"episode":' + json.dumps(Path(episode).name)
                + f',"n_frames":{int(n_frames)}{errors},"messages":['
                + ",".join(f"[{json.dumps(t)},{lt},{text}]" for t, lt, text in self.messages) + "]}")
        tmp = out.with_name(out.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(gzip.compress(body.encode(), compresslevel=1))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, out)
        return out


def read_digest(episode: Path) -> Digest | None:
    """The digest of ``episode``, or None when there is none or it does not belong to this episode / cannot be
    read (then read the MCAP file instead)."""
    path = digest_path(episode)
    try:
        d = orjson.loads(gzip.decompress(path.read_bytes()))  # ~4x json's speed: digests are mostly ground truth
    except (OSError, EOFError, ValueError):  # orjson.JSONDecodeError is a ValueError
        return None
    if not isinstance(d, dict) or d.get("format") not in _READ_FORMATS or d.get("episode") != Path(episode).name:
        return None
    try:
        errors = d.get("gt_error_mm")
        return Digest([(str(t), int(lt), msg) for t, lt, msg in d["messages"]],
                      None if errors is None else {int(f): float("nan") if v is None else float(v) for f, v in errors})
    except (KeyError, TypeError, ValueError):
        return None
