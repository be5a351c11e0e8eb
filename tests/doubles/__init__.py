"""Test doubles of the vendor SDKs (franky, ur-rtde, pyrealsense2, depthai) and a Modbus gripper.

Each double is a small module object that tests install with
``monkeypatch.setitem(sys.modules, name, double)``; it records calls and replays realistic
responses and faults, so the real drivers run without hardware or SDKs.
"""
