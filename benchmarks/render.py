"""Mock-mode costs per 1/30 s camera frame: physics, rendering and FakeCamera.read() end to end.

Objects as in configs/mock.yaml, both arms moving (a smooth 6 s joint motion), 640x480 and
1280x720. Each figure is the median over frames of wall time and of process CPU time (all
threads; numpy / open3d may use more than one). The machine is shared: also look at the load.

Run: .venv/bin/python benchmarks/render.py [--frames N]   (prints figures; no assertions)
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from drivers.clock import SimClock
from drivers.config import FakeArmConfig, FakeCameraConfig, FakeGripperConfig, Pose, SimObjectConfig
from drivers.fake.devices import FakeArm, FakeCamera, FakeGripper, SimStation
from drivers.fake.render import mock_camera_pose
from tdcommon.types import JointMotion

MOCK = Path(__file__).resolve().parents[1] / "configs" / "mock.yaml"
HOME = {
    "left": [-0.082209, -0.221521, -0.309478, -2.116897, -0.070888, 1.904804, 0.424088],
    "right": [0.082002, -0.221535, 0.309668, -2.116897, 0.070935, 1.904801, 1.146671],
}
SWING = np.array([0.3, 0.2, 0.0, 0.3, 0.0, -0.2, 0.5])  # rad, joint offsets of the benchmark motion


def mock_objects() -> dict[str, SimObjectConfig]:
    """The simulated objects of configs/mock.yaml by object name."""
    plan = yaml.safe_load(MOCK.read_text())["plan"]["objects"]
    return {o["name"]: SimObjectConfig(category=o["category"], **o["sim"]) for o in plan}


def station(obj: SimObjectConfig, width: int, height: int) -> tuple[SimStation, FakeCamera]:
    """A simulated station (both arms moving) and its connected camera on a simulated clock."""
    clock = SimClock(0.0)
    st = SimStation(obj, clock)
    for n, y, sign in (("left", 0.45, 1.0), ("right", -0.45, -1.0)):
        arm = FakeArm(FakeArmConfig(base=Pose(xyz=(0, y, 0)), home=HOME[n]), name=n, clock=clock, station=st)
        FakeGripper(FakeGripperConfig(), name=n, clock=clock, station=st)
        q0 = np.array(HOME[n])
        arm.start_motion(JointMotion.smoothstep(q0, q0 + sign * SWING, 6.0))
    cam = FakeCamera(FakeCameraConfig(width=width, height=height, pose=mock_camera_pose()), clock=clock, station=st)
    cam.connect()
    return st, cam


def timed(fn: Callable[[], object], n: int) -> tuple[float, float]:
    """Median wall and process CPU time (ms) of ``fn`` over ``n`` calls."""
    wall, cpu = [], []
    for _ in range(n):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=60, help="frames per figure (default 60)")
    n = parser.parse_args().frames
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; medians of {n} frames, arms moving")
    print(f"{'object':14s} {'size':9s} {'physics/frame':>22s} {'render':>22s} {'FakeCamera.read()':>22s}")
    for kind, obj in mock_objects().items():
        for w, h in ((640, 480), (1280, 720)):
            # Physics and render separately (the station's query pattern, a frame every 1/30 s)...
            st, cam = station(obj, w, h)
            cam.read()
            r = cam._renderer  # noqa: SLF001 - benchmark internals
            assert r is not None
            phys, rend = [], []
            for k in range(n):
                t = st.clock.now() + 1.0 / 30.0
                st.clock.sleep_until(t)
                phys.append(timed(lambda s=st, t=t: s.advance_to(t), 1))
                arms, mesh = st.arm_meshes(t), st.object_mesh()
                rend.append(timed(lambda r=r, a=arms, m=mesh, k=k: r.render(a, m, frame_index=k), 1))
            # ... and the camera end to end (physics, ground truth, meshes, render).
            st, cam = station(obj, w, h)
            cam.read()
            read = timed(cam.read, n)
            p, q = np.median(phys, axis=0), np.median(rend, axis=0)
            print(
                f"{kind:14s} {w}x{h:<5d}"
                f" {p[0]:6.1f} wall {p[1]:6.1f} CPU {q[0]:6.1f} wall {q[1]:6.1f} CPU"
                f" {read[0]:6.1f} wall {read[1]:6.1f} CPU  (ms, {st.sim.n_particles} particles)"
            )


if __name__ == "__main__":
    main()
