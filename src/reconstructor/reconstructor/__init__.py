"""Geometric model of the dynamic camera and dynamic laser, triangulation, and the node
publishing PointCloud2 in V0.
"""
