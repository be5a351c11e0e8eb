"""Waypoint programs in joint space and time: model, files, ruckig timing, kinematics.

No devices and no threads here: everything is a function of joint values and time.
"""
