"""``galvoscan calibrate``: calibration stages from the command line (no rclpy).

    galvoscan calibrate STAGE --bags DIR [DIR ...] --calibration FILE
                        [--initial FILE | --rig NAME] [--reference FILE]
                        [--robot-poses FILE --artefact FILE]
    galvoscan calibrate STAGE --sim [--rig NAME] [--seed N] [--quick] --calibration FILE
                        [--reference FILE] [--robot-poses FILE --artefact FILE]
    galvoscan calibrate all --sim [--rig NAME] [--seed N] [--quick] --calibration FILE
                        [--initial FILE]

STAGE is one of intrinsics, dynamic_camera, laser_plane, laser_axis, joint_correction (the
rig's chain, which ``all`` runs in order) or cell_extrinsic (where the calibrated scanner
sits in the robot cell: ``--reference FILE`` gives the robot-reported sphere positions, see
:func:`calibration_tools.cell_extrinsic.read_reference`; the result is the file's
``cell_T_v0``, which the reconstructor publishes on ``/tf_static``) or hand_eye (where the
scanner sits on a robot's flange: ``--robot-poses FILE``, the flange poses, see
:func:`calibration_tools.robot_poses.read_robot_poses`, and ``--artefact FILE``, see
:func:`calibration_tools.hand_eye.read_artefact`; the result is the file's ``cell_T_v0``
with the flange as its frame). The bags are rosbag2 directories recorded by the calibration
node (``poseNNN_stepMMM``), or the node's run folder holding them. The stage starts from
FILE when it exists, else from ``--initial FILE``, else from the design values of the
simulated rig ``--rig`` (see :func:`galvoscan.simulated_rig.nominal_calibration`); the
result is merged and FILE is written atomically, with the bags' paths and sha256 digests.

``STAGE --sim`` captures that one stage on the rig simulator in this process, starting from
FILE. For cell_extrinsic and hand_eye it also prints how far the result lies from the
simulator's true mounting, the rig's ``W_T_V0`` (W is the cell for cell_extrinsic, the
flange for hand_eye), in mm and degrees. ``all --sim`` runs every stage of the chain in
order on the rig simulator: each stage's capture plan (made with the calibration so far) is
rendered as the driver's sim backend would, computed and merged, and FILE is written after
every stage. It starts from ``--initial FILE`` or the design values of ``--rig`` (FILE is
replaced).

Exit status: 0 on success, 1 on any error (the message says what is wrong).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from calibration_tools.stages import KNOWN_STAGES, MOUNTING_STAGES, STAGES
from galvoscan.progress import Progress

PROG = 'galvoscan calibrate'


class UsageError(ValueError):
    """Bad command line."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise UsageError(message)


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description=__doc__.split('\n\n')[0].strip(),
                formatter_class=argparse.RawDescriptionHelpFormatter,
                epilog='stages: ' + ', '.join(KNOWN_STAGES) + ', or all (with --sim)')
    p.add_argument('stage', metavar='STAGE', help='calibration stage, or all (with --sim)')
    p.add_argument('--bags', nargs='+', metavar='DIR',
                   help='rosbag2 directories (or folders of them) captured for the stage')
    p.add_argument('--calibration', required=True, metavar='FILE',
                   help='calibration YAML to update (written atomically)')
    p.add_argument('--initial', metavar='FILE',
                   help='calibration to start from when FILE does not exist yet')
    p.add_argument('--rig', metavar='NAME',
                   help="simulated rig (name or YAML) whose design values start the "
                        "calibration (default for --sim: reference); with --sim and "
                        "--initial, only the rig simulated")
    p.add_argument('--sim', action='store_true',
                   help='all: capture every stage in-process on the rig simulator')
    p.add_argument('--quick', action='store_true', help='all --sim: reduced capture plans')
    p.add_argument('--seed', type=int, default=0, help='--sim: simulator seed')
    p.add_argument('--reference', metavar='FILE',
                   help='cell_extrinsic: robot-reported sphere positions (YAML, metres)')
    p.add_argument('--robot-poses', metavar='FILE',
                   help='hand_eye: the flange poses base_T_flange (YAML or CSV: metres, '
                        'quaternion x y z w)')
    p.add_argument('--artefact', metavar='FILE',
                   help="hand_eye: the artefact's sphere layout and where it stands (YAML)")
    p.add_argument('--model', choices=('physical', 'paper'), default=None,
                   help="dynamic_camera: the model form to fit (default physical: each mirror "
                        "a plane on its own axis; paper: the paper's model as published)")
    return p


#: Command-line option -> the stage input it gives (:func:`calibration_tools.registry.
#: stage_inputs` refuses one the stage does not take).
_INPUT_OPTIONS = {'reference': 'cell_reference', 'robot_poses': 'robot_poses',
                  'artefact': 'hand_eye_artefact'}


def _inputs(args) -> dict:
    """The operator's inputs for the stage, from the options given."""
    out = {name: getattr(args, option) for option, name in _INPUT_OPTIONS.items()
           if getattr(args, option)}
    if getattr(args, 'model', None) and args.stage == 'dynamic_camera':
        out['model'] = args.model
    return out


def _starting_calibration(args, fresh: bool):
    """The calibration a run starts from, and a description of where it came from."""
    from galvoscan.simulated_rig import nominal_calibration
    from reconstructor import calibration_file

    path = Path(args.calibration)
    if not fresh and path.exists():
        cal, origin = calibration_file.load(path), str(path)
    elif args.initial:
        cal, origin = calibration_file.load(args.initial), args.initial
    elif args.rig or fresh:
        rig = args.rig or 'reference'
        try:
            cal = nominal_calibration(rig)
        except OSError as exc:
            raise ValueError(f'rig {rig}: {exc}') from None
        origin = f'design values of rig {rig}'
    else:
        raise ValueError(f'{path} does not exist: give --initial FILE or --rig NAME to '
                         f'start from')
    if cal.source != 'calibrated':
        raise ValueError(f"{origin} holds source '{cal.source}', not a calibration: "
                         f'refusing to calibrate on top of it')
    return cal, origin


def _progress_callback(progress: Progress, name: str, unit: str = 'items'):
    """A stage's ``progress(done, total, message)`` shown on ``progress``."""
    state = {'total': None, 'done': 0}

    def callback(done, total, message=''):
        if state['total'] != total:
            state['total'], state['done'] = total, 0
            progress.stage(name, total, unit)
        progress.advance(max(int(done) - state['done'], 0), message)
        state['done'] = max(int(done), state['done'])

    return callback


def _report(result, progress: Progress):
    from calibration_tools.stage_runner import flatten

    progress.log(f'{result.stage}: {result.samples_used} samples used, '
                 f'{result.samples_rejected} rejected')
    for reason in result.rejected[:10]:
        progress.log(f'  rejected: {reason}')
    if len(result.rejected) > 10:
        progress.log(f'  ... and {len(result.rejected) - 10} more rejections')
    for key, value in result.residuals.items():
        progress.log(f'  residual {key} = {value:.6g}')
    mounting = result.extra.get(result.stage) if result.stage in MOUNTING_STAGES else None
    if mounting is not None:  # the measured cell_T_v0 and its standard errors
        import numpy as np
        from scipy.spatial.transform import Rotation

        T = np.asarray(mounting['cell_T_v0'])
        progress.log(f"  cell_T_v0 ({mounting['cell_frame']} -> v0): translation "
                     f'{np.round(T[:3, 3], 6).tolist()} m +- '
                     f"{np.round(mounting['translation_std_m'], 7).tolist()}, rotation vector "
                     f'{np.round(Rotation.from_matrix(T[:3, :3]).as_rotvec(), 6).tolist()} '
                     f"rad +- {np.round(mounting['rotation_std_rad'], 7).tolist()}")
    sigma = flatten(getattr(result, 'standard_errors', None) or {})
    for key, value in flatten(result.updates).items():
        se = sigma.get(key)
        tail = '' if se is None else ' (held fixed)' if se == 0 else f' +- {se:.3g}'
        progress.log(f'  {key} = {value:.9g}{tail}')


def run_stage(args, progress: Progress) -> int:
    from calibration_tools import registry, stage_runner
    from calibration_tools.stages import apply_result
    from reconstructor import calibration_file

    if args.sim:
        return run_stage_sim(args, progress)
    if not args.bags:
        raise UsageError(f'{args.stage} needs --bags DIR [DIR ...] (or --sim)')
    cal, origin = _starting_calibration(args, fresh=False)
    progress.log(f'{args.stage}: starting from {origin}')
    bags = stage_runner.expand_bag_dirs(args.bags)
    progress.stage('reading bags', len(bags), 'bags')
    views = []
    for bag in bags:
        views += stage_runner.views_from_bags([bag])
        progress.advance(1, bag.name)
    progress.log(f'{len(views)} frames from {len(bags)} bag(s)')
    t0 = time.monotonic()
    inputs = _inputs(args)
    if 'measured_poses' in registry.stage(args.stage).options:
        # the target poses the capture measured, written beside its bags
        from calibration_tools.operator_flow import read_measured_poses

        inputs['measured_poses'] = read_measured_poses(bags)
    result = stage_runner.compute(args.stage, views, cal,
                                  progress=_progress_callback(progress, args.stage),
                                  inputs=inputs)
    sources = [{'path': str(b.resolve()), 'sha256': stage_runner.bag_digest(b)} for b in bags]
    new = apply_result(cal, result, sources)
    calibration_file.save(new, args.calibration)
    _report(result, progress)
    progress.log(f'{args.stage}: computed in {time.monotonic() - t0:.1f} s; wrote '
                 f'{new.path}')
    progress.log(f'verdict: {stage_runner.verdict(new)}')
    return 0


def _simulator(args):
    """The in-process rig simulator of ``--rig`` (default reference), with an empty scene."""
    from galvoscan_sim import Simulator, load_rig, load_scene_text

    rig_name = args.rig or 'reference'
    try:
        rig = load_rig(rig_name)
    except OSError as exc:
        raise ValueError(f'rig {rig_name}: {exc}') from None
    empty = ('format_version: 1\nname: empty\nobjects:\n  - type: plane\n    name: floor\n'
             '    pose: {translation: [0.0, 0.0, 5.0]}\n    albedo: 0.1\n')
    return Simulator(rig, load_scene_text(empty), seed=args.seed), rig


def _sim_stage(stage, cal, sim, rig, args, progress: Progress):
    """Capture ``stage`` on the simulator with ``cal``, compute it, merge and save."""
    from calibration_tools import stage_runner
    from calibration_tools.capture_plans import total_frames
    from calibration_tools.registry import plan
    from calibration_tools.stages import apply_result
    from galvoscan.simulated_rig import execute_in_process
    from reconstructor import calibration_file

    t0 = time.monotonic()
    steps = plan(stage, cal, quick=args.quick, inputs=_inputs(args))
    views, _ = execute_in_process(
        sim, steps, progress=_progress_callback(progress, f'{stage}: capture', 'frames'))
    t1 = time.monotonic()
    result = stage_runner.compute(stage, views, cal, inputs=_inputs(args),
                                  progress=_progress_callback(progress, stage))
    source = {'path': f'in-process simulator: rig {rig.name}, seed {args.seed}, '
                      f'{len(steps)} capture steps',
              'sha256': stage_runner.views_digest(views)}
    cal = apply_result(cal, result, [source])
    calibration_file.save(cal, args.calibration)
    _report(result, progress)
    if stage in MOUNTING_STAGES:
        progress.log(_mounting_check(cal, rig, stage))
    progress.log(f'{stage}: {total_frames(steps)} frames in {len(steps)} steps, capture '
                 f'{t1 - t0:.1f} s, compute {time.monotonic() - t1:.1f} s')
    return cal


def _mounting_check(cal, rig, stage: str) -> str:
    """How far the measured ``cell_T_v0`` lies from the simulator's true mounting (the rig's
    ``W_T_V0``): the simulator's check of a mounting stage, for people (mm, deg)."""
    import numpy as np

    from calibration_tools.cell_extrinsic import rotation_angle

    T, truth = cal.cell_T_v0, rig.W_T_V0
    mm = float(np.linalg.norm(T[:3, 3] - truth[:3, 3])) * 1e3
    deg = float(np.degrees(rotation_angle(T[:3, :3] @ truth[:3, :3].T)))
    sigma = cal.stages[stage]
    return (f'{stage}: simulator check: cell_T_v0 is {mm:.4f} mm and {deg:.5f} deg from the '
            f"true mounting (the rig's W_T_V0); stated 1-sigma "
            f"{', '.join(f'{v * 1e3:.4f}' for v in sigma['translation_std_m'])} mm, "
            f"{', '.join(f'{np.degrees(v):.5f}' for v in sigma['rotation_std_rad'])} deg")


def run_stage_sim(args, progress: Progress) -> int:
    """One stage captured on the simulator, starting from FILE (or --initial / --rig)."""
    if args.bags:
        raise UsageError('--sim captures its own data: no --bags')
    cal, origin = _starting_calibration(args, fresh=False)
    sim, rig = _simulator(args)
    progress.log(f'{args.stage} on the simulated rig {rig.name} (seed {args.seed}), '
                 f'starting from {origin}')
    cal = _sim_stage(args.stage, cal, sim, rig, args, progress)
    progress.log(f'wrote {cal.path}')
    return 0


def run_all_sim(args, progress: Progress) -> int:
    if not args.sim:
        raise UsageError('all needs --sim (bags are captured and computed per stage)')
    if args.bags:
        raise UsageError('all --sim captures its own data: no --bags')
    if _inputs(args):
        raise UsageError('all runs the rig chain; cell_extrinsic (--reference) and hand_eye '
                         '(--robot-poses, --artefact) run after it')
    cal, origin = _starting_calibration(args, fresh=True)
    sim, rig = _simulator(args)
    progress.log(f'calibrating the simulated rig {rig.name} (seed {args.seed}'
                 f'{", quick plans" if args.quick else ""}), starting from {origin}')
    for stage in STAGES:
        cal = _sim_stage(stage, cal, sim, rig, args, progress)
    progress.log(f'wrote {cal.path}')
    return 0


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.WARNING, format='[%(name)s] %(levelname)s %(message)s')
    parser = _parser()
    if not argv or argv[0] in ('-h', '--help'):
        parser.print_help()
        return 0 if argv else 1
    progress = Progress(stream=sys.stdout)
    try:
        args = parser.parse_args(argv)
        if args.initial and args.rig and not args.sim:
            raise UsageError('--initial and --rig both name the calibration to start from; '
                             'give one (with --sim, --rig names the simulated rig)')
        if args.stage == 'all':
            return run_all_sim(args, progress)
        if args.stage not in KNOWN_STAGES:
            raise UsageError(f"unknown stage '{args.stage}'; one of "
                             f"{', '.join(KNOWN_STAGES)}, or all (with --sim)")
        return run_stage(args, progress)
    except UsageError as exc:
        print(f'{PROG}: error: {exc}\n{parser.format_usage().strip()}', file=sys.stderr)
        return 1
    except (ValueError, OSError, RuntimeError) as exc:
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
