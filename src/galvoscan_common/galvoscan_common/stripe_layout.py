"""Which way the laser stripe runs in the image, from the laser plane seen by the camera.

The one place where the chain decides the stripe's direction: capture plans and targets,
stripe extraction, the laser stages, joint correction, evaluation scenes and scan patterns
all take it from :func:`stripe_layout` (through ``reconstructor.planning.stripe_layout``
for a calibration, ``galvoscan_sim.rig_family`` for a simulated rig), never from an
assumed laser position.

The laser plane at U2 = 0 in V0 (the view at U1 = 0), ``n . X + e = 0``, is on a surface
facing the camera the image line ``n_x x + n_y y = const`` in normalised coordinates; its
normal in pixels is ``(n_x / fx, n_y / fy)``. A laser below or above the camera (the sheet
nearly horizontal, ``|n_y| > |n_x|``) draws a stripe along the image rows that G2 moves up
and down, i.e. along V0's y, and G1's tilt moves the view across it; a laser beside the
camera draws one along the columns that G2 moves along V0's x, across which G1's pan moves
the view. G1's pan turns the view about V0's y (moving it along x) and its tilt about x
(moving it along y), so the V0 axis the stripe moves along and the G1 axis index are one
number, :attr:`StripeLayout.across`.

An oblique stripe is taken along the nearer of rows and columns. The extractor finds one
centre per column (or row) and fits each profile across the stripe along that column: a
stripe ``t`` off the columns' normal is ``1 / cos t`` wider along them (and its centre along
them is still the centre: the profile stays symmetric), up to :data:`MAX_STRIPE_TILT`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Largest angle of the stripe to the nearer of the image rows and columns [rad] the chain
#: takes. At 20 deg a stripe is 6 % wider along the extraction direction (1 / cos 20 deg)
#: and its cut with a flat target is still one point per column (row); the capture plans
#: place the boards along the nearer image axis, so a board's stripe leaves a 20 deg
#: tilted band of it, tan 20 deg = 36 % of the board's length across it, inside the board
#: of the kit's 11 x 8 grid (8 / 11 = 73 %). Beyond it the stripe is refused with this reason.
MAX_STRIPE_TILT = math.radians(20.0)

#: The extractor's orientation names (``stripe_extractor.config.ORIENTATIONS``).
ORIENTATION_OF_ACROSS = {1: 'horizontal', 0: 'vertical'}


@dataclass(frozen=True)
class StripeLayout:
    """The stripe's direction in the image and what moves across it.

    Attributes
    ----------
    orientation : str
        ``'horizontal'`` (along the rows: laser below or above the camera) or ``'vertical'``
        (along the columns: laser beside it), the stripe extractor's ``orientation``.
    tilt : float
        Angle of the stripe to that image axis [rad], in [0, pi/4].
    across : int
        The V0 axis (0: x, 1: y) along which the stripe moves as U2 changes, and the index
        of the G1 voltage (0: pan, 1: tilt) that moves the view that way.
    along : int
        The other V0 axis: the stripe's own direction in V0.
    sign : float
        +1 when increasing U2 tilt moves the sheet towards +``across`` on the optical axis
        (the laser below, or to the right, as seen by the camera), -1 the other way.
    side : float
        +1 when the laser sits on the +``across`` side of the camera (below it, V0's y
        pointing down, or to its right), -1 on the other (above, left): where the sheet
        lies at the camera's depth.
    """

    orientation: str
    tilt: float
    across: int
    along: int
    sign: float
    side: float = 1.0

    @property
    def turn(self) -> float:
        """The turn about V0's z (the optical axis) [rad] that takes the paper's layout, the
        laser below the camera, to this one: 0 below, pi above, -pi/2 to the right, pi/2 to
        the left (``galvoscan_sim.rig_family.LASER_SIDES``). An object set up for a laser
        below, turned by it, meets this laser as the paper's object meets the paper's."""
        if self.across == 1:
            return 0.0 if self.side > 0 else math.pi
        return -math.pi / 2 if self.side > 0 else math.pi / 2

    @property
    def image_axis(self) -> int:
        """Index into (u, v) the stripe moves along: 1 (v, rows) or 0 (u, columns)."""
        return self.across

    def point_on_plane(self, plane, along: float, depth: float) -> np.ndarray:
        """The V0 point [m] of ``plane`` (a, b, c, e) at ``along`` on the stripe's own V0
        axis and at ``depth``, its coordinate across the stripe solved (NaN when the
        plane contains that direction)."""
        pi = np.asarray(plane, dtype=np.float64)
        p = np.zeros(3)
        p[self.along], p[2] = along, depth
        den = pi[self.across]
        p[self.across] = (-(pi[self.along] * along + pi[2] * depth + pi[3]) / den
                          if abs(den) > 1e-12 else np.nan)
        return p

    def unit(self, axis: int) -> np.ndarray:
        """V0's unit vector of axis ``axis`` (e.g. ``layout.unit(layout.along)``)."""
        e = np.zeros(3)
        e[axis] = 1.0
        return e

    def refusal(self) -> str | None:
        """Why the chain cannot take this stripe, or None."""
        if self.tilt <= MAX_STRIPE_TILT + 1e-12:
            return None
        return (f'the stripe runs {math.degrees(self.tilt):.1f} deg off the nearest of the '
                f'image rows and columns; the stripe extraction and the capture plans take it '
                f'along one of them within {math.degrees(MAX_STRIPE_TILT):.0f} deg (turn the '
                'line laser about its beam, or the G2 head about the optical axis, to bring '
                'the stripe along the rows or the columns)')


def stripe_layout(plane_v0, fx: float, fy: float, plane_moved=None) -> StripeLayout:
    """The stripe layout of a laser plane seen at U1 = 0.

    Parameters
    ----------
    plane_v0 : array_like, shape (4,)
        The laser plane at U2 = 0 in V0 (a, b, c, e), normal of any length.
    fx, fy : float
        Focal lengths [px].
    plane_moved : array_like, shape (4,), optional
        The plane at a slightly larger U2 tilt; gives :attr:`StripeLayout.sign` (+1 without it).

    Raises
    ------
    ValueError
        A plane that is not finite, or one seen edge-on (containing the optical axis'
        direction only: no stripe direction).
    """
    pi = np.asarray(plane_v0, dtype=np.float64).reshape(-1)
    if pi.shape != (4,) or not np.all(np.isfinite(pi)) or not (fx > 0 and fy > 0):
        raise ValueError(f'stripe_layout: expected a finite plane (4,) and focal lengths > 0, '
                         f'got {plane_v0!r}, {fx!r}, {fy!r}')
    gx, gy = abs(pi[0]) / fx, abs(pi[1]) / fy
    if math.hypot(gx, gy) < 1e-12 * max(abs(pi[2]), 1.0) / max(fx, fy):
        raise ValueError('stripe_layout: the laser plane is perpendicular to the image: the '
                         'stripe has no direction')
    angle_to_rows = math.atan2(gx, gy)            # normal's angle from the image's v axis
    across = 1 if angle_to_rows <= math.pi / 4 else 0
    tilt = angle_to_rows if across == 1 else math.pi / 2 - angle_to_rows
    # the laser's side: where the sheet lies at the camera's depth (z = 0), across the stripe
    side = 1.0 if -pi[3] / pi[across] >= 0.0 else -1.0
    sign = 1.0
    if plane_moved is not None:
        q = np.asarray(plane_moved, dtype=np.float64).reshape(-1)
        # where each plane meets V0's optical-axis-parallel line through the stripe direction:
        # the coordinate along ``across`` at the crossing depth of the first plane
        if abs(pi[2]) > 1e-12 and abs(q[across]) > 1e-12 and abs(pi[across]) > 1e-12:
            z = -pi[3] / pi[2]
            a0 = -(pi[2] * z + pi[3]) / pi[across]
            a1 = -(q[2] * z + q[3]) / q[across]
            sign = 1.0 if a1 >= a0 else -1.0
    return StripeLayout(ORIENTATION_OF_ACROSS[across], float(tilt), across, 1 - across, sign,
                        side)
