"""Panda kinematics with pinocchio: TCP poses, the arm input u_t and link meshes in the world.

The model and meshes come from ``example-robot-data`` (loaded once per process). Joint
vectors are (7,) rad; the two fingers are set from the gripper opening. Poses are (4, 4)
float64 homogeneous transforms, world <- frame, metres.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from tdcommon.meshes import box_mesh, merge_meshes
from tdcommon.transforms import pose_to_input

TCP_FRAME = "panda_hand_tcp"
N_JOINTS = 7
# The Panda's ready pose (rad): elbow up, flange pointing down; the default start of arms and programs.
HOME_Q = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)


@dataclass(frozen=True)
class LinkMesh:
    """A rigid piece of the arm: triangles in the frame of ``joint_index`` (pinocchio joint)."""

    name: str
    joint_index: int
    placement: np.ndarray  # (4, 4) joint <- mesh
    vertices: np.ndarray  # (V, 3) float64, mesh frame, m
    triangles: np.ndarray  # (F, 3) int32


@functools.lru_cache(maxsize=1)
def panda_models() -> tuple:
    """(model, collision_model) of the Panda with hand, loaded once.

    Built as ``example_robot_data.load("panda")`` builds them (URDF, SRDF reference posture and collision
    pairs) but without its visual model, whose meshes take ~0.6 s to load and are used nowhere here; a
    loader without the attributes this relies on gets the full ``load``.
    """
    import os

    import pinocchio as pin
    from example_robot_data import getModelPath, load

    try:
        from example_robot_data.robots_loader import PandaLoader
        from example_robot_data.utils import readParamsFromSrdf

        urdf_rel = os.path.join(PandaLoader.path, PandaLoader.urdf_subpath, PandaLoader.urdf_filename)
        root = getModelPath(urdf_rel)
        srdf = os.path.join(root, PandaLoader.path, PandaLoader.srdf_subpath, PandaLoader.srdf_filename)
    except (ImportError, AttributeError, OSError):
        robot = load("panda")
        return robot.model, robot.collision_model
    model, cmodel = pin.buildModelsFromUrdf(os.path.join(root, urdf_rel), [os.path.join(root, "../..")],
                                            geometry_types=pin.GeometryType.COLLISION)
    readParamsFromSrdf(model, srdf, False, PandaLoader.has_rotor_parameters, PandaLoader.ref_posture)
    cmodel.addAllCollisionPairs()
    pin.removeCollisionPairs(model, cmodel, srdf, False)
    return model, cmodel


@functools.lru_cache(maxsize=1)
def panda_link_meshes() -> tuple[LinkMesh, ...]:
    """The Panda's collision geometry (≈2.3k triangles) as plain arrays, loaded once.

    The meshes are the ones pinocchio loaded into the collision model (coal BVH models, ``meshScale`` applied
    at load), copied out: reading the files again would take a mesh library (open3d: ~1 s to import).
    """
    _, cmodel = panda_models()
    out = []
    for g in cmodel.geometryObjects:
        if g.meshPath.endswith((".stl", ".STL", ".obj", ".dae")):
            bvh = g.geometry
            v = np.array(bvh.vertices(), dtype=np.float64).reshape(-1, 3)
            tris = [bvh.tri_indices(i) for i in range(bvh.num_tris)]
            f = np.array([(t[0], t[1], t[2]) for t in tris], dtype=np.int32).reshape(-1, 3)
        else:  # finger pads are boxes
            v, f = box_mesh((0.0, 0.0, 0.0), np.asarray(g.geometry.halfSide, dtype=np.float64))
        out.append(LinkMesh(g.name, int(g.parentJoint), g.placement.homogeneous.copy(), v, f))
    return tuple(out)


@dataclass(frozen=True)
class LinkSoup:
    """Some of the Panda's link meshes merged once, to be posed every frame without merging again.

    vertices: (V, 3) float64 m, each in its mesh's frame; triangles: (F, 3) int32 into them (read-only);
    bounds: (L + 1,) int64 vertex offsets of the L meshes; joint_index: (L,) int64 pinocchio joint of each;
    placement: (L, 4, 4) joint <- mesh.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    bounds: np.ndarray
    joint_index: np.ndarray
    placement: np.ndarray

    def posed(self, joint_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The meshes at joint poses (J, 4, 4) world <- joint: vertices (V, 3) float64 m world, the
        (shared, read-only) triangles (F, 3) int32."""
        T = joint_poses[self.joint_index] @ self.placement
        out = np.empty_like(self.vertices)
        for k, (a, b) in enumerate(zip(self.bounds[:-1], self.bounds[1:], strict=True)):
            out[a:b] = self.vertices[a:b] @ T[k, :3, :3].T + T[k, :3, 3]
        return out, self.triangles


@functools.lru_cache(maxsize=4)
def panda_link_soup(joints: tuple[int, ...] | None = None) -> LinkSoup:
    """``panda_link_meshes`` (those on ``joints`` only, else all) merged into one ``LinkSoup``, built once."""
    links = [m for m in panda_link_meshes() if joints is None or m.joint_index in joints]
    v, f = merge_meshes([(m.vertices, m.triangles) for m in links])
    f.setflags(write=False)
    bounds = np.cumsum([0] + [len(m.vertices) for m in links]).astype(np.int64)
    placement = np.stack([m.placement for m in links]) if links else np.zeros((0, 4, 4))
    return LinkSoup(v, f, bounds, np.array([m.joint_index for m in links], np.int64), placement)


def joint_limits() -> dict[str, np.ndarray]:
    """The Panda's published joint limits, each (7,): position lower/upper (rad), velocity (rad/s),
    acceleration (rad/s^2) and jerk (rad/s^3) from Franka's datasheet."""
    model, _ = panda_models()
    return {
        "lower": model.lowerPositionLimit[:N_JOINTS].copy(),
        "upper": model.upperPositionLimit[:N_JOINTS].copy(),
        "velocity": model.velocityLimit[:N_JOINTS].copy(),
        "acceleration": np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0]),
        "jerk": np.array([7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0]),
    }


class PandaKinematics:
    """Forward kinematics of one Panda whose base sits at ``T_world_base`` (4, 4)."""

    def __init__(self, T_world_base: np.ndarray | None = None) -> None:
        import pinocchio as pin

        self._pin = pin
        self.model, _ = panda_models()
        self.data = self.model.createData()
        self.T_world_base = np.eye(4) if T_world_base is None else np.asarray(T_world_base, dtype=np.float64)
        self.tcp_id = self.model.getFrameId(TCP_FRAME)
        self._bodies: list[tuple[str, int, np.ndarray]] | None = None  # link name, parent joint, joint <- link

    def _q_full(self, q: np.ndarray, finger_width: float) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (N_JOINTS,):
            raise ValueError(f"expected a (7,) joint vector, got shape {q.shape}")
        half = float(np.clip(finger_width / 2.0, 0.0, 0.04))
        return np.concatenate([q, [half, half]])

    def tcp_pose(self, q: np.ndarray) -> np.ndarray:
        """(4, 4) world <- TCP (between the fingertips) for joints ``q`` (7,)."""
        pin = self._pin
        pin.forwardKinematics(self.model, self.data, self._q_full(q, 0.0))
        M = pin.updateFramePlacement(self.model, self.data, self.tcp_id)
        return self.T_world_base @ M.homogeneous

    def joint_poses(self, q: np.ndarray, finger_width: float = 0.08) -> np.ndarray:
        """(n_joints+1, 4, 4) world <- joint frame for every pinocchio joint (index 0 = base)."""
        pin = self._pin
        pin.forwardKinematics(self.model, self.data, self._q_full(q, finger_width))
        return np.stack([self.T_world_base @ M.homogeneous for M in self.data.oMi])

    def link_frames(self, q: np.ndarray, finger_width: float = 0.08) -> dict[str, np.ndarray]:
        """(4, 4) world <- link for every link of the arm and hand, by its URDF name (``panda_link0`` ...
        ``panda_hand``, ``panda_leftfinger``): what a viewer needs to place the arm's URDF meshes."""
        poses = self.joint_poses(q, finger_width)
        if self._bodies is None:
            pin = self._pin
            self._bodies = [(str(f.name), int(f.parentJoint), f.placement.homogeneous.copy())
                            for f in self.model.frames if f.type == pin.FrameType.BODY]
        return {name: poses[j] @ M for name, j, M in self._bodies}

    def world_meshes(self, q: np.ndarray, finger_width: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
        """The whole arm as one triangle soup in the world frame.

        Returns vertices (V, 3) float64 m and triangles (F, 3) int32, ≈2.3k triangles (one read-only array
        shared by every call).
        """
        return panda_link_soup().posed(self.joint_poses(q, finger_width))

    def finger_meshes(self, q: np.ndarray, finger_width: float) -> tuple[np.ndarray, np.ndarray]:
        """The two fingers alone at this opening (m) for joints ``q`` (7,): vertices (V, 3) float64 m world,
        triangles (F, 3) int32 (shared, read-only)."""
        return panda_link_soup(HAND_JOINTS[1:]).posed(self.joint_poses(q, finger_width))


def arm_inputs(left: PandaKinematics, right: PandaKinematics, q_left: np.ndarray, q_right: np.ndarray) -> np.ndarray:
    """The paper's control input u_t: (12,) = left TCP [p, rotvec] then right TCP [p, rotvec], world frame."""
    return np.concatenate([pose_to_input(left.tcp_pose(q_left)), pose_to_input(right.tcp_pose(q_right))])


def arm_inputs_batch(left: PandaKinematics, right: PandaKinematics, q_left: np.ndarray,
                     q_right: np.ndarray) -> np.ndarray:
    """u_t for T joint states: (T, 12) from q_left, q_right (T, 7) rad.

    Convention (the paper's control input): per arm the TCP (``panda_hand_tcp``, between the
    fingertips) position in metres then its orientation as a rotation vector (axis * angle, rad,
    |angle| <= pi), both in the world frame; left arm in columns 0-5, right arm in columns 6-11.
    """
    from scipy.spatial.transform import Rotation

    q_left, q_right = np.atleast_2d(np.asarray(q_left, dtype=np.float64)), np.atleast_2d(np.asarray(q_right))
    if q_left.shape != q_right.shape or q_left.shape[1:] != (N_JOINTS,):
        raise ValueError(f"expected two (T, 7) joint arrays, got {q_left.shape} and {q_right.shape}")
    out = np.empty((len(q_left), 12))
    for c, kin, qs in ((0, left, q_left), (6, right, q_right)):
        T = np.stack([kin.tcp_pose(q) for q in qs]) if len(qs) else np.empty((0, 4, 4))
        out[:, c:c + 3] = T[:, :3, 3]
        out[:, c + 3:c + 6] = Rotation.from_matrix(T[:, :3, :3]).as_rotvec() if len(qs) else np.empty((0, 3))
    return out


HAND_JOINTS = (7, 8, 9)  # pinocchio joints carrying the hand and the two fingers


def hand_mesh(T_world_tcp: np.ndarray, finger_width: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
    """The Franka Hand and fingers placed at a TCP pose (4, 4), for datasets without joint states.

    Returns vertices (V, 3) float64 m world and triangles (F, 3) int32.
    """
    kin = PandaKinematics()
    q0 = np.array(HOME_Q)
    poses = kin.joint_poses(q0, finger_width)
    T_world_base = np.asarray(T_world_tcp) @ np.linalg.inv(kin.tcp_pose(q0))
    return panda_link_soup(HAND_JOINTS).posed(T_world_base @ poses)
