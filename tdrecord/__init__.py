"""Recorded data: episode MCAP files, the paper's published folder layout and its reference npz.

Used by replay, offline tracking, exports and reports; imports only :mod:`tdcommon`. The public
reader API is re-exported here; :mod:`tdrecord.episodes`, :mod:`tdrecord.paper` and
:mod:`tdrecord.sequence` hold the implementation.
"""

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
    "ACTIVE_SUFFIX", "Calibration", "DatasetError", "FrameSource", "RecordedRun", "ReferenceKeypoints", "Sequence",
    "nearest_index", "read_calibration", "read_episode_metadata", "read_episodes", "read_paper_layout",
    "read_reference_npz", "read_sequence", "recorded_runs", "run_key", "verify_sequence_files", "write_paper_layout",
    "write_reference_npz",
]
