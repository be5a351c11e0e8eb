"""Recorded data: episode MCAP files, the paper's published folder layout and its reference npz.

Used by replay, offline tracking, exports and reports; imports only :mod:`tdcommon`. The public
reader API is re-exported here: :func:`load_episode` / :func:`iter_episodes` (:mod:`tdrecord.api`, numpy
arrays per episode) and the readers of :mod:`tdrecord.episodes`, :mod:`tdrecord.paper` and :mod:`tdrecord.sequence`.
"""

from tdrecord.api import Episode, episode_entries, iter_episodes, load_episode, read_manifest
from tdrecord.episodes import ACTIVE_SUFFIX, RecordedRun, read_episode_metadata, read_episodes, recorded_runs, run_key
from tdrecord.io import Calibration, read_calibration, read_sequence, verify_sequence_files
from tdrecord.paper import (
    ReferenceKeypoints,
    read_paper_layout,
    read_reference_npz,
    write_paper_layout,
    write_reference_npz,
)
from tdrecord.sequence import DatasetError, FrameSource, Sequence, nearest_index

__all__ = [
    "ACTIVE_SUFFIX", "Calibration", "DatasetError", "Episode", "FrameSource", "RecordedRun", "ReferenceKeypoints",
    "Sequence", "episode_entries", "iter_episodes", "load_episode", "nearest_index", "read_calibration",
    "read_episode_metadata", "read_episodes", "read_manifest", "read_paper_layout", "read_reference_npz",
    "read_sequence", "recorded_runs", "run_key", "verify_sequence_files", "write_paper_layout",
    "write_reference_npz",
]
