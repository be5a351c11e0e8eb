"""One entry point for any recorded sequence: episodes or the paper's layout, chosen from what the path is."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from tdrecord.episodes import ACTIVE_SUFFIX, episode_files, read_episode_metadata, read_episodes, unfinished_message
from tdrecord.paper import (
    RGBD_FILE,
    npz_member_header,
    paper_calibration,
    paper_layout_files,
    read_paper_layout,
    verify_npz,
)
from tdrecord.sequence import DatasetError, Sequence


class Calibration(NamedTuple):
    """What a dataset says about its camera: K (3, 3), image size px, T_world_cam (4, 4), bases (4, 4) or None."""

    K: np.ndarray
    width: int
    height: int
    T_world_cam: np.ndarray
    T_world_base: dict[str, np.ndarray] | None


def read_sequence(path: str | Path, **options: Any) -> Sequence:
    """Read an episode ``.mcap``, a folder of episodes, or a folder (or its ``rgbd.npz``) in the paper's layout.

    ``options`` go to the chosen reader (``camera_id`` for episodes; ``world``, ``fps``, ``align`` for the
    paper layout).
    """
    path = Path(path)
    if path.is_file() and path.name == RGBD_FILE:
        return read_paper_layout(path.parent, **options)
    if path.is_dir() and (path / RGBD_FILE).is_file():
        return read_paper_layout(path, **options)
    if path.name.endswith(ACTIVE_SUFFIX) or path.suffix == ".mcap":
        return read_episodes(path, **options)
    if path.is_dir():
        files, active = episode_files(path)
        if files or active:
            return read_episodes(path, **options)
        raise DatasetError(f"{path}: neither episode .mcap files nor a {RGBD_FILE} (the paper's layout)")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    raise DatasetError(f"{path}: not an episode .mcap, a folder of them, or a folder with {RGBD_FILE}")


def read_calibration(path: str | Path) -> Calibration:
    """A dataset's camera calibration without reading its frames (cheap: metadata / calibration file only)."""
    path = Path(path)
    folder = path.parent if path.name == RGBD_FILE else path
    if folder.is_dir() and (folder / RGBD_FILE).is_file():
        K, T_world_cam, bases = paper_calibration(folder, "left")
        shape, _ = npz_member_header(folder / RGBD_FILE, "color")
        return Calibration(K, int(shape[2]), int(shape[1]), T_world_cam, bases)
    files, active = episode_files(path) if path.exists() else ([], [])
    if path.is_file() and active:
        raise DatasetError(unfinished_message(path))
    if files:
        try:
            cal = read_episode_metadata(files[0]).get("calibration") or {}
        except ValueError:
            cal = {}
        if {"K", "T_world_cam", "width", "height"} <= set(cal):
            bases = cal.get("T_world_base")
            return Calibration(
                np.asarray(cal["K"], dtype=np.float64).reshape(3, 3), int(cal["width"]), int(cal["height"]),
                np.asarray(cal["T_world_cam"], dtype=np.float64).reshape(4, 4),
                {k: np.asarray(v, dtype=np.float64).reshape(4, 4) for k, v in bases.items()} if bases else None,
            )
    seq = read_sequence(path)
    return Calibration(seq.K, seq.width, seq.height, seq.T_world_cam, seq.T_world_base)




def verify_sequence_files(path: str | Path, *, except_streamed: bool = False, structure_only: bool = False) -> None:
    """Check a paper-layout dataset's .npz files completely (zip CRCs) before a long job reads them.

    Raises DatasetError naming the first corrupt file; episode files need no check here (MCAP chunks
    carry their own CRCs, checked as they are read). except_streamed: leave out ``rgbd.npz``'s depth and colour
    arrays, for a caller that reads every frame's (``Sequence.frames.iter_depth``), whose stream checks those
    CRCs itself at their end. structure_only: only that every file opens as a zip (cheap; catches truncation).
    """
    path = Path(path)
    folder = path.parent if path.name == RGBD_FILE else path
    if folder.is_dir() and (folder / RGBD_FILE).is_file():
        for f in paper_layout_files(folder):
            skip = ("depth.npy", "color.npy") if except_streamed and f.name == RGBD_FILE else ()
            verify_npz(f, skip, structure_only)
