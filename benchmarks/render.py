"""Mock-mode costs: median render time at 640x480 and 1280x720, physics step per 1/30 s frame.

Run: .venv/bin/python benchmarks/render.py   (prints figures; no assertions)
"""

from __future__ import annotations

import os
import time

import numpy as np

from drivers.clock import SimClock
from drivers.config import FakeArmConfig, FakeCameraConfig, FakeGripperConfig, Pose, SimObjectConfig
from drivers.fake.devices import FakeArm, FakeCamera, FakeGripper, SimStation
from drivers.fake.render import SceneRenderer, mock_camera_pose

HOME = {
    "left": [-0.082209, -0.221521, -0.309478, -2.116897, -0.070888, 1.904804, 0.424088],
    "right": [0.082002, -0.221535, 0.309668, -2.116897, 0.070935, 1.904801, 1.146671],
}


def median_ms(fn, n: int) -> str:
    """Median wall time and median process CPU time (all threads) of ``fn``, as text."""
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(n):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return f"{1e3 * np.median(wall):6.1f} ms wall, {1e3 * np.median(cpu):6.1f} ms CPU"


def station(kind: str) -> SimStation:
    clock = SimClock()
    st = SimStation(SimObjectConfig(kind=kind), clock)
    for n, y in (("left", 0.45), ("right", -0.45)):
        FakeArm(FakeArmConfig(base=Pose(xyz=(0, y, 0)), home=HOME[n]), name=n, clock=clock, station=st)
        FakeGripper(FakeGripperConfig(), name=n, clock=clock, station=st)
    return st


def main() -> None:
    print(f"scene: both arms + object + 6 clutter boxes, mock camera pose; load average {os.getloadavg()[0]:.2f}")
    for kind in ("rope", "branched_rope", "cloth"):
        st = station(kind)
        sim = st.sim
        poses = {n: a.tcp_at(0.0) for n, a in st.arms.items()}
        closed = {"left": True, "right": True}
        phys = median_ms(lambda: sim.step(1 / 30, poses, closed), 30)  # noqa: B023
        print(f"{kind:14s} physics: {sim.n_particles} particles, {phys} per 1/30 s frame (median of 30)")
        arms, obj = st.arm_meshes(st.time), st.object_mesh()
        for w, h in ((640, 480), (1280, 720)):
            cfg = FakeCameraConfig(width=w, height=h, pose=mock_camera_pose())
            cam = FakeCamera(cfg, clock=st.clock, station=st)
            r = SceneRenderer(cam.intrinsics, cfg.pose.matrix(), clutter=cfg.clutter)
            k = iter(range(10**6))
            ms = median_ms(lambda: r.render(arms, obj, frame_index=next(k)), 15)  # noqa: B023
            print(f"{kind:14s} render {w}x{h}: {ms} (median of 15)")
    st = station("rope")
    cam = FakeCamera(FakeCameraConfig(width=640, height=480, pose=mock_camera_pose()), clock=st.clock, station=st)
    cam.connect()
    ms = median_ms(cam.read, 30)
    print(f"FakeCamera.read() end to end, rope, 640x480: {ms} (median of 30)")


if __name__ == "__main__":
    main()
