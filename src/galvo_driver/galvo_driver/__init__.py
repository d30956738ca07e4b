"""Galvo driver for galvoscan: publishes galvo voltages and camera frames from the physical rig
simulator, a serial DAC board or a bag.
"""
