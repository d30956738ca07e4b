"""The simulated rig as the application uses it (no rclpy): its design values, its truth, and
capture steps run on it.

- :func:`nominal_rig`, :func:`nominal_calibration`: the rig as designed, the calibration
  every stage starts from (what an operator knows before calibrating);
- :func:`execute_in_process`: capture steps run on a :class:`galvoscan_sim.Simulator`
  exactly as the driver's sim backend runs them;
- :func:`truth_model`, :func:`truth_calibration`: the simulator's true parameters,
  FOR TESTS AND COMPARISONS ONLY. A calibration made this way is not a calibration: it is
labelled ``source: simulator_truth`` in the file, and the reconstructor says so when it
loads one. Accuracy figures come from calibrating the simulated rig, never from this.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from pathlib import Path

from calibration_tools.placement import board_laser_steps, sphere_grid_steps
from calibration_tools.stages import CaptureStep, CaptureView
from reconstructor.calibration_file import Calibration
from reconstructor.model import CameraIntrinsics, MirrorParams, RigModel


def truth_model(rig, u2_pan: float = 0.0, kind: str = 'paper') -> RigModel:
    """The RigModel equivalent of a simulated rig.

    ``kind='paper'``: the paper's model (exact for a rig without imperfections);
    ``kind='physical'``: the physical mirror model, exact for every rig
    (``Rig.physical_model_parameters``).
    """
    p = rig.true_model_parameters(u2_pan)
    cam = rig.camera
    if kind == 'physical':
        return RigModel.from_dict({
            'intrinsics': {'fx': p.fx, 'fy': p.fy, 'cx': p.cx, 'cy': p.cy,
                           'dist': [float(x) for x in p.distortion], 'width': cam.width,
                           'height': cam.height},
            'model': 'physical', **rig.physical_model_parameters(u2_pan)})
    if kind != 'paper':
        raise ValueError(f"kind must be 'paper' or 'physical', got {kind!r}")
    return RigModel(
        intrinsics=CameraIntrinsics(fx=p.fx, fy=p.fy, cx=p.cx, cy=p.cy,
                                    dist=tuple(float(x) for x in p.distortion),
                                    width=cam.width, height=cam.height),
        g1_pan=MirrorParams(theta0=p.theta0_pan, k=p.k_pan),
        g1_tilt=MirrorParams(theta0=p.theta0_tilt, k=p.k_tilt),
        l=p.l, d=p.d,
        laser_plane_v0=p.pi0, laser_axis_dir=p.n, laser_axis_point=p.P,
        # the sim's theta4 = k2 * U2_tilt; only differences of theta4 enter the model
        g2_tilt=MirrorParams(theta0=math.pi / 4, k=p.k2),
    )


def truth_calibration(rig, u2_pan: float = 0.0, kind: str = 'paper') -> Calibration:
    """A calibration file object holding the simulator's truth, labelled as such."""
    return Calibration(model=truth_model(rig, u2_pan, kind), source='simulator_truth',
                       stages={'simulator_truth': {'rig': rig.name,
                                                   'note': 'true parameters, tests only'}})


NOMINAL_NOTE = 'design values from the rig description, before calibration'


# ----------------------------------------------------------------------------- nominal
def _zeroed(value):
    """The same structure with every number set to 0 (booleans and strings kept)."""
    if isinstance(value, dict):
        return {k: _zeroed(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_zeroed(v) for v in value]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return value
    return 0.0


def nominal_rig(rig):
    """The rig as designed: its description with every geometric imperfection zeroed.

    Parameters
    ----------
    rig : str, Path, dict or galvoscan_sim.Rig
        A shipped rig name (``'reference'``), a rig YAML path, a parsed rig description, or
        a Rig loaded from a file.

    Returns
    -------
    galvoscan_sim.Rig
        Lens distortion, camera mounting, laser mounting and every mirror's zero offset,
        gain error, nonlinearity, jitter, surface offset and axis tilt are zero; the image
        formation settings are kept.
    """
    from galvoscan_sim.config import read_yaml_file
    from galvoscan_sim.rig import RIG_DIR, Rig, rig_from_dict

    if isinstance(rig, dict):
        data, source = copy.deepcopy(rig), '<rig description>'
    else:
        if isinstance(rig, Rig):
            path = Path(rig.source)
            if not path.is_file():
                raise ValueError(f"rig: '{rig.name}' was not loaded from a file ({rig.source}); "
                                 f'pass its name, its YAML path or its parsed description')
        else:
            if not isinstance(rig, (str, Path)) or not str(rig):
                raise ValueError(f'rig must be a name, a path, a dict or a Rig, got {rig!r}')
            path = Path(rig)
            if not path.suffix and not path.exists():
                path = RIG_DIR / f'{rig}.yaml'
        data, source = read_yaml_file(path), str(path)
    imp = data.get('imperfections')
    if not isinstance(imp, dict):
        raise ValueError(f"rig {source}: no 'imperfections' section")
    data['imperfections'] = {k: (v if k == 'image' else _zeroed(v)) for k, v in imp.items()}
    return rig_from_dict(data, f'{source} (nominal: imperfections zeroed)')


def nominal_calibration(rig):
    """The calibration to start from: the rig's design values.

    The rig description with its ``imperfections`` removed (:func:`nominal_rig`), converted
    to a RigModel as :func:`galvoscan.simulated_rig.truth_model` does (exact for such a rig).
    What an operator knows before calibrating: lens data, the galvo heads' drawings and
    datasheet gains, where the laser was mounted.

    Parameters
    ----------
    rig : str, Path, dict or galvoscan_sim.Rig
        See :func:`nominal_rig`.

    Returns
    -------
    reconstructor.calibration_file.Calibration
        ``source: calibrated`` with a ``stages.nominal`` entry saying what it is.
    """
    from reconstructor.calibration_file import Calibration, now_iso

    design = nominal_rig(rig)
    return Calibration(model=truth_model(design), source='calibrated',
                       stages={'nominal': {'note': NOMINAL_NOTE, 'rig': design.name,
                                           'created': now_iso()}})


def execute_in_process(sim, steps, progress: Callable | None = None):
    """Run capture steps on a simulator as the driver's sim backend would.

    Per step: the scene is replaced when the step has one; every voltage row is quantised by
    the rig's DAC; a laser-off row gives ``sim.calibration_frame`` (a fully textured board
    frame at the calibration exposure), a laser-on row ``sim.render`` (a stripe frame); the
    view stores the quantised voltages and the step's pose_index, stamped on a virtual clock
    (``i / frame_rate`` within a step, steps back to back, plus half the laser exposure).

    Parameters
    ----------
    sim : galvoscan_sim.Simulator
        Its scene is replaced by the steps' scenes.
    steps : sequence of CaptureStep
    progress : callable, optional
        ``progress(done, total, message)`` after every frame.

    Returns
    -------
    views : list of CaptureView
    truths : list of FrameTruth
        The simulator's truth of each view (for scoring only).
    """
    from galvoscan_sim.scene import load_scene_text

    steps = list(steps)
    for i, s in enumerate(steps):
        if not isinstance(s, CaptureStep):
            raise ValueError(f'steps[{i}] must be a CaptureStep, got {type(s).__name__}')
    total = sum(s.frames for s in steps)
    views, truths = [], []
    clock = 0.0
    half_exposure = sim.rig.image.exposure / 2.0
    for s in steps:
        if s.scene_yaml is not None:
            sim.set_scene(load_scene_text(s.scene_yaml, f'<{s.note or "capture step"}>'))
        volts = sim.rig.dac.quantize(s.voltages)
        for i, v in enumerate(volts):
            frame = sim.render(v) if s.laser_on else sim.calibration_frame(v)
            views.append(CaptureView(frame.image, v.copy(), s.laser_on, s.pose_index,
                                     clock + i / s.frame_rate + half_exposure))
            truths.append(frame.truth)
            if progress is not None:
                progress(len(views), total, s.note)
        clock += len(volts) / s.frame_rate
    return views, truths


# ----------------------------------------------------------------------------- conveniences
def board_poses_on_laser(sim, model, u2_tilts, depths, board, *,
                         offsets=(0.0,), tilt_y: float = 0.4, seed: int = 0):
    """:func:`board_laser_steps` executed on ``sim``: returns ``(views, truths)``."""
    steps = board_laser_steps(model, u2_tilts, depths, board, offsets=offsets, tilt_y=tilt_y,
                              seed=seed)
    return execute_in_process(sim, steps)


def sphere_g1_grid(sim, model, u2_tilt: float, radius: float, pans, tilts, *,
                   depth: float = 0.65, lateral: float = 0.0, absolute: bool = False,
                   wall_gap: float | None = 0.0, occluder=None, occluded_nodes=(),
                   pose_index: int = 0):
    """:func:`sphere_grid_steps` executed on ``sim``.

    Returns
    -------
    views : list of CaptureView
    truths : list of FrameTruth
    centre : ndarray, shape (3,), metres
        Where the sphere was placed (scene frame).
    aim : ndarray, shape (2,), volts
        The G1 voltages aimed at the sphere (grid origin).
    """
    steps, centre, aim = sphere_grid_steps(
        model, u2_tilt, radius, pans, tilts, depth=depth, lateral=lateral, absolute=absolute,
        wall_gap=wall_gap, occluder=occluder, occluded_nodes=occluded_nodes,
        pose_index=pose_index)
    views, truths = execute_in_process(sim, steps)
    return views, truths, centre, aim
