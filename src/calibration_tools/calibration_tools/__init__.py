"""Calibration of the galvoscan rig (intrinsics, dynamic camera, laser plane and axis, joint
correction): pure stages, targets, capture plans and the runner, plus the calibration node
that serves them as ROS services. No simulator and no application here.
"""
