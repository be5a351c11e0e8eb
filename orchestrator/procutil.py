"""Child processes of the session that run below the capture loop's CPU priority."""

from __future__ import annotations

import logging
import os
import subprocess
from typing import Any

log = logging.getLogger(__name__)

NICE = 10  # capture and recording must keep 30 Hz on a small machine; tracking adapts its rate


def popen_nice(cmd: list[str], **kwargs: Any) -> subprocess.Popen[bytes]:
    """``subprocess.Popen(cmd, **kwargs)``, then lower the child's priority by ``NICE`` from this side.

    The priority is not set with ``preexec_fn``: that runs Python in the forked child of a process with
    other threads (zenoh's, the recorder's), where a lock held at the fork never comes free, so the
    child can hang before it execs and ``Popen`` never returns. The child runs at our priority
    for the moments until ``setpriority`` (its imports), which does not matter.
    """
    if "preexec_fn" in kwargs:
        raise ValueError("popen_nice sets the priority itself; preexec_fn is not safe with threads")
    proc: subprocess.Popen[bytes] = subprocess.Popen(cmd, **kwargs)
    try:
        os.setpriority(os.PRIO_PROCESS, proc.pid, os.getpriority(os.PRIO_PROCESS, 0) + NICE)
    except OSError as e:  # the child already gone, or not allowed: it runs, only not lowered
        log.warning("could not lower the priority of %s (pid %d): %s", cmd[:3], proc.pid, e)
    return proc
