"""Named scan patterns: voltage lists of shape (n, 4), rows (U1_pan, U1_tilt, U2_pan, U2_tilt).

Every backend (sim, serial) scans the same lists; the ``StartScan`` service names them.
Pure numpy, no rclpy.
"""

from __future__ import annotations

import numpy as np

from galvoscan_common.frame import check_voltages

PATTERNS = ('raster', 'g1_grid', 'g2_sweep', 'custom')
#: The G1 axis a raster steps with G2 tilt: the one that moves the view across the stripe
#: (``reconstructor.planning.stripe_layout``): tilt for a laser below or above the camera,
#: pan for a laser beside it.
RASTER_G1_AXES = ('tilt', 'pan')


def _steps(name, n):
    n = int(n)
    if n < 1:
        raise ValueError(f'{name}: need at least 1 step, got {n}')
    return n


def _line(lo, hi, n):
    return np.array([0.5 * (lo + hi)]) if n == 1 else np.linspace(lo, hi, n)


def raster(g1_pan, g1_tilt, g2_tilt, steps_pan, steps_tilt, g2_pan=0.0, g1_axis='tilt'):
    """The paper's synchronised raster over a region.

    With ``g1_axis`` 'tilt' (a laser below or above the camera: the stripe along the image
    rows), for each of ``steps_pan`` G1 pan columns, G1 tilt and G2 tilt are stepped together
    (linearly coupled) across their ranges, so that the stripe stays in the camera's view
    while both sweep. With 'pan' (a laser beside the camera: the stripe along the columns,
    moved sideways by G2) the roles of the G1 axes are exchanged: for each of ``steps_tilt``
    G1 tilt rows, G1 pan and G2 tilt are stepped together over ``steps_pan`` steps. Lines
    alternate direction (serpentine) to avoid large jumps.

    Parameters
    ----------
    g1_pan, g1_tilt, g2_tilt : (float, float), volts
        (start, end) of each range; the G2 tilt range is traversed in step with the G1 axis
        ``g1_axis``.
    steps_pan, steps_tilt : int
    g2_pan : float, volts
        Fixed G2 pan voltage.
    g1_axis : {'tilt', 'pan'}
        The G1 axis stepped with G2 (:data:`RASTER_G1_AXES`).

    Returns
    -------
    ndarray, shape (steps_pan * steps_tilt, 4), volts
    """
    if g1_axis not in RASTER_G1_AXES:
        raise ValueError(f"g1_axis: expected one of {RASTER_G1_AXES}, got {g1_axis!r}")
    n_pan, n_tilt = _steps('steps_pan', steps_pan), _steps('steps_tilt', steps_tilt)
    # outer: the G1 axis along the stripe; inner: the one across it, coupled with G2
    cross = 1 if g1_axis == 'tilt' else 0
    outer_range, inner_range = (g1_pan, g1_tilt) if cross == 1 else (g1_tilt, g1_pan)
    n_outer, n_inner = (n_pan, n_tilt) if cross == 1 else (n_tilt, n_pan)
    outer = _line(*outer_range, n_outer)
    frac = np.linspace(0.0, 1.0, n_inner) if n_inner > 1 else np.array([0.5])
    rows = []
    for i, o in enumerate(outer):
        f = frac if i % 2 == 0 else frac[::-1]
        block = np.empty((n_inner, 4))
        block[:, 1 - cross] = o
        block[:, cross] = inner_range[0] + f * (inner_range[1] - inner_range[0])
        block[:, 2] = g2_pan
        block[:, 3] = g2_tilt[0] + f * (g2_tilt[1] - g2_tilt[0])
        rows.append(block)
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


def from_request(req, raster_g1_axis: str = 'tilt'):
    """Build the voltage list of a ``galvoscan_msgs/StartScan`` request (duck-typed).

    Size the request with :func:`check_scan_size` first: this allocates the whole table.
    ``raster_g1_axis``: the G1 axis a raster steps with G2 (:func:`raster`).
    """
    pattern = req.pattern
    if pattern == 'raster':
        return raster((req.g1_pan_min, req.g1_pan_max), (req.g1_tilt_min, req.g1_tilt_max),
                      (req.g2_tilt_min, req.g2_tilt_max), req.steps_pan, req.steps_tilt,
                      g1_axis=raster_g1_axis)
    if pattern == 'g1_grid':
        return g1_grid((req.g1_pan_min, req.g1_pan_max), (req.g1_tilt_min, req.g1_tilt_max),
                       req.steps_pan, req.steps_tilt, g2_tilt=req.g2_tilt_min)
    if pattern == 'g2_sweep':
        return g2_sweep((req.g2_tilt_min, req.g2_tilt_max), req.steps_tilt,
                        g1_pan=req.g1_pan_min, g1_tilt=req.g1_tilt_min)
    if pattern == 'custom':
        return custom(list(req.voltages))
    raise ValueError(f"pattern: unknown '{pattern}'; known: {', '.join(PATTERNS)}")
