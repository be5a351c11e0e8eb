"""File-system helpers shared by the recorder and the session journal."""

from __future__ import annotations

import os
import shutil
from pathlib import Path


def fsync_dir(path: Path) -> None:
    """fsync a directory, so a file created or renamed in it survives a power cut."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def free_bytes(path: Path) -> int:
    """Free bytes on the file system holding ``path`` (for an unprivileged writer)."""
    return shutil.disk_usage(path).free


class SpaceReserve:
    """``size`` bytes held in ``<directory>/.trackdeform.reserve`` while a session runs.

    When the disk fills up (ENOSPC), :meth:`release` frees them so the journal record and the
    summary saying why the session stopped can still be written.
    """

    NAME = ".trackdeform.reserve"

    def __init__(self, directory: Path, size: int = 1 << 20) -> None:
        self.path = Path(directory) / self.NAME
        self.held = False
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                os.posix_fallocate(fd, 0, size)
            finally:
                os.close(fd)
            self.held = True
        except OSError:
            self.path.unlink(missing_ok=True)  # too little space already: the guards will say so

    def release(self) -> None:
        """Give the space back (idempotent)."""
        self.path.unlink(missing_ok=True)
        self.held = False
