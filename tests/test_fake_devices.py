"""The simulated station's devices (drivers/fake/devices.py) against the Protocols of drivers/base.py."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.base import Arm, DeviceError, Gripper, RGBDCamera, create_arm, create_camera, create_gripper
from drivers.clock import RealClock, SimClock
from drivers.config import FakeArmConfig, FakeCameraConfig, FakeGripperConfig, Pose, SimObjectConfig
from drivers.fake.devices import FakeArm, SimStation
from drivers.fake.render import mock_camera_pose
from tdcommon.types import JointMotion

HOME = {  # configs/mock.yaml: TCPs at (0.45, +-0.25, 0.40) pointing down
    "left": [-0.082209, -0.221521, -0.309478, -2.116897, -0.070888, 1.904804, 0.424088],
    "right": [0.082002, -0.221535, 0.309668, -2.116897, 0.070935, 1.904801, 1.146671],
}
BASE_Y = {"left": 0.45, "right": -0.45}


@pytest.fixture
def station():
    clock = SimClock(10.0)
    st = SimStation(SimObjectConfig(category="dlo"), clock, seed=0, settle_time=0.5)
    arms = {
        n: create_arm(FakeArmConfig(base=Pose(xyz=(0, BASE_Y[n], 0)), home=HOME[n]), name=n, clock=clock, station=st)
        for n in ("left", "right")
    }
    grippers = {n: create_gripper(FakeGripperConfig(), name=n, clock=clock, station=st) for n in ("left", "right")}
    cam = create_camera(
        FakeCameraConfig(width=320, height=240, pose=mock_camera_pose(), clutter=3), clock=clock, station=st
    )
    for d in (*arms.values(), *grippers.values(), cam):
        d.connect()
    return clock, st, arms, grippers, cam


def test_devices_implement_the_protocols(station):
    _, _, arms, grippers, cam = station
    assert all(isinstance(a, Arm) for a in arms.values())
    assert all(isinstance(g, Gripper) for g in grippers.values())
    assert isinstance(cam, RGBDCamera)


def test_frames_at_30hz_without_gaps_with_ground_truth(station):
    clock, _, _, _, cam = station
    frames = [cam.read() for _ in range(8)]
    assert [f.frame_number for f in frames] == list(range(300, 308))  # frame k at k / 30 s
    stamps = np.array([f.device_stamp for f in frames])
    assert np.allclose(np.diff(stamps), 1 / 30)
    assert all(f.host_stamp == f.device_stamp for f in frames)  # SimClock: no latency
    f = frames[-1]
    assert f.color.shape == (240, 320, 3) and f.depth.shape == (240, 320) and f.depth.dtype == np.uint16
    gt = f.ground_truth
    assert gt is not None and gt.keypoints.shape == (20, 3) and gt.category == "dlo"
    assert gt.grasp == {"left": 0, "right": 19}
    # The grasped ends are at the TCPs of the arms at the frame time.
    assert np.linalg.norm(gt.keypoints[0] - [0.45, 0.25, 0.40]) < 0.005
    assert clock.now() == pytest.approx(stamps[-1])


def test_object_is_visible_in_depth(station):
    _, _, _, _, cam = station
    cam.render_mask = True
    f = cam.read()
    mask = cam.last_mask
    assert mask is not None and mask.sum() > 150
    z = f.depth_m()[mask & (f.depth > 0)]
    assert 0.6 < np.median(z) < 1.4


def test_arm_reaches_motion_end_and_carries_the_rope(station):
    clock, st, arms, _, cam = station
    arm = arms["left"]
    q1 = np.array(HOME["left"]) + np.array([0.15, 0.1, 0.0, 0.1, 0.0, -0.1, 0.0])
    t0 = clock.now()
    arm.start_motion(JointMotion.smoothstep(arm.read_state().q, q1, 1.0))
    with pytest.raises(DeviceError):
        arm.start_motion(JointMotion.smoothstep(q1, q1, 0.5))  # busy
    assert arm.wait_motion(0.3) is False
    assert arm.wait_motion(5.0) is True
    assert clock.now() == pytest.approx(t0 + 1.0)
    assert np.allclose(arm.read_state().q, q1, atol=1e-9)
    f = cam.read()
    tcp = arm.tcp_at(clock.now())[:3, 3]
    assert np.linalg.norm(f.ground_truth.keypoints[0] - tcp) < 0.005
    assert st.sim.stretch_ratio().max() < 1.02


def test_motion_must_start_at_current_state(station):
    _, _, arms, _, _ = station
    q = np.array(HOME["right"])
    with pytest.raises(DeviceError, match="away from the current joint"):
        arms["right"].start_motion(JointMotion.smoothstep(q + 0.1, q, 1.0))


def test_arm_fault_injection_and_recovery(station):
    clock, _, arms, _, _ = station
    arm = arms["left"]
    q0 = arm.read_state().q
    q1 = q0 + 0.2
    t0 = clock.now()
    arm.inject_fault(t0 + 0.4)
    arm.start_motion(JointMotion.smoothstep(q0, q1, 1.0))
    with pytest.raises(DeviceError) as e:
        arm.wait_motion(5.0)
    assert e.value.recoverable and clock.now() == pytest.approx(t0 + 0.4)
    frozen = arm.read_state().q
    clock.sleep_until(t0 + 2.0)
    assert np.allclose(arm.read_state().q, frozen)  # frozen, not finishing the motion
    with pytest.raises(DeviceError):
        arm.start_motion(JointMotion.smoothstep(frozen, q1, 1.0))
    arm.recover()
    arm.start_motion(JointMotion.smoothstep(arm.read_state().q, q1, 1.0))
    assert arm.wait_motion(2.0) and np.allclose(arm.read_state().q, q1)


def test_arm_lag_and_noise():
    clock = SimClock()
    arm = FakeArm(FakeArmConfig(lag=0.05, noise=0.001), name="left", clock=clock)
    q0 = np.array(FakeArmConfig().home)
    arm.start_motion(JointMotion.smoothstep(q0, q0 + 0.3, 1.0))
    clock.sleep_until(0.5)
    q_lag, _ = arm.state_at(0.5)
    q_cmd = arm._motion.sample(0.5)[0]
    assert np.all(q_lag < q_cmd - 0.005)  # behind the command while it moves up
    arm.wait_motion(2.0)
    clock.sleep_until(2.0)
    s = arm.read_state()
    assert np.allclose(s.q, q0 + 0.3, atol=0.006)  # converged, within noise
    assert s.stamp == pytest.approx(2.0)


def test_gripper_release_and_regrasp(station):
    clock, st, _, grippers, cam = station
    g = grippers["left"]
    assert g.read_state().grasped and g.read_state().width == pytest.approx(0.016)
    g.command(closed=False)
    clock.sleep_until(clock.now() + 0.3)
    assert 0.016 < g.read_state().width < 0.08  # fingers move at 0.1 m/s
    clock.sleep_until(clock.now() + 0.5)
    s = g.read_state()
    assert not s.grasped and s.width == pytest.approx(0.08)
    f = cam.read()
    assert f.ground_truth.grasp["left"] == -1
    g.command(closed=False, width=0.03)
    clock.sleep_until(clock.now() + 0.1)
    # The released end has swung away from the TCP; closing now grasps nothing.
    g.command(closed=True)
    clock.sleep_until(clock.now() + 1.0)
    s = g.read_state()
    assert not s.grasped and s.width == pytest.approx(0.0)


def test_camera_faults(station):
    _, _, _, _, cam = station
    a = cam.read()
    cam.inject_fault("drop")
    b = cam.read()
    assert b.frame_number == a.frame_number + 2  # one frame lost
    cam.inject_fault("error")
    with pytest.raises(DeviceError):
        cam.read()
    c = cam.read()
    assert c.frame_number == b.frame_number + 2  # the failed read consumed a frame
    cam.close()
    with pytest.raises(DeviceError):
        cam.read()


def test_station_episode_facts_and_object_swap(station):
    clock, st, _, _, cam = station
    cam.read()
    facts = st.episode_facts()
    assert facts["grasp_indices"] == {"left": 0, "right": 19} and facts["sim_category"] == "dlo"
    st.set_object(SimObjectConfig(category="cloth", spacing=0.035))
    f = cam.read()
    assert f.ground_truth.category == "cloth" and f.ground_truth.keypoints.shape == (36, 3)
    assert f.ground_truth.grasp == {"left": 0, "right": 5}


def test_physics_does_not_depend_on_query_pattern():
    def run(state_rate_reads: bool) -> np.ndarray:
        clock = SimClock(0.0)
        st = SimStation(SimObjectConfig(category="dlo"), clock, settle_time=0.3)
        arms = {
            n: FakeArm(FakeArmConfig(base=Pose(xyz=(0, BASE_Y[n], 0)), home=HOME[n]), name=n, clock=clock, station=st)
            for n in ("left", "right")
        }
        g = create_gripper(FakeGripperConfig(), name="left", clock=clock, station=st)
        q0 = np.array(HOME["left"])
        arms["left"].start_motion(JointMotion.smoothstep(q0, q0 + 0.2, 1.0))
        for k in range(1, 301 if state_rate_reads else 2):  # many gripper reads, or one
            clock.sleep_until(k / 250 if state_rate_reads else 1.2)
            g.read_state()
        clock.sleep_until(1.2)
        st.advance_to(1.2)
        return st.sim.positions

    assert np.array_equal(run(True), run(False))


def test_scheduled_arm_fault_from_config():
    """config.faults (wall-clock times) freezes the arm like inject_fault; a time already past never fires."""
    import time

    clock = SimClock(10.0)
    st = SimStation(SimObjectConfig(category="dlo"), clock, seed=0, settle_time=0.5)
    now = time.time()
    cfg = FakeArmConfig(base=Pose(xyz=(0, 0.45, 0)), home=HOME["left"],
                        faults=[{"at_wall": now - 5.0}, {"at_wall": now + 0.4, "kind": "reflex"}])
    arm = create_arm(cfg, name="left", clock=clock, station=st)
    arm.connect()
    q0 = arm.read_state().q
    t0 = clock.now()
    arm.start_motion(JointMotion.smoothstep(q0, q0 + 0.2, 1.0))  # the past fault is skipped, not raised here
    with pytest.raises(DeviceError, match="scheduled reflex") as e:
        arm.wait_motion(5.0)
    assert e.value.recoverable and clock.now() == pytest.approx(t0 + 0.4, abs=0.05)
    arm.recover()
    q = arm.read_state().q
    arm.start_motion(JointMotion.smoothstep(q, q0 + 0.2, 1.0))
    assert arm.wait_motion(2.0)  # no fault left


def test_scheduled_camera_stall_from_config():
    """config.stalls: no frame is captured inside the window, frame_number jumps over it."""
    import time

    clock = SimClock(10.0)
    st = SimStation(SimObjectConfig(category="dlo"), clock, seed=0, settle_time=0.5)
    cfg = FakeCameraConfig(width=160, height=120, pose=mock_camera_pose(), clutter=0,
                           stalls=[{"at_wall": time.time() + 0.5, "seconds": 1.0}])
    cam = create_camera(cfg, clock=clock, station=st)
    cam.connect()
    t0 = clock.now()
    numbers = []
    while clock.now() < t0 + 2.0:
        numbers.append(cam.read(timeout=2.0).frame_number)
    jumps = np.diff(numbers)
    assert sorted(jumps)[-1] == pytest.approx(31, abs=1) and sorted(jumps)[-2] == 1  # one 1 s hole at 30 fps


def test_fault_schedule_validation():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="seconds"):
        FakeCameraConfig(stalls=[{"at_wall": 1.0, "seconds": 0.0}])
    with pytest.raises(ValidationError, match="kind"):
        FakeArmConfig(faults=[{"at_wall": 1.0, "kind": "explode"}])


def _two_station_frames(render: str, n: int = 3, kill_child: bool = False) -> list:
    """``n`` frames of a fresh seeded station whose camera renders ``render`` ("inline" / "process")."""
    clock = SimClock(10.0)
    st = SimStation(SimObjectConfig(category="dlo"), clock, seed=0, settle_time=0.5)
    for n_ in ("left", "right"):
        create_arm(FakeArmConfig(base=Pose(xyz=(0, BASE_Y[n_], 0)), home=HOME[n_]), name=n_, clock=clock,
                   station=st).connect()
    cam = create_camera(FakeCameraConfig(width=160, height=120, pose=mock_camera_pose(), clutter=2, render=render),
                        clock=clock, station=st)
    cam.connect()
    try:
        frames = [cam.read() for _ in range(n)]
        if kill_child:
            proc = cam._renderer._proc  # noqa: SLF001 - the child a device fault would take down
            proc.kill()
            proc.wait(5)
            with pytest.raises(DeviceError, match="render process"):
                cam.read()
            assert cam._renderer is None  # noqa: SLF001 - closed, nothing left running
            cam.connect()  # what the station's reconnect does: a new child
            frames.append(cam.read())
        return frames
    finally:
        cam.close()


def test_render_process_gives_the_inline_frames_and_survives_its_death():
    inline = _two_station_frames("inline", n=4)
    process = _two_station_frames("process", n=3, kill_child=True)
    for a, b in zip(inline[:3], process[:3], strict=True):
        assert a.frame_number == b.frame_number
        assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth)  # bit-identical
    assert process[3].frame_number > process[2].frame_number  # frames again after the reconnect
    assert process[3].depth.shape == (120, 160) and (process[3].depth > 0).any()


def test_streaming_camera_captures_on_time_while_the_reader_is_busy():
    """Real clock + render process: the camera's own thread captures; only a reader later than the queue loses."""
    clock = RealClock()
    st = SimStation(SimObjectConfig(category="dlo"), clock, seed=0, settle_time=0.2)
    for n in ("left", "right"):
        create_arm(FakeArmConfig(base=Pose(xyz=(0, BASE_Y[n], 0)), home=HOME[n]), name=n, clock=clock,
                   station=st).connect()
    cam = create_camera(FakeCameraConfig(width=160, height=120, pose=mock_camera_pose(), clutter=2, queue_depth=6),
                        clock=clock, station=st)
    cam.connect()  # render "auto": a process under the real clock
    try:
        assert cam.streaming
        first = cam.read(timeout=5.0)
        time.sleep(0.1)  # the reader busy for 3 frame periods: the camera goes on capturing
        burst = [cam.read(timeout=2.0) for _ in range(5)]
        assert [f.frame_number for f in burst] == list(range(first.frame_number + 1, first.frame_number + 6))
        assert all(abs(f.device_stamp - f.frame_number / 30) < 1e-9 for f in burst)  # stamped at capture
        time.sleep(0.5)  # 15 frame periods: more than the queue holds
        late = cam.read(timeout=2.0)
        assert late.frame_number > burst[-1].frame_number + 6  # the older ones fell out of the queue
        cam.inject_fault("drop", count=2)
        numbers = [cam.read(timeout=2.0).frame_number for _ in range(10)]
        assert 3 in np.diff(numbers)  # the two dropped frames were never captured
        advance = st.advance_to
        st.advance_to = lambda t: (time.sleep(0.04), advance(t))  # the scene now costs more than a frame period
        slow = [cam.read(timeout=2.0) for _ in range(20)]  # behind: scene and render overlap, no frame lost
        assert np.all(np.diff([f.frame_number for f in slow]) == 1)
        assert all(abs(f.device_stamp - f.frame_number / 30) < 1e-9 for f in slow)
        proc = cam._renderer._proc  # noqa: SLF001 - the child must be gone after close
    finally:
        cam.close()
    assert not cam.streaming and proc.poll() is not None


def test_render_process_closed_by_another_thread_mid_send_is_a_device_error() -> None:
    """The camera closing while its capture thread sends a frame: the connection's handle is gone mid-write
    (multiprocessing raises TypeError there); the sender gets a recoverable DeviceError, not a traceback."""
    from drivers.fake.render_process import RenderProcess

    class Closed:
        def send(self, obj: object) -> None:
            raise TypeError("'NoneType' object cannot be interpreted as an integer")

        def poll(self, timeout: float) -> bool:
            return True

        def recv(self) -> object:
            raise TypeError("'NoneType' object cannot be interpreted as an integer")

    rp = RenderProcess.__new__(RenderProcess)
    rp.name, rp._proc, rp._tx, rp._rx = "camera cam0", None, Closed(), Closed()
    with pytest.raises(DeviceError, match="closed") as e:
        rp._send(("frame",))
    assert e.value.recoverable
    rp._proc = object()  # open: a TypeError is a bug, not a close, and is raised
    with pytest.raises(TypeError):
        rp._send(("frame",))
