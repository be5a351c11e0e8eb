"""Inverse kinematics of the Panda TCP: damped least squares with pinocchio, for authoring programs.

``solve_ik(kin, T_target, q0)`` finds joints (7,) rad putting the TCP of arm ``kin`` at the world
pose ``T_target`` (4, 4), starting from (and pulled in the null space towards) ``q0``, within the
joint limits. ``python -m trajectories.ik`` regenerates the shipped library programs.
"""

from __future__ import annotations

import numpy as np

from tdcommon.robot import HOME_Q, N_JOINTS, PandaKinematics, joint_limits


class IKError(ValueError):
    """No joint solution reached the target pose within tolerance."""


def solve_ik(kin: PandaKinematics, T_target: np.ndarray, q0: np.ndarray, *, tol_pos: float = 1e-4,
             tol_rot: float = 1e-3, damping: float = 1e-4, max_iter: int = 1000, posture_gain: float = 0.05,
             limit_margin: float = 0.05) -> np.ndarray:
    """(7,) rad joints putting the TCP at world pose ``T_target`` (4, 4), starting from ``q0`` (7,).

    Damped least squares on the 6-D TCP error (local frame, log map), with a null-space pull
    towards ``q0`` and joints clipped ``limit_margin`` rad inside the Panda limits.
    Raises IKError when the pose is not reached within ``tol_pos`` m / ``tol_rot`` rad.
    """
    import pinocchio as pin

    lim = joint_limits()
    lo, hi = lim["lower"] + limit_margin, lim["upper"] - limit_margin
    model, data = kin.model, kin.data
    T_base_target = np.linalg.inv(kin.T_world_base) @ np.asarray(T_target, dtype=np.float64)
    target = pin.SE3(T_base_target[:3, :3].copy(), T_base_target[:3, 3].copy())
    q0 = np.clip(np.asarray(q0, dtype=np.float64), lo, hi)
    q = q0.copy()
    full = np.zeros(model.nq)
    err = np.full(6, np.inf)
    for _ in range(max_iter):
        full[:N_JOINTS] = q
        pin.forwardKinematics(model, data, full)
        M = pin.updateFramePlacement(model, data, kin.tcp_id)
        err = pin.log6(M.actInv(target)).vector  # (6,) local frame: [v, w]
        if np.linalg.norm(err[:3]) < tol_pos and np.linalg.norm(err[3:]) < tol_rot:
            return q
        J = pin.computeFrameJacobian(model, data, full, kin.tcp_id, pin.ReferenceFrame.LOCAL)[:, :N_JOINTS]
        JJt = J @ J.T + damping * np.eye(6)
        Jpinv = J.T @ np.linalg.solve(JJt, np.eye(6))
        dq = Jpinv @ err + (np.eye(N_JOINTS) - Jpinv @ J) @ (posture_gain * (q0 - q))
        step = np.linalg.norm(dq)
        if step > 0.2:
            dq *= 0.2 / step
        q = np.clip(q + dq, lo, hi)
    raise IKError(f"IK did not converge: position error {np.linalg.norm(err[:3]):.2e} m, "
                  f"rotation error {np.linalg.norm(err[3:]):.2e} rad")


def tcp_target(xyz: np.ndarray, yaw: float = 0.0, tilt: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """(4, 4) world pose of a gripper pointing down at ``xyz`` (m), turned by ``yaw`` about world z
    and tilted by ``tilt`` = (about world x, about world y), rad."""
    from scipy.spatial.transform import Rotation

    down = np.diag([1.0, -1.0, -1.0])  # TCP z-axis along world -z, x along world +x
    R = (Rotation.from_euler("xyz", [tilt[0], tilt[1], yaw]) * Rotation.from_matrix(down)).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = xyz
    return T


# Shipped programs: (name, category, description, [(left xyz, right xyz, yaw_left, yaw_right)]).
# Every program starts with the grippers holding the object at x=0.45, y=±0.25, z=0.40, pointing down.
_START = ((0.45, 0.25, 0.40), (0.45, -0.25, 0.40), 0.0, 0.0)
LIBRARY_SPEC: list[tuple[str, str, str, list[tuple]]] = [
    ("rope_swing", "dlo", "Both ends of a rope held level: swing left and right, bring the ends closer "
     "so the rope sags, then back to the start.", [
        _START,
        ((0.45, 0.35, 0.45), (0.45, -0.15, 0.45), 0.0, 0.0),
        ((0.45, 0.15, 0.45), (0.45, -0.35, 0.45), 0.0, 0.0),
        ((0.55, 0.15, 0.35), (0.55, -0.15, 0.35), 0.3, -0.3),
        _START,
    ]),
    ("branched_lift", "bdlo", "Two ends of a branched rope (wire harness) held: lift, tilt one side up, "
     "push forward with a twist, lower, back to the start.", [
        _START,
        ((0.45, 0.25, 0.55), (0.45, -0.25, 0.55), 0.0, 0.0),
        ((0.45, 0.25, 0.60), (0.45, -0.25, 0.35), 0.0, 0.0),
        ((0.55, 0.25, 0.45), (0.55, -0.25, 0.45), 0.4, -0.4),
        ((0.45, 0.25, 0.30), (0.45, -0.25, 0.30), 0.0, 0.0),
        _START,
    ]),
    ("cloth_fold", "cloth", "Two corners of a cloth held: lift and pull back, lay it forward on the table, "
     "fold it back over itself, lift, back to the start.", [
        _START,
        ((0.35, 0.25, 0.50), (0.35, -0.25, 0.50), 0.0, 0.0),
        ((0.60, 0.25, 0.20), (0.60, -0.25, 0.20), 0.0, 0.0),
        ((0.40, 0.22, 0.25), (0.40, -0.22, 0.25), 0.0, 0.0),
        ((0.45, 0.25, 0.45), (0.45, -0.25, 0.45), 0.0, 0.0),
        _START,
    ]),
]


def build_library_program(name: str, category: str, description: str, poses: list[tuple],
                          bases: dict[str, np.ndarray]) -> object:
    """A Program whose waypoints reach ``poses`` (left xyz, right xyz, left yaw, right yaw) by IK."""
    from trajectories.program import Program, Waypoint

    home = np.array(HOME_Q)
    kins = {a: PandaKinematics(bases[a]) for a in ("left", "right")}
    prev = {"left": home, "right": home}
    wps = []
    seen: dict[tuple, dict[str, np.ndarray]] = {}
    for pose in poses:
        pl, pr, yl, yr = pose
        q = seen.get(pose) or {a: solve_ik(kins[a], tcp_target(np.asarray(p), yaw), prev[a])
                               for a, p, yaw in (("left", pl, yl), ("right", pr, yr))}
        seen[pose] = prev = q  # a pose seen before gets the same joints (e.g. back to the start)
        wps.append(Waypoint(left=[round(float(x), 6) for x in q["left"]],
                            right=[round(float(x), 6) for x in q["right"]],
                            grippers={"left": {"state": "closed", "force": 20.0},
                                      "right": {"state": "closed", "force": 20.0}} if not wps else {}))
    return Program(name=name, description=description, category=category, waypoints=wps)  # type: ignore[arg-type]


def main() -> None:
    """Regenerate ``trajectories/library/*.yaml`` for the mock station's base placements."""
    from trajectories.program import LIBRARY_DIR, save_program
    from trajectories.safety import MOCK_BASES

    for name, category, description, poses in LIBRARY_SPEC:
        prog = build_library_program(name, category, description, poses, MOCK_BASES)
        save_program(prog, LIBRARY_DIR / f"{name}.yaml")
        print(f"wrote {LIBRARY_DIR / f'{name}.yaml'}")


if __name__ == "__main__":
    main()
