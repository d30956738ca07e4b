"""Calibration of the galvoscan rig (intrinsics, dynamic camera, laser plane and axis, joint
correction) as ROS services and offline commands; the galvoscan command.
"""
