"""Why the physical model's laser-axis stage fits a cone with an offset: the planes a real G2
sweeps do not contain its axis (the fan is not square to the mirror axis, the mirror surface
is off the axis), and the planes through one line of the paper's method miss them by tens of
micrometres at the ends of the scans' voltage range. The simulator's exact sheets (the
reference rig's G2 ray-traced off its mirror), no images."""

import dataclasses
import math

import numpy as np

from calibration_tools.laser_axis import fit_axis
from galvoscan import sim_scores
from galvoscan.simulated_rig import nominal_rig, truth_model
from galvoscan_sim import load_rig
from reconstructor.model import MirrorParams, laser_plane_v0


def _worst_gap(rig, method, fit_offset, volts):
    planes = sim_scores._true_planes(rig, volts)
    fit = fit_axis(planes, volts, poly_degree=3, method=method, fit_offset=fit_offset)
    model = dataclasses.replace(
        truth_model(rig), laser_plane_v0=sim_scores._true_planes(rig, [0.0])[0],
        laser_axis_dir=fit.direction, laser_axis_point=fit.point,
        g2_tilt=MirrorParams(theta0=math.pi / 4, k=fit.k, poly=tuple(fit.poly)))
    return max(sim_scores._plane_gap(np.asarray(laser_plane_v0(model, float(u))), t)
               for u, t in zip(volts, planes, strict=True))


def test_a_cone_with_an_offset_represents_the_true_sheets_and_planes_through_a_line_do_not():
    volts = np.linspace(-8.0, 5.5, 19)
    rig = load_rig('reference')
    cone = _worst_gap(rig, 'cone', True, volts)
    line = _worst_gap(rig, 'paper', False, volts)
    assert cone < 15e-6 and line > 40e-6, (cone, line)
    # the same rig built without imperfections: the cone adds nothing (the ~9 um left is the
    # rigid-rotation model's floor on this G2, imperfections or not)
    ideal = nominal_rig(rig)
    floor = _worst_gap(ideal, 'paper', False, volts)
    assert abs(_worst_gap(ideal, 'cone', True, volts) - floor) < 0.1e-6
    assert cone < 1.2 * floor < line / 4
