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


#: PCL's name, size, type letter and count of each field, in CLOUD_DTYPE order (PCD v0.7).
_PCD_FIELDS = tuple((name, 4, 'F', 1) for name in CLOUD_DTYPE.names)


def _ply_header(n: int, frame_id: str) -> bytes:
    lines = ['ply', 'format binary_little_endian 1.0',
             f'comment galvoscan cloud, frame {frame_id}, x y z in metres, '
             'intensity in DN, width in px',
             f'element vertex {n}']
    lines += [f'property float {name}' for name in CLOUD_DTYPE.names]
    lines.append('end_header')
    return ('\n'.join(lines) + '\n').encode('ascii')


def _pcd_header(n: int, frame_id: str) -> bytes:
    lines = [f'# .PCD v0.7 - galvoscan cloud, frame {frame_id}, metres',
             'VERSION 0.7',
             'FIELDS ' + ' '.join(f[0] for f in _PCD_FIELDS),
             'SIZE ' + ' '.join(str(f[1]) for f in _PCD_FIELDS),
             'TYPE ' + ' '.join(f[2] for f in _PCD_FIELDS),
             'COUNT ' + ' '.join(str(f[3]) for f in _PCD_FIELDS),
             f'WIDTH {n}', 'HEIGHT 1', 'VIEWPOINT 0 0 0 1 0 0 0', f'POINTS {n}', 'DATA binary']
    return ('\n'.join(lines) + '\n').encode('ascii')


def save_cloud(cloud: np.ndarray, path, frame_id: str = 'v0') -> str:
    """Write a cloud as binary PLY or PCD (chosen by the extension), every field kept.

    Both files carry x, y, z [m], intensity [DN] and width [px] as named float32 fields, in
    :data:`CLOUD_DTYPE` order: PLY as ``property float`` of the ``vertex`` element, PCD v0.7
    with PCL's conventions (``TYPE F``, ``SIZE 4``, one row: ``HEIGHT 1``), so PCL's tools,
    CloudCompare, open3d, plyfile and pypcd4 read them as they are. The file is written
    under a temporary name and renamed, so a reader never sees half a cloud.

    Parameters
    ----------
    cloud : ndarray of CLOUD_DTYPE, shape (n,)
    path : str or Path
        Ends in ``.ply`` or ``.pcd``.
    frame_id : str
        The frame of the coordinates, written in the header comment.

    Returns
    -------
    str
        The path written.

    Raises
    ------
    ValueError
        Another extension or dtype.
    OSError
        The file cannot be written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in ('.ply', '.pcd'):
        raise ValueError(f'{path}: extension must be .ply or .pcd')
    if not isinstance(cloud, np.ndarray) or cloud.dtype != CLOUD_DTYPE or cloud.ndim != 1:
        raise ValueError(f'cloud: expected a 1-D array of dtype {CLOUD_DTYPE}, got '
                         f'{getattr(cloud, "dtype", type(cloud).__name__)}')
    header = (_ply_header if suffix == '.ply' else _pcd_header)(len(cloud), frame_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f'.{path.name}.tmp')
    try:
        with open(tmp, 'wb') as f:
            f.write(header)
            f.write(np.ascontiguousarray(cloud).tobytes())
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return str(path)


def load_cloud(path) -> np.ndarray:
    """Read a cloud that :func:`save_cloud` wrote (binary PLY or PCD with CLOUD_DTYPE fields).

    Returns
    -------
    ndarray of CLOUD_DTYPE, shape (n,)

    Raises
    ------
    ValueError
        Not such a file: another format, other fields, or a truncated body.
    """
    path = Path(path)
    data = path.read_bytes()
    suffix = path.suffix.lower()
    markers = {'.ply': (b'end_header\n', _ply_header), '.pcd': (b'DATA binary\n', _pcd_header)}
    if suffix not in markers:
        raise ValueError(f'{path}: extension must be .ply or .pcd')
    marker, expected = markers[suffix]
    end = data.find(marker)
    if end < 0:
        raise ValueError(f'{path}: not a binary galvoscan {suffix[1:].upper()} cloud')
    head, body = data[:end + len(marker)], data[end + len(marker):]
    n, rest = divmod(len(body), CLOUD_DTYPE.itemsize)
    if rest or _fields_of(head) != _fields_of(expected(n, '')):
        raise ValueError(f'{path}: header or size does not match {n} points of '
                         f'{", ".join(CLOUD_DTYPE.names)} (float32)')
    return np.frombuffer(body, CLOUD_DTYPE).copy()


def _fields_of(header: bytes) -> list[bytes]:
    """The header lines that define the layout (no comments)."""
    return [ln for ln in header.split(b'\n') if ln and not ln.startswith((b'comment', b'#'))]
