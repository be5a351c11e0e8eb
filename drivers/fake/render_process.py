"""The mock camera's renderer in a child process, so its CPU is not taken under the caller's GIL.

In real time the daemon's capture, joint-state, recording and bus threads share one interpreter; the
rasterisation of a frame (10-35 ms of mostly small numpy operations) held the GIL long enough that the
capture thread fell behind the fake camera's frame queue on two cores. :class:`RenderProcess` runs a
:class:`~drivers.fake.render.SceneRenderer` built from the same arguments in ``python -m
drivers.fake.render_process``: the same inputs give bit-identical frames. Requests and replies are
pickled over the child's stdin / stdout (``multiprocessing.connection`` framing); the child dies with
its parent: the only write end of its stdin is the parent's, so the parent's exit (kill -9 too) is an end of
file there, and a parent-pid check backs that up. (``PR_SET_PDEATHSIG`` would fire when the *thread* that
started the child ends, and any thread may reconnect a camera.)
"""

from __future__ import annotations

import logging
import os
import queue
import subprocess
import sys
import threading
from collections.abc import Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import DeviceError
from tdcommon.meshes import Mesh

log = logging.getLogger(__name__)
READY_TIMEOUT_S = 120.0  # the child imports open3d and pre-renders the static scene before it answers
PARENT_CHECK_S = 1.0  # the child checks its parent this often while idle


class RenderProcess:
    """A :class:`~drivers.fake.render.SceneRenderer` in a child process; :meth:`render` returns what it would.

    kwargs: the renderer's constructor arguments (``intrinsics``, ``T_world_cam``, noise settings ...).
    name: for messages ("camera cam0"). The child starts at once; the first :meth:`render` waits for it.
    Raises :class:`DeviceError` (recoverable) when the child fails, dies or does not answer in time;
    after that this object is closed, and a new one must be made.
    """

    def __init__(self, kwargs: dict[str, Any], *, name: str = "camera") -> None:
        self.name = name
        root = str(Path(__file__).resolve().parents[2])  # the folder that holds the drivers package
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p))
        self._proc: subprocess.Popen[bytes] | None = subprocess.Popen(
            [sys.executable, "-m", "drivers.fake.render_process", str(os.getpid())],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, close_fds=True,
            start_new_session=True,  # a terminal's Ctrl-C (or a signal to the group) leaves the camera running
        )
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._tx = Connection(os.dup(self._proc.stdin.fileno()), readable=False)
        self._rx = Connection(os.dup(self._proc.stdout.fileno()), writable=False)
        self._proc.stdin.close()
        self._proc.stdout.close()
        self._ready = False
        self._send(kwargs)

    def _send(self, obj: object) -> None:
        """Pickle ``obj`` to the child; a broken pipe closes this object and raises DeviceError."""
        try:
            self._tx.send(obj)
        except (OSError, ValueError) as e:
            self._fail(f"cannot reach it ({e})")
        except TypeError:  # the connection was closed by another thread mid-send (the camera closing)
            if self._proc is not None:
                raise
            raise DeviceError(f"{self.name}: render process closed", recoverable=True) from None

    def _fail(self, why: str) -> None:
        """Close, then raise a recoverable DeviceError naming the process and its exit code."""
        rc = self._proc.poll() if self._proc is not None else None
        self.close()
        raise DeviceError(f"{self.name}: render process {why}" + (f" (exit code {rc})" if rc is not None else ""),
                          recoverable=True)

    def _reply(self, timeout: float) -> tuple[Any, ...]:
        """The child's next message, or DeviceError when it fails, exits or stays silent for ``timeout`` s."""
        if self._proc is None:
            raise DeviceError(f"{self.name}: render process closed", recoverable=True)
        try:
            if not self._rx.poll(timeout):
                self._fail(f"did not answer within {timeout:.0f} s")
            msg = self._rx.recv()
        except (EOFError, OSError) as e:
            self._fail(f"exited ({type(e).__name__})")
        except TypeError:  # closed by another thread while waiting (the camera closing)
            if self._proc is not None:
                raise
            raise DeviceError(f"{self.name}: render process closed", recoverable=True) from None
        if msg[0] == "error":
            self._fail(f"failed: {msg[1]}")
        return msg

    def wait_ready(self) -> None:
        """Return once the child has built its renderer (DeviceError if it cannot)."""
        if not self._ready:
            self._reply(READY_TIMEOUT_S)
            self._ready = True

    def render(
        self, arms: Sequence[Mesh], obj: Mesh | None, *, object_color: np.ndarray, frame_index: int,
        with_mask: bool, timeout: float = 10.0,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(color (H, W, 3) uint8, depth (H, W) uint16 mm, mask (H, W) bool or None) of one frame.

        Arguments as :meth:`SceneRenderer.render`, with the object's colour (RGB 0-255) set first.
        timeout: s to wait for the frame once the child is up.
        """
        self.submit(arms, obj, object_color=object_color, frame_index=frame_index, with_mask=with_mask)
        return self.result(timeout)

    def submit(
        self, arms: Sequence[Mesh], obj: Mesh | None, *, object_color: np.ndarray, frame_index: int, with_mask: bool,
    ) -> None:
        """Send one frame to render without waiting for it; :meth:`result` returns the frames in order."""
        self.wait_ready()
        self._send(([tuple(m) for m in arms], obj, np.asarray(object_color, np.float32), int(frame_index),
                    bool(with_mask)))

    def result(self, timeout: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The oldest submitted frame not yet returned: (color, depth, mask) as :meth:`render`."""
        _, color, depth, mask = self._reply(timeout)
        return color, depth, mask

    def close(self) -> None:
        """Ask the child to exit (closing its stdin), then kill it if it has not within a second (idempotent)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        for conn in (self._tx, self._rx):
            conn.close()
        try:
            proc.wait(1.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)

    def __del__(self) -> None:
        """A process left open is not left behind."""
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown: best effort
            pass


def _serve(parent_pid: int) -> int:
    """The child: build the renderer from the first message, then answer render requests until stdin closes."""
    if os.getppid() != parent_pid:
        return 0
    rx, tx = Connection(os.dup(0), writable=False), Connection(os.dup(1), readable=False)
    devnull = os.open(os.devnull, os.O_RDWR)
    os.dup2(devnull, 0)
    os.dup2(2, 1)  # stray prints go to stderr, never into the reply stream
    from drivers.fake.render import SceneRenderer  # imports open3d: after the pipes are set up

    try:
        renderer = SceneRenderer(**rx.recv())
    except EOFError:
        return 0
    except Exception as e:  # noqa: BLE001 - reported to the parent, which raises it as a device fault
        tx.send(("error", f"{type(e).__name__}: {e}"))
        return 1
    tx.send(("ready",))
    requests: queue.Queue[Any] = queue.Queue()

    def read_requests() -> None:  # drains stdin while a frame renders: the parent may send the next one then
        try:
            while True:
                requests.put(rx.recv())
        except (EOFError, OSError):
            requests.put(None)

    threading.Thread(target=read_requests, name="requests", daemon=True).start()
    while True:
        try:
            request = requests.get(timeout=PARENT_CHECK_S)
        except queue.Empty:
            if os.getppid() != parent_pid:
                return 0
            continue
        if request is None:
            return 0
        arms, obj, color, frame_index, with_mask = request
        try:
            renderer.object_color = color
            out = renderer.render(arms, obj, frame_index=frame_index, with_mask=with_mask)
            reply: tuple[Any, ...] = ("ok", out.color, out.depth, out.mask)
        except Exception as e:  # noqa: BLE001 - reported to the parent, which raises it as a device fault
            reply = ("error", f"{type(e).__name__}: {e}")
        try:
            tx.send(reply)
        except OSError:  # the parent closed the camera while this frame rendered: nobody is waiting for it
            return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    sys.exit(_serve(int(sys.argv[1])))
