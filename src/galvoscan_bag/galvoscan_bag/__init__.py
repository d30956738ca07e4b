"""Bag recording, replay and recovery for galvoscan (rosbag2 directories: metadata.yaml + MCAP).

Pure library modules (no rclpy): :mod:`.typestore`, :mod:`.writer`, :mod:`.reader`,
:mod:`.recover`. ROS adapters: :mod:`.ros_messages`, :mod:`.record_node`, :mod:`.replay_node`.
"""
