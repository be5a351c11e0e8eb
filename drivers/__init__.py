"""Hardware behind small interfaces: arms, grippers and RGB-D cameras.

Each device kind has one ``Protocol`` (:mod:`drivers.base`) and a registry keyed by the
config's ``type:`` field. Vendor SDKs are imported lazily inside their driver module, so
mock mode and the tests need none of them.
"""

from drivers.base import Arm, Gripper, RGBDCamera, create_arm, create_camera, create_gripper, register
from tdcommon.types import CameraIntrinsics, GripperState, JointState, RGBDFrame

__all__ = [
    "Arm",
    "CameraIntrinsics",
    "Gripper",
    "GripperState",
    "JointState",
    "RGBDCamera",
    "RGBDFrame",
    "create_arm",
    "create_camera",
    "create_gripper",
    "register",
]
