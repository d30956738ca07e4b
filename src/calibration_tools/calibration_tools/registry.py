"""The calibration stages by name: each one's capture plan, targets and solver, in one table.

Every stage is an entry of :data:`REGISTRY`, in :data:`~calibration_tools.stages.STAGES`
order, with

- ``plan(model, quick)``: the capture steps (:mod:`calibration_tools.capture_plans`);
- ``options``: the options its solver is run with;
- ``targets(targets, model)``: the targets its solver is run with, from the kit's
  :class:`~calibration_tools.capture_plans.Targets` that
  :func:`~calibration_tools.capture_plans.choose_targets` derives from the operator's model:
  the plan and the solver of a stage get them from that one function, for the same
  calibration (the one the plan was made with);
- ``run(views, calibration, options, progress)``: the solver, in the Open3D ``run(config)``
  style (:class:`~calibration_tools.stages.StageResult` out);
- ``inputs``: what the operator must supply besides the captured views (the cell stage's
  robot-reported positions, the hand-eye stage's robot poses and artefact); they reach
  ``plan`` and ``run`` as options;
- ``pose_topic_input``: the input that the calibration node may take from the robot's
  ``geometry_msgs/PoseStamped`` topic instead, one robot pose per capture (hand-eye).

The node, the offline command and the benchmarks all go through :func:`plan` and
:func:`calibration_tools.stage_runner.compute`, which look stages up here; no other module
branches on a stage's name. Solvers are imported when they run (each pulls in OpenCV and
SciPy). No rclpy.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

from calibration_tools import capture_plans as cp
from calibration_tools.stages import (
    KNOWN_STAGES,
    VOLTAGE_TOL,
    CaptureStep,
    CaptureView,
    StageResult,
)

log = logging.getLogger('galvoscan.calibration.plans')


@dataclass(frozen=True)
class Stage:
    """One calibration stage: how to capture for it and how to compute it.

    Attributes
    ----------
    name : str
    plan : callable ``(model, quick: bool[, options]) -> list[CaptureStep]``
        Stages with ``inputs`` get the options (with the inputs) as a third argument.
    run : callable ``(views, calibration, options, report) -> StageResult``
        ``report(done, total, message)`` is always callable (a no-op without a listener).
    options : mapping
        Options passed to the solver.
    targets : callable ``(targets: capture_plans.Targets, model) -> dict``
        The targets passed to the solver (those its plan placed).
    inputs : mapping of str to str
        Options the operator supplies (each required), with a line saying what it is.
    pose_topic_input : str
        The one of ``inputs`` (robot flange poses) that the calibration node may instead
        record from the robot's pose topic, one pose per capture; '' for none.
    rows : bool
        Its solver fits one laser plane per G2 voltage from the boards lit there, so its
        boards come in rows (:func:`calibration_tools.operator_flow.row_key`).
    """

    name: str
    plan: Callable
    run: Callable
    options: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    inputs: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    targets: Callable = field(default=lambda targets, model: {})
    pose_topic_input: str = ''
    rows: bool = False


# ----------------------------------------------------------------------------- solvers
def _run_intrinsics(views, calibration, options, report):
    from calibration_tools.intrinsics import run_intrinsics

    return run_intrinsics(views, calibration, options['board'], progress=report,
                          max_abs_u1=options['max_abs_u1'])


def _run_dynamic_camera(views, calibration, options, report):
    """The board poses measured during capture (``measured_poses``, from the board's own
    detections) are the priors; without them the plan's placements
    (:func:`capture_plans.circle_board_poses`, views captured exactly where planned)."""
    from calibration_tools.dynamic_camera import run_dynamic_camera

    placed = options.get('measured_poses') or dict(enumerate(options['board_poses']))
    poses = sorted({int(v.pose_index) for v in views})
    unknown = [p for p in poses if p not in placed]
    if unknown:
        raise ValueError(f'dynamic_camera: pose_index {unknown} is not a placement with a '
                         f'known pose ({sorted(placed)})')
    priors = {p: placed[p] for p in poses}
    return run_dynamic_camera(views, calibration, options['board'], board_pose=priors,
                              refine_poly=options['refine_poly'], model=options['model'],
                              progress=report)


def board_views(views: Sequence[CaptureView]) -> list[CaptureView]:
    """Views relabelled so that every (pose_index, G1 voltages) pair is its own pose.

    The laser stages' plans show several boards per scene, each at its own G1 voltages;
    the stages expect one board per pose.
    """
    import dataclasses

    import numpy as np

    keys: dict[tuple, int] = {}
    out = []
    for v in views:
        u = np.asarray(v.voltages, dtype=np.float64)
        key = (int(v.pose_index), int(round(u[0] / VOLTAGE_TOL)), int(round(u[1] / VOLTAGE_TOL)))
        out.append(dataclasses.replace(v, pose_index=keys.setdefault(key, len(keys))))
    return out


def _laser_stage(solver: Callable) -> Callable:
    """A laser stage's runner: every (pose, G1 voltages) pair is a board (:func:`board_views`)."""
    def run(views, calibration, options, report):
        boards = board_views(views)
        report(0, 1, f'{len({v.pose_index for v in boards})} board placements')
        result = solver()(boards, calibration, board=options['board'],
                          edge_margin=options['edge_margin'],
                          min_spread=options['min_spread'])
        report(1, 1, 'done')
        return result
    return run


def _laser_plane_solver():
    from calibration_tools.laser_plane import run_laser_plane

    return run_laser_plane


def _laser_axis_solver():
    from calibration_tools.laser_axis import run_laser_axis

    return run_laser_axis


def _run_joint_correction(views, calibration, options, report):
    from calibration_tools.joint_correction import run_joint_correction

    report(0, 1, 'reconstructing and registering the sphere views')
    result = run_joint_correction(views, calibration, sphere_radius=options['sphere_radius'])
    report(1, 1, 'done')
    return result


def _run_cell_extrinsic(views, calibration, options, report):
    from calibration_tools.cell_extrinsic import run_cell_extrinsic

    return run_cell_extrinsic(views, calibration, options, progress=report)


def _plan_cell_extrinsic(model, quick, options):
    from calibration_tools.cell_extrinsic import plan_steps

    return plan_steps(model, quick, options)


def _run_hand_eye(views, calibration, options, report):
    from calibration_tools.hand_eye import run_hand_eye

    return run_hand_eye(views, calibration, options, progress=report)


def _plan_hand_eye(model, quick, options):
    from calibration_tools.hand_eye import plan_steps

    return plan_steps(model, quick, options)


# ----------------------------------------------------------------------------- plans
def _plan_joint_correction(model, quick):
    return cp.joint_correction_steps(model, [0.0] if quick else list(cp.JOINT_LATERALS),
                                     reach=(0.1, 0.1) if quick else (0.3, 0.1))


def _circle_board(targets, model) -> dict:
    return {'board': targets.circle_board,
            'board_poses': cp.circle_board_poses(model, targets)}


def _laser_board(targets, model) -> dict:
    """The laser grid the plan placed, how far stripe points keep from its circles, and how
    far a plane's stripe points must spread."""
    return {'board': targets.laser_board, 'edge_margin': targets.edge_margin,
            'min_spread': targets.min_spread}


def _options(**kw) -> MappingProxyType:
    return MappingProxyType(kw)


#: The stages, in calibration order.
REGISTRY: MappingProxyType = MappingProxyType({s.name: s for s in (
    # G1 is aimed at the board wherever the operator put it: plane mirrors move the virtual
    # camera but leave its intrinsics as they are, so views at any U1 count.
    Stage('intrinsics',
          lambda model, quick: cp.intrinsics_steps(model, 8 if quick else 30),
          _run_intrinsics, _options(max_abs_u1=cp.MAX_ABS_VOLTAGE + 0.1),
          targets=lambda t, m: {'board': t.checkerboard}),
    # The reference rig's galvos are non-linear by up to ~0.02 deg: fit their cubic.
    # 24 views on each side placement: l is seen through how the board's views turn and
    # shift across G1's range, most of all on the side placements' wide angles; twice their
    # 12 views brought l's standard error on the reference rig from 0.14 to 0.11 mm
    # predicted (calibration_tools.stopping) and from 0.13 to 0.06 mm in the solver (true
    # intrinsics, seed 0). Of the chain's stages this one carries the largest share of a
    # point's predicted error (reconstructor.uncertainty's by-stage shares).
    Stage('dynamic_camera',
          lambda model, quick: cp.dynamic_camera_steps(
              model, [20] if quick else [40, 24, 24, 24, 24]),
          _run_dynamic_camera, _options(refine_poly=2, model='physical', measured_poses=None),
          targets=_circle_board),
    Stage('laser_plane',
          lambda model, quick: cp.laser_plane_steps(model, 1 if quick else 2),
          _laser_stage(_laser_plane_solver), targets=_laser_board),
    Stage('laser_axis', cp.laser_axis_steps, _laser_stage(_laser_axis_solver),
          targets=_laser_board, rows=True),
    Stage('joint_correction', _plan_joint_correction,
          _run_joint_correction,
          targets=lambda t, m: {'sphere_radius': t.sphere_radius}),
    Stage('cell_extrinsic', _plan_cell_extrinsic, _run_cell_extrinsic,
          _options(),
          _options(cell_reference='YAML file of the robot-reported sphere positions in the '
                                  'cell frame (see calibration_tools.cell_extrinsic.'
                                  'read_reference)'),
          targets=lambda t, m: {'sphere_radius': t.sphere_radius}),
    Stage('hand_eye', _plan_hand_eye, _run_hand_eye, _options(),
          _options(robot_poses='YAML or CSV file of the robot\'s flange poses, base_T_flange '
                               '(see calibration_tools.robot_poses.read_robot_poses); the '
                               'calibration node can record them from the robot\'s pose topic '
                               'instead',
                   hand_eye_artefact='YAML file of the artefact\'s sphere layout and where it '
                                     'stands (see calibration_tools.hand_eye.read_artefact)'),
          pose_topic_input='robot_poses'),
)})
assert tuple(REGISTRY) == KNOWN_STAGES, 'REGISTRY and KNOWN_STAGES must name the same stages'


def stage(name: str) -> Stage:
    """The registered stage ``name``.

    Raises
    ------
    ValueError
        An unknown name (the message lists the known ones).
    """
    try:
        return REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"stage: unknown '{name}', one of {', '.join(KNOWN_STAGES)}") \
            from None


#: Stage options an operator may set per run (node parameter or offline flag of that name):
#: ``model``, the model form (``paper`` or ``physical``) the dynamic-camera stage fits;
#: ``measured_poses``, the board poses the capture measured (``{pose_index: V0_T_W}``,
#: :func:`calibration_tools.operator_flow.read_measured_poses`).
OVERRIDABLE = ('model', 'measured_poses')


def stage_inputs(name: str, inputs=None) -> dict:
    """The stage's options with the operator's ``inputs`` merged in, every required one present.

    Raises
    ------
    ValueError
        An input the stage needs is missing or empty, or one it does not take is given.
    """
    entry = stage(name)
    given = {k: v for k, v in dict(inputs or {}).items() if v not in (None, '')}
    unknown = sorted(set(given) - set(entry.inputs) - (set(OVERRIDABLE) & set(entry.options)))
    if unknown:
        raise ValueError(f"{name} takes no input {', '.join(unknown)}")
    missing = [k for k in entry.inputs if k not in given]
    if missing:
        raise ValueError(f'{name} needs ' + '; '.join(f'{k}: {entry.inputs[k]}'
                                                      for k in missing))
    return {**entry.options, **given}


def plan(name: str, calibration, quick: bool = False, inputs=None) -> list[CaptureStep]:
    """The capture plan of a calibration stage.

    Parameters
    ----------
    name : str
        One of :data:`calibration_tools.stages.KNOWN_STAGES`.
    calibration : reconstructor.calibration_file.Calibration or RigModel
        The operator's current model: targets are placed and G1 is aimed with it only.
    quick : bool
        A reduced plan (few frames; end-to-end tests).
    inputs : dict, optional
        What the operator supplies for stages with ``inputs`` (:func:`stage_inputs`).

    Returns
    -------
    capture_plans.Plan or list of CaptureStep
        A :class:`~calibration_tools.capture_plans.Plan` carries its ``report``: the steps
        that were replaced or dropped and why (each also logged as a warning).

    Raises
    ------
    ValueError
        Unknown stage, missing inputs, or what can be placed cannot constrain the stage's
        parameters (:class:`~calibration_tools.capture_plans.PlanError`, naming them).
    """
    entry = stage(name)
    options = stage_inputs(name, inputs)
    model = cp.current_model(calibration)
    if entry.inputs:
        options['calibration'] = calibration
        options.update(entry.targets(cp.choose_targets(model), model))
        steps = entry.plan(model, bool(quick), options)
    else:
        steps = entry.plan(model, bool(quick))
    for line in getattr(steps, 'report', ()):
        log.warning('plan %s: %s', name, line)
    return steps


def stage_options(name: str, calibration=None) -> dict:
    """Options the stage's solver is run with, with the targets for ``calibration``'s model
    (those its plan is made for) when it is given."""
    entry = stage(name)
    out = dict(entry.options)
    if calibration is not None:
        model = cp.current_model(calibration)
        out.update(entry.targets(cp.choose_targets(model), model))
    return out


def run(name: str, views: Sequence[CaptureView], calibration,
        progress: Callable | None = None, inputs=None) -> StageResult:
    """Run the registered solver of stage ``name`` (``stage_runner.compute`` checks the input)."""
    entry = stage(name)
    options = {**stage_options(name, calibration), **stage_inputs(name, inputs)}

    def report(done, total, message=''):
        if progress is not None:
            progress(done, total, message)

    return entry.run(views, calibration, options, report)
