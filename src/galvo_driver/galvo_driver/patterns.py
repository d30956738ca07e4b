"""Named scan patterns: voltage lists of shape (n, 4), rows (U1_pan, U1_tilt, U2_pan, U2_tilt).

Every backend (sim, serial) scans the same lists; the ``StartScan`` service names them.
Pure numpy, no rclpy.
"""

from __future__ import annotations

import numpy as np

from galvoscan_common.frame import check_voltages

PATTERNS = ('raster', 'g1_grid', 'g2_sweep', 'custom')


def _steps(name, n):
    n = int(n)
    if n < 1:
        raise ValueError(f'{name}: need at least 1 step, got {n}')
    return n


def _line(lo, hi, n):
    return np.array([0.5 * (lo + hi)]) if n == 1 else np.linspace(lo, hi, n)


def raster(g1_pan, g1_tilt, g2_tilt, steps_pan, steps_tilt, g2_pan=0.0):
    """The paper's synchronised raster over a region.

    For each of ``steps_pan`` G1 pan columns, G1 tilt and G2 tilt are stepped together
    (linearly coupled) across their ranges, so that the stripe stays in the camera's view
    while both sweep. Columns alternate direction (serpentine) to avoid large jumps.

    Parameters
    ----------
    g1_pan, g1_tilt, g2_tilt : (float, float), volts
        (start, end) of each range; the G2 tilt range is traversed in step with G1 tilt.
    steps_pan, steps_tilt : int
    g2_pan : float, volts
        Fixed G2 pan voltage.

    Returns
    -------
    ndarray, shape (steps_pan * steps_tilt, 4), volts
    """
    n_pan, n_tilt = _steps('steps_pan', steps_pan), _steps('steps_tilt', steps_tilt)
    pans = _line(*g1_pan, n_pan)
    frac = np.linspace(0.0, 1.0, n_tilt) if n_tilt > 1 else np.array([0.5])
    rows = []
    for i, pan in enumerate(pans):
        f = frac if i % 2 == 0 else frac[::-1]
        t1 = g1_tilt[0] + f * (g1_tilt[1] - g1_tilt[0])
        t2 = g2_tilt[0] + f * (g2_tilt[1] - g2_tilt[0])
        rows.append(np.column_stack([np.full(n_tilt, pan), t1, np.full(n_tilt, g2_pan), t2]))
    return check_voltages(np.vstack(rows))


def g1_grid(g1_pan, g1_tilt, steps_pan, steps_tilt, g2_tilt=0.0, g2_pan=0.0):
    """Calibration: a G1 pan x tilt grid with the laser held still (row-major, pan outer)."""
    n_pan, n_tilt = _steps('steps_pan', steps_pan), _steps('steps_tilt', steps_tilt)
    pan, tilt = np.meshgrid(_line(*g1_pan, n_pan), _line(*g1_tilt, n_tilt), indexing='ij')
    n = pan.size
    return check_voltages(np.column_stack(
        [pan.ravel(), tilt.ravel(), np.full(n, g2_pan), np.full(n, g2_tilt)]))


def g2_sweep(g2_tilt, steps, g1_pan=0.0, g1_tilt=0.0, g2_pan=0.0):
    """Calibration: a G2 tilt sweep with the camera held still."""
    n = _steps('steps_tilt', steps)
    t2 = _line(*g2_tilt, n)
    return check_voltages(np.column_stack(
        [np.full(n, g1_pan), np.full(n, g1_tilt), np.full(n, g2_pan), t2]))


def custom(voltages):
    """An explicit list, flat (4n,) or (n, 4), volts."""
    arr = np.asarray(voltages, dtype=np.float64)
    if arr.ndim == 1:
        if arr.size == 0 or arr.size % 4:
            raise ValueError(f'voltages: need a non-empty multiple of 4 values, got {arr.size}')
        arr = arr.reshape(-1, 4)
    return check_voltages(arr)


#: Default limits of one scan, the driver's parameters ``max_scan_frames`` and
#: ``max_scan_duration``: 2 million frames hold a 64 MB voltage table and last 67 min at
#: 500 fps; a longer job is several scans.
MAX_SCAN_FRAMES = 2_000_000
MAX_SCAN_DURATION = 4 * 3600.0


def frame_count(req) -> int:
    """Frames a ``StartScan`` request would produce, computed without building the table.

    Raises
    ------
    ValueError
        An unknown pattern, or a step count below 1.
    """
    pattern = req.pattern
    if pattern == 'raster' or pattern == 'g1_grid':
        return _steps('steps_pan', req.steps_pan) * _steps('steps_tilt', req.steps_tilt)
    if pattern == 'g2_sweep':
        return _steps('steps_tilt', req.steps_tilt)
    if pattern == 'custom':
        n = len(req.voltages)
        if n == 0 or n % 4:
            raise ValueError(f'voltages: need a non-empty multiple of 4 values, got {n}')
        return n // 4
    raise ValueError(f"pattern: unknown '{pattern}'; known: {', '.join(PATTERNS)}")


def check_scan_size(req, frame_rate: float, max_frames: int = MAX_SCAN_FRAMES,
                    max_duration: float = MAX_SCAN_DURATION) -> int:
    """The frame count of a request, refused before anything is allocated when too large.

    Parameters
    ----------
    req : galvoscan_msgs/StartScan request (duck-typed)
    frame_rate : float, Hz
    max_frames : int
    max_duration : float, seconds

    Returns
    -------
    int
        The number of frames.

    Raises
    ------
    ValueError
        A bad pattern or step count, or a scan over ``max_frames`` frames or
        ``max_duration`` seconds (the message names the limit).
    """
    n = frame_count(req)
    if n > max_frames:
        raise ValueError(f'{n} frames exceed the limit of {max_frames} frames per scan '
                         f'(parameter max_scan_frames); split the job into several scans')
    duration = n / frame_rate
    if duration > max_duration:
        raise ValueError(f'{n} frames at {frame_rate:g} Hz take {duration:.0f} s, over the '
                         f'limit of {max_duration:.0f} s per scan (parameter '
                         f'max_scan_duration)')
    return n


def from_request(req):
    """Build the voltage list of a ``galvoscan_msgs/StartScan`` request (duck-typed).

    Size the request with :func:`check_scan_size` first: this allocates the whole table.
    """
    pattern = req.pattern
    if pattern == 'raster':
        return raster((req.g1_pan_min, req.g1_pan_max), (req.g1_tilt_min, req.g1_tilt_max),
                      (req.g2_tilt_min, req.g2_tilt_max), req.steps_pan, req.steps_tilt)
    if pattern == 'g1_grid':
        return g1_grid((req.g1_pan_min, req.g1_pan_max), (req.g1_tilt_min, req.g1_tilt_max),
                       req.steps_pan, req.steps_tilt, g2_tilt=req.g2_tilt_min)
    if pattern == 'g2_sweep':
        return g2_sweep((req.g2_tilt_min, req.g2_tilt_max), req.steps_tilt,
                        g1_pan=req.g1_pan_min, g1_tilt=req.g1_tilt_min)
    if pattern == 'custom':
        return custom(list(req.voltages))
    raise ValueError(f"pattern: unknown '{pattern}'; known: {', '.join(PATTERNS)}")
