"""Point-cloud records and files (no rclpy).

A cloud is a numpy structured array of :data:`CLOUD_DTYPE`: x, y, z in metres (V0), the
stripe strength as ``intensity`` [DN] and the stripe ``width`` [px], all float32, in this
order. The same layout is the PointCloud2 the reconstructor publishes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

CLOUD_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                        ('intensity', '<f4'), ('width', '<f4')])


def xyz(cloud: np.ndarray) -> np.ndarray:
    """The (n, 3) float64 coordinates [m] of a CLOUD_DTYPE array."""
    return np.column_stack([cloud['x'], cloud['y'], cloud['z']]).astype(np.float64)


def save_cloud(cloud: np.ndarray, path) -> str:
    """Write a cloud as PLY or PCD (chosen by the extension) with open3d.

    Coordinates are written in metres; the stripe strength becomes a grey colour
    (intensity / 255, clipped) so viewers show it.
    """
    import open3d as o3d

    path = Path(path)
    if path.suffix.lower() not in ('.ply', '.pcd'):
        raise ValueError(f'{path}: extension must be .ply or .pcd')
    if cloud.dtype != CLOUD_DTYPE:
        raise ValueError(f'cloud: expected dtype {CLOUD_DTYPE}, got {cloud.dtype}')
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz(cloud)))
    grey = np.clip(cloud['intensity'].astype(np.float64) / 255.0, 0.0, 1.0)
    pcd.colors = o3d.utility.Vector3dVector(np.repeat(grey[:, None], 3, axis=1))
    path.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_point_cloud(str(path), pcd):
        raise OSError(f'{path}: open3d could not write the cloud')
    return str(path)
