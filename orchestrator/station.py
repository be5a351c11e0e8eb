"""The station of one object: its arms, grippers and camera from the config (in mock mode a simulated
station holding that object), connected with retries, sampled as ``arms/state`` messages."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.base import Arm, DeviceError, Gripper, RGBDCamera, create_arm, create_camera, create_gripper
from drivers.clock import Clock
from orchestrator.config import Config, ObjectConfig
from orchestrator.recorder import TF_RATE
from tdcommon.robot import PandaKinematics
from tdcommon.transforms import pose_to_input
from tdcommon.types import RGBDFrame

log = logging.getLogger(__name__)
ARMS = ("left", "right")


class Station:
    """The station's devices for one object (in mock mode, a simulated station holding that object)."""

    def __init__(self, config: Config, obj: ObjectConfig, clock: Clock) -> None:
        st = config.station
        self.clock = clock
        self.sim: Any = None
        context: dict[str, Any] = {"clock": clock}
        if st.simulated:
            from drivers.fake.devices import SimStation

            assert obj.sim is not None  # guaranteed by Config validation
            self.sim = SimStation(obj.sim, clock, n_keypoints=obj.n_keypoints)
            context["station"] = self.sim
        slots = {"left": st.left, "right": st.right}
        self.arms: dict[str, Arm] = {n: create_arm(s.arm, name=n, **context) for n, s in slots.items()}
        self.grippers: dict[str, Gripper] = {
            n: create_gripper(s.gripper, name=n, **context, **self._gripper_context(s)) for n, s in slots.items()
        }
        self.camera: RGBDCamera = create_camera(st.camera, **context)
        self.kin = {n: PandaKinematics(s.arm.base.matrix()) for n, s in slots.items()}
        self.bases = {n: s.arm.base.matrix() for n, s in slots.items()}
        self.T_world_cam = st.camera.pose.matrix()
        self.fps = st.camera.fps
        self.broken: str | None = None  # set after a fault that needs a person; no more runs here
        self._connected: list[Any] = []
        self._links_t = -float("inf")  # when link frames were last computed (station clock, s)

    @staticmethod
    def _gripper_context(slot: Any) -> dict[str, Any]:
        """A Franka Hand talks to the controller of the arm it is mounted on."""
        return {"arm_config": slot.arm} if slot.gripper.type == "franka_hand" else {}

    def connect(self, retries: int = 3) -> None:
        """Connect every device (retrying device faults); raise DeviceError naming the one that failed."""
        devices: list[tuple[str, Any]] = [
            *((f"{n} arm", a) for n, a in self.arms.items()),
            *((f"{n} gripper", g) for n, g in self.grippers.items()),
            ("camera", self.camera),
        ]
        for label, dev in devices:
            for attempt in range(1, retries + 1):
                try:
                    dev.connect()
                    self._connected.append(dev)
                    break
                except DeviceError as e:
                    if attempt == retries or not e.recoverable:
                        raise DeviceError(f"{label}: could not connect after {attempt} attempts: {e}") from e
                    log.warning("%s: connect failed (%s), retrying", label, e)
                    time.sleep(0.5 * attempt)

        recorded_pose = getattr(self.camera, "T_world_cam", None)  # a replay brings its recording's pose
        if recorded_pose is not None:
            self.T_world_cam = np.asarray(recorded_pose, dtype=np.float64)

    def close(self) -> None:
        """Close every connected device, in reverse order, whatever happens."""
        for dev in reversed(self._connected):
            try:
                dev.close()
            except Exception as e:
                log.warning("closing %r failed: %s", dev, e)
        self._connected.clear()

    def sample_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """Both arms' joint states, gripper states and u_t (12,) as the ``arms/state`` message, plus the
        frames for ``/tf``: each TCP (``left_tcp``) and each joint of arm and hand (``left/panda_joint1``)."""
        msg: dict[str, Any] = {}
        u, tcps = [], {}
        now = self.clock.now()
        links_due = now - self._links_t >= 1.0 / TF_RATE - 1e-9  # link frames only as often as /tf is written
        if links_due:
            self._links_t = now
        for n in ARMS:
            js = self.arms[n].read_state()
            gs = self.grippers[n].read_state()
            T = self.kin[n].tcp_pose(js.q)
            tcps[f"{n}_tcp"] = T
            if links_due:
                tcps.update({f"{n}/{name}": F for name, F in self.kin[n].link_frames(js.q, gs.width).items()})
            u.append(pose_to_input(T))
            msg[n] = {
                "stamp": js.stamp, "q": js.q.tolist(), "dq": js.dq.tolist(),
                "gripper_width": gs.width, "grasped": gs.grasped,
            }
        msg["stamp"] = msg["left"]["stamp"]
        msg["u"] = np.concatenate(u).tolist()
        return msg, tcps

    def current_q(self) -> dict[str, np.ndarray]:
        """(7,) joint vector of each arm now."""
        return {n: self.arms[n].read_state().q for n in ARMS}

    def read_frame(self, retries: int = 3) -> RGBDFrame:
        """The camera's next frame; a failed read is retried, then the camera reconnected once.

        Raises DeviceError when no frame comes after ``retries`` attempts and the reconnect.
        """
        last: DeviceError | None = None
        for attempt in range(retries):
            try:
                return self.camera.read(timeout=2.0)
            except DeviceError as e:
                last = e
                log.warning("camera read failed (%s), attempt %d/%d", e, attempt + 1, retries)
        try:  # reconnect once before giving up
            self.camera.close()
            self.camera.connect()
            return self.camera.read(timeout=2.0)
        except DeviceError as e:
            raise DeviceError(f"camera: no frame after {retries} attempts and a reconnect: {last}; {e}") from e

    def stop_arms(self) -> None:
        """Stop every arm, ignoring arms that cannot (a faulted arm is already stopped)."""
        for arm in self.arms.values():
            try:
                arm.stop()
            except DeviceError as e:
                log.warning("stop after a fault: %s", e)

    def recover(self) -> None:
        """Clear recoverable faults on every arm; raises DeviceError when one cannot be cleared."""
        for arm in self.arms.values():
            arm.recover()


class StatePoller:
    """Samples joint states at ``rate`` Hz on a thread (real time only)."""

    def __init__(self, sample: Callable[[], None], rate: float) -> None:
        self._sample, self._period = sample, 1.0 / rate
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="state-poller", daemon=True)
        self.errors: list[str] = []

    def _run(self) -> None:
        t = time.monotonic()
        while not self._stop.is_set():
            try:
                self._sample()
            except Exception as e:
                self.errors.append(f"joint state sampling: {type(e).__name__}: {e}")
                log.warning("joint state sampling failed: %s", e)
            t += self._period
            delay = t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                t = time.monotonic()  # fell behind: do not burst

    def __enter__(self) -> StatePoller:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)
