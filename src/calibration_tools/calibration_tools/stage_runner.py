"""Running calibration stages on captured data, for the node and the offline command (no rclpy).

- :func:`nominal_calibration`: the rig's design values (its description without its
  imperfections), the calibration every stage starts from;
- :func:`views_from_bags`: the camera frames of rosbag2 directories recorded by the
  calibration node (``<run>/poseNNN_stepMMM``), as :class:`~calibration_tools.stages.
  CaptureView`;
- :func:`compute`: one stage on those views, with the targets and options the capture plans
  of :mod:`calibration_tools.capture_plans` use;
- :func:`bag_digest` and :func:`flatten` for the file's provenance and the service response.
"""

from __future__ import annotations

import hashlib
import logging
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from calibration_tools import capture_plans as cp
from calibration_tools.stages import STAGES, CaptureView, StageResult

log = logging.getLogger('galvoscan.calibration.stage_runner')

#: Directory names written by the calibration node: one bag per capture step.
BAG_NAME = re.compile(r'^pose(\d+)_step(\d+)$')
#: G1 voltages closer than this are one board placement of a laser stage [V].
VOLTAGE_TOL = 1e-3

# ----------------------------------------------------------------------------- bags
def expand_bag_dirs(paths) -> list[Path]:
    """Bag directories from paths naming bags or folders of bags.

    A directory holding ``metadata.yaml`` (or a ``.mcap`` file) is a bag; any other
    directory stands for the bags directly inside it, sorted by name (the calibration
    node's ``<stage>_<time>`` run folder).

    Raises
    ------
    ValueError
        A path that does not exist, or a folder without bags.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    out = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise ValueError(f'bag {p} does not exist')
        if _is_bag(p):
            out.append(p)
            continue
        if not p.is_dir():
            raise ValueError(f'bag {p} is neither a rosbag2 directory nor a folder of bags')
        inner = sorted(q for q in p.iterdir() if q.is_dir() and _is_bag(q))
        if not inner:
            raise ValueError(f'{p} holds no rosbag2 directory (metadata.yaml or .mcap)')
        out += inner
    if not out:
        raise ValueError('no bags given')
    return out


def _is_bag(p: Path) -> bool:
    if p.is_file():
        return p.suffix == '.mcap'
    return p.is_dir() and ((p / 'metadata.yaml').exists() or any(p.glob('*.mcap')))


def views_from_bags(bag_dirs) -> list[CaptureView]:
    """The camera frames of bags as CaptureViews, bag after bag, each in stamp order.

    Parameters
    ----------
    bag_dirs : sequence of path
        rosbag2 directories with ``/camera/image_raw`` and ``/galvo/state`` (or folders of
        them, see :func:`expand_bag_dirs`). A bag named ``poseNNN_stepMMM`` (as the
        calibration node writes them) gives its frames ``pose_index = NNN``; otherwise the
        bag's position in the list.

    Returns
    -------
    list of CaptureView
        Image, the frame's reported voltages (DAC output), laser flag, pose and stamp.

    Raises
    ------
    ValueError
        A missing or unreadable bag, or no camera frame in any bag (a bag without frames
        is skipped with a logged warning).
    """
    from galvoscan_bag.frames import read_frames
    from galvoscan_bag.reader import BagReadError

    bags = expand_bag_dirs(bag_dirs)
    views, empty = [], []
    for i, bag in enumerate(bags):
        m = BAG_NAME.match(bag.name)
        pose = int(m.group(1)) if m else i
        n = 0
        try:
            for frame in read_frames(bag):
                if frame.image is None:
                    continue
                views.append(CaptureView(frame.image, np.asarray(frame.voltages, float),
                                         bool(frame.laser_on), pose, float(frame.stamp)))
                n += 1
        except (BagReadError, FileNotFoundError) as exc:
            raise ValueError(str(exc)) from None
        if n == 0:
            log.warning('bag %s holds no camera frame paired with a galvo state', bag)
            empty.append(str(bag))
    if not views:
        raise ValueError(f'no camera frames paired with galvo states in {", ".join(empty)}')
    return views


def bag_digest(bag_dir) -> str:
    """sha256 (hex) of a bag's MCAP file(s), in name order.

    For a bag with one MCAP file (what the node writes) it equals that file's sha256.

    Raises
    ------
    ValueError
        No MCAP file in the bag.
    """
    p = Path(bag_dir)
    files = [p] if p.is_file() and p.suffix == '.mcap' else sorted(p.glob('*.mcap'))
    if not files:
        raise ValueError(f'bag {p} holds no .mcap file')
    h = hashlib.sha256()
    for f in files:
        with open(f, 'rb') as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b''):
                h.update(chunk)
    return h.hexdigest()


def views_digest(views) -> str:
    """sha256 (hex) of views' images, voltages, laser flags and poses (in-process data)."""
    h = hashlib.sha256()
    for v in views:
        h.update(np.ascontiguousarray(v.image).tobytes())
        h.update(np.asarray(v.voltages, np.float64).tobytes())
        h.update(bytes([bool(v.laser_on)]) + int(v.pose_index).to_bytes(8, 'little'))
    return h.hexdigest()


def flatten(updates: dict, prefix: str = '') -> dict:
    """Nested stage updates as flat names: ``{'g1_pan': {'k': 1}}`` -> ``{'g1_pan.k': 1}``.

    Lists expand element-wise (``'laser_plane_v0[0]'`` ...); values are floats.
    """
    if not isinstance(updates, dict):
        raise ValueError(f'updates must be a dict, got {type(updates).__name__}')
    out = {}
    for key, value in updates.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict):
            out.update(flatten(value, f'{name}.'))
        elif isinstance(value, (list, tuple, np.ndarray)):
            for j, v in enumerate(np.asarray(value, dtype=np.float64).ravel()):
                out[f'{name}[{j}]'] = float(v)
        else:
            out[name] = float(value)
    return out


# ----------------------------------------------------------------------------- compute
def board_views(views: Sequence[CaptureView]) -> list[CaptureView]:
    """Views relabelled so that every (pose_index, G1 voltages) pair is its own pose.

    The laser stages' plans show several boards per scene, each at its own G1 voltages;
    the stages expect one board per pose.
    """
    import dataclasses

    keys: dict[tuple, int] = {}
    out = []
    for v in views:
        u = np.asarray(v.voltages, dtype=np.float64)
        key = (int(v.pose_index), int(round(u[0] / VOLTAGE_TOL)), int(round(u[1] / VOLTAGE_TOL)))
        out.append(dataclasses.replace(v, pose_index=keys.setdefault(key, len(keys))))
    return out


def stage_options(stage: str) -> dict:
    """Targets and options :func:`compute` passes to a stage (those the plans are made for)."""
    if stage == 'intrinsics':
        return {'board': cp.INTRINSICS_BOARD}
    if stage == 'dynamic_camera':
        # The reference rig's galvos are non-linear by up to ~0.02 deg: fit their cubic.
        return {'board': cp.CIRCLE_BOARD, 'refine_poly': 2}
    if stage == 'laser_plane':
        return {'board': cp.LASER_BOARD}
    if stage == 'laser_axis':
        return {'board': cp.LASER_BOARD}
    if stage == 'joint_correction':
        return {'sphere_radius': cp.SPHERE_RADIUS}
    raise ValueError(f"stage: unknown '{stage}', one of {', '.join(STAGES)}")


def compute(stage: str, views: Sequence[CaptureView], calibration,
            progress: Callable | None = None) -> StageResult:
    """Run one calibration stage on captured views.

    Targets and options are those of :func:`stage_options`. The dynamic-camera stage gets
    the plan's board placements (:func:`capture_plans.circle_board_pose`) as its board
    priors; the laser stages see every (pose_index, G1 voltages) pair as its own board pose
    (:func:`board_views`), since the plans show several boards per scene.

    Parameters
    ----------
    stage : str
        One of :data:`calibration_tools.stages.STAGES`.
    views : sequence of CaptureView
        Captured as :func:`calibration_tools.capture_plans.plan` describes.
    calibration : reconstructor.calibration_file.Calibration
        The current calibration (the one the plan was made with).
    progress : callable, optional
        ``progress(done, total, message)``.

    Returns
    -------
    StageResult
        Merge it with :func:`calibration_tools.stages.apply_result`.

    Raises
    ------
    ValueError
        Unknown stage, no views, or a stage that cannot compute (the reason in the message).
    """
    options = stage_options(stage)
    views = list(views)
    if not views:
        raise ValueError(f'{stage}: no views')
    for i, v in enumerate(views):
        if not isinstance(v, CaptureView):
            raise ValueError(f'views[{i}] must be a CaptureView, got {type(v).__name__}')
    if not hasattr(calibration, 'model'):
        raise ValueError('calibration must be a reconstructor.calibration_file.Calibration')

    def report(done, total, message=''):
        if progress is not None:
            progress(done, total, message)

    if stage == 'intrinsics':
        from calibration_tools.intrinsics import run_intrinsics

        return run_intrinsics(views, calibration, options['board'], progress=progress)
    if stage == 'dynamic_camera':
        from calibration_tools.dynamic_camera import run_dynamic_camera

        poses = sorted({int(v.pose_index) for v in views})
        unknown = [p for p in poses if p >= len(cp.CIRCLE_BOARD_OFFSETS)]
        if unknown:
            raise ValueError(f'dynamic_camera: pose_index {unknown} is not a placement of the '
                             f'capture plan (0..{len(cp.CIRCLE_BOARD_OFFSETS) - 1})')
        priors = {p: cp.circle_board_pose(p) for p in poses}
        return run_dynamic_camera(views, calibration, options['board'], board_pose=priors,
                                  refine_poly=options['refine_poly'], progress=progress)
    if stage == 'joint_correction':
        from calibration_tools.joint_correction import run_joint_correction

        report(0, 1, 'reconstructing and registering the sphere views')
        result = run_joint_correction(views, calibration,
                                      sphere_radius=options['sphere_radius'])
        report(1, 1, 'done')
        return result
    boards = board_views(views)
    report(0, 1, f'{len({v.pose_index for v in boards})} board placements')
    if stage == 'laser_plane':
        from calibration_tools.laser_plane import run_laser_plane

        result = run_laser_plane(boards, calibration, board=options['board'])
    else:
        from calibration_tools.laser_axis import run_laser_axis

        result = run_laser_axis(boards, calibration, board=options['board'])
    report(1, 1, 'done')
    return result
