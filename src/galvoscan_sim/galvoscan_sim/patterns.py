"""Scan patterns: lists of (U1_pan, U1_tilt, U2_pan, U2_tilt) rows, one per frame [V].

- :func:`g1_grid`: the dynamic-camera calibration pattern (board imaged at many G1
  voltages, laser still).
- :func:`g2_sweep`: the dynamic-laser calibration pattern (G1 still, G2 tilt stepped).
- :func:`synchronised`: the paper's scan: both tilt mirrors stepped together so the stripe
  stays in the camera's small field of view while the view moves across the object.
- :func:`aim_laser`: the G2 tilt voltage that puts the sheet on the virtual camera's
  optical axis at a given distance (used to start a synchronised scan).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq

from .rig import Rig


def _values(values, name: str) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if arr.ndim != 1 or not len(arr) or not np.all(np.isfinite(arr)):
        raise ValueError(f'{name}: expected a non-empty 1-D list of finite voltages')
    return arr


def g1_grid(pan_values, tilt_values, u2=(0.0, 0.0)) -> np.ndarray:
    """Every (pan, tilt) combination of G1, G2 held at ``u2``.

    Parameters
    ----------
    pan_values, tilt_values : array_like, shape (n,), (m,), volts
    u2 : array_like, shape (2,), volts
        (U2_pan, U2_tilt).

    Returns
    -------
    ndarray, shape (n * m, 4), volts
        Pan varies slowest.
    """
    p = _values(pan_values, 'pan_values')
    t = _values(tilt_values, 'tilt_values')
    u2 = np.asarray(u2, dtype=np.float64)
    if u2.shape != (2,):
        raise ValueError(f'u2: expected shape (2,), got {u2.shape}')
    P, T = np.meshgrid(p, t, indexing='ij')
    out = np.zeros((P.size, 4))
    out[:, 0], out[:, 1] = P.ravel(), T.ravel()
    out[:, 2:] = u2
    return out


def g2_sweep(tilt_values, u1=(0.0, 0.0), u2_pan: float = 0.0) -> np.ndarray:
    """G2 tilt stepped through ``tilt_values`` with G1 held at ``u1``.

    Returns
    -------
    ndarray, shape (n, 4), volts
    """
    t = _values(tilt_values, 'tilt_values')
    u1 = np.asarray(u1, dtype=np.float64)
    if u1.shape != (2,):
        raise ValueError(f'u1: expected shape (2,), got {u1.shape}')
    out = np.zeros((len(t), 4))
    out[:, :2] = u1
    out[:, 2] = u2_pan
    out[:, 3] = t
    return out


def aim_laser(rig: Rig, u1_pan: float, u1_tilt: float, distance: float = 0.65,
              u2_pan: float = 0.0) -> float:
    """G2 tilt voltage whose sheet meets the virtual camera's optical axis at ``distance``.

    Uses the rig's true geometry without jitter (a planning aid, as an operator would aim).

    Parameters
    ----------
    distance : float
        Along the optical axis from the virtual camera centre [m].

    Raises
    ------
    ValueError
        No voltage in the DAC range reaches that point.
    """
    if not distance > 0:
        raise ValueError(f'distance: expected > 0 m, got {distance}')
    fs = rig.dac.full_scale
    th = rig.mirror_angles(rig.applied_voltages(np.array([u1_pan, u1_tilt, u2_pan, 0.0])))
    G_T_V = rig.G_T_V(th[0], th[1])
    target = G_T_V[:3, 3] + distance * G_T_V[:3, 2]

    def f(u):
        a = rig.mirror_angles(np.array([0.0, 0.0, u2_pan, u]))
        pi = rig.laser_sheet_G(a[2], a[3]).plane
        return float(pi[:3] @ target + pi[3])

    lo, hi = -fs, fs * (1.0 - 1e-9)
    if f(lo) * f(hi) > 0:
        raise ValueError(f'distance: no G2 tilt voltage within +-{fs} V puts the sheet at '
                         f'{distance} m on the optical axis for U1 = ({u1_pan}, {u1_tilt})')
    return float(brentq(f, lo, hi, xtol=1e-12))


def synchronised(rig: Rig, u1_pan_values, u1_tilt_start: float, steps: int,
                 tilt_step: float, distance: float = 0.65, u2_pan: float = 0.0,
                 reaim_every: int | None = None) -> np.ndarray:
    """The paper's synchronised scan over a region.

    For each G1 pan voltage, the laser is aimed (:func:`aim_laser`) at the optical axis at
    ``distance`` for the first tilt position; then both tilt mirrors are stepped together
    by the same mechanical angle (``tilt_step`` volts on G1, scaled by the nominal gain
    ratio on G2), ``steps`` frames in all. The view and the sheet turn about different
    axes, so with equal steps the stripe drifts slowly through the image (about 10 px per
    0.1 deg step at 650 mm for the reference geometry); ``reaim_every`` = k re-aims the
    laser every k frames to bring it back.

    Parameters
    ----------
    u1_pan_values : array_like, shape (n,), volts
    u1_tilt_start, tilt_step : float
        [V]; the paper steps 0.1 deg, i.e. 0.05 V at 2 deg/V.
    steps : int
        Frames per pan position.
    reaim_every : int, optional
        Re-aim period in frames; None aims only at the start of each pan position.

    Returns
    -------
    ndarray, shape (n * steps, 4), volts
    """
    pans = _values(u1_pan_values, 'u1_pan_values')
    if steps < 1:
        raise ValueError(f'steps: expected >= 1, got {steps}')
    if reaim_every is not None and reaim_every < 1:
        raise ValueError(f'reaim_every: expected None or >= 1, got {reaim_every}')
    ratio = rig.g1.tilt_drive.gain / rig.g2.tilt_drive.gain
    fs = rig.dac.full_scale
    out = np.zeros((len(pans) * steps, 4))
    row = 0
    for p in pans:
        base_k, base_u2 = 0, 0.0
        for k in range(steps):
            u1t = u1_tilt_start + k * tilt_step
            if abs(u1t) > fs:
                raise ValueError(f'the pattern leaves the +-{fs} V range at U1_tilt = {u1t}')
            if k == 0 or (reaim_every is not None and k % reaim_every == 0):
                base_k, base_u2 = k, aim_laser(rig, float(p), u1t, distance, u2_pan)
            out[row] = (p, u1t, u2_pan, base_u2 + (k - base_k) * tilt_step * ratio)
            row += 1
    if np.any(np.abs(out) > fs):
        raise ValueError(f'the pattern leaves the +-{fs} V range; use fewer or smaller steps')
    return out
