"""Running calibration stages on captured data, for the node and the offline command (no rclpy).

- :func:`nominal_calibration`: the rig's design values (its description without its
  imperfections), the calibration every stage starts from;
- :func:`views_from_bags`: the camera frames of rosbag2 directories recorded by the
  calibration node (``<run>/poseNNN_stepMMM``), as :class:`~calibration_tools.stages.
  CaptureView`;
- :func:`compute`: one stage on those views, with the solver, targets and options of its
  entry in :mod:`calibration_tools.registry`;
- :func:`coverage` and :func:`coverage_line`: what a computed stage rests on (views used,
  voltage ranges spanned, residuals, standard errors where the stage gives them), for its
  log line and the service response;
- :func:`bag_digest` and :func:`flatten` for the file's provenance and the service response.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from calibration_tools import registry
from calibration_tools.stages import STAGES, CaptureView, StageResult

log = logging.getLogger('galvoscan.calibration.stage_runner')

#: Directory names written by the calibration node: one bag per capture step.
BAG_NAME = re.compile(r'^pose(\d+)_step(\d+)$')


@contextlib.contextmanager
def opencv_single_thread():
    """OpenCV on one thread while the block runs (its thread count restored after).

    OpenCV's parallel loops split their sums by thread, in an order that varies from run to
    run: two computes of the same intrinsics views differed in the 14th digit, and the
    dynamic-camera fit, whose l and d lie along a flat valley, carried that to about 1 um in
    l, 0.01 px in fx, and 5 % in the calibration's shape error over the range (reference
    rig). One thread makes a stage a function of its data. OpenCV's
    thread count is the process's: an extractor in the same process runs on one thread too
    while a stage computes.
    """
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


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
        elif isinstance(value, str):  # the model form ('physical'): its keys say it
            continue
        else:
            out[name] = float(value)
    return out


# ----------------------------------------------------------------------------- coverage
#: Voltage channels a coverage reports, by index of ``CaptureView.voltages``.
_CHANNELS = (('U1_pan', 0), ('U1_tilt', 1), ('U2_tilt', 3))


def coverage(result: StageResult, views: Sequence[CaptureView]) -> dict:
    """What a computed stage rests on.

    Parameters
    ----------
    result : StageResult
    views : sequence of CaptureView
        The views the stage was computed from.

    Returns
    -------
    dict
        ``views`` (captured), ``laser_views``, ``used`` and ``rejected`` (the stage's
        samples), ``poses`` (target placements), ``span_V`` ({channel: [min, max]} volts over
        the views, for U1_pan, U1_tilt and, over the laser views, U2_tilt), ``residuals``
        (the stage's, SI units) and ``standard_errors`` (when the stage gives them).
    """
    views = list(views)
    U = np.array([np.asarray(v.voltages, dtype=np.float64) for v in views]).reshape(-1, 4)
    lit = np.array([bool(v.laser_on) for v in views], dtype=bool)
    span = {}
    for name, j in _CHANNELS:
        sel = U[lit, j] if name.startswith('U2') else U[:, j]
        if sel.size:
            span[name] = [float(sel.min()), float(sel.max())]
    return {
        'views': len(views), 'laser_views': int(lit.sum()),
        'used': int(result.samples_used), 'rejected': int(result.samples_rejected),
        'poses': len({int(v.pose_index) for v in views}),
        'span_V': span,
        # where the views looked: the distinct G1 voltages (0.01 V), for coverage maps
        'u1_V': np.unique(np.round(U[:, :2], 2), axis=0).tolist(),
        'residuals': {k: float(v) for k, v in result.residuals.items()},
        'standard_errors': flatten(dict(getattr(result, 'standard_errors', None) or {})),
    }


def coverage_line(stage: str, cov: dict) -> str:
    """One line of a stage's :func:`coverage`, for logs and the service response."""
    span = ', '.join(f'{k} {a:+.2f}..{b:+.2f} V' for k, (a, b) in cov['span_V'].items()
                     if a != b or k.startswith('U1'))
    res = ', '.join(f'{k} {v:.3g}' for k, v in cov['residuals'].items()
                    if 'rms' in k or 'max' in k)
    line = (f'{stage} coverage: {cov["used"]} samples used, {cov["rejected"]} rejected, from '
            f'{cov["views"]} views ({cov["laser_views"]} lit) of {cov["poses"]} placement(s); '
            f'span {span}; residuals {res or "none"}')
    if cov['standard_errors']:
        line += '; standard errors ' + ', '.join(
            f'{k} {v:.3g}' for k, v in list(cov['standard_errors'].items())[:8])
    return line


# ----------------------------------------------------------------------------- verdict
#: A calibration is good when no view of its uncertainty map predicts more than this many
#: times the map's median error (flat over the range).
VERDICT_FLATNESS = 4.0
#: The chain's stages whose covariances the verdict needs (the joint correction has none).
VERDICT_STAGES = tuple(s for s in STAGES if s != 'joint_correction')


def verdict(calibration) -> str:
    """One line on a calibration: ``good: ...``, ``redo <stage> ...`` (which stage, and
    near which G1 voltages), or ``incomplete: ...``.

    From the predicted uncertainty map over +-8 V at the depth where the laser plane at
    U2 = 0 crosses V0's axis (:func:`reconstructor.uncertainty.point_uncertainty_map`): good
    when its worst view is within :data:`VERDICT_FLATNESS` x its median; else the stage
    whose parameters carry the largest share of the worst view's variance is named, with
    the view's voltages (capture more views there, or views that constrain it better).
    """
    from reconstructor.uncertainty import frame_noise, parameter_covariance, point_uncertainty_map

    try:
        pc = parameter_covariance(calibration)
    except ValueError as exc:
        return f'incomplete: {exc}'
    # a stage counts once it stored a covariance, even when a later stage re-estimated all
    # its parameters (the laser bundle takes the laser plane's U2 = 0 plane)
    have = {s for s, rec in (calibration.stages or {}).items()
            if isinstance(rec, dict) and rec.get('covariance')}
    missing = [s for s in VERDICT_STAGES if s not in have]
    if missing:
        return f"incomplete: no covariance yet from {', '.join(missing)}"
    from calibration_tools.capture_plans import laser_crossing_depth

    depth = laser_crossing_depth(calibration.model)
    try:
        umap = point_uncertainty_map(calibration.model, pc, depth=float(depth),
                                     frame_noise_v=frame_noise(calibration))
    except ValueError as exc:
        return f'incomplete: {exc}'
    worst, up, ut = umap.worst()
    median = float(np.nanmedian(umap.sigma_m))
    head = (f'predicted 1-sigma point error {umap.rms_m * 1e3:.3f} mm RMS over +-8 V at '
            f'{depth * 1e3:.0f} mm, worst {worst * 1e3:.3f} mm at U1 = ({up:+.1f}, {ut:+.1f}) V')
    if umap.frame_rms_m > 0:  # the verdict judges the calibration's part only
        head += (f"; the galvos' frame noise adds {umap.frame_rms_m * 1e3:.3f} mm "
                 f'({umap.total_rms_m * 1e3:.3f} mm together)')
    if not (worst > VERDICT_FLATNESS * median):
        return f'good: {head}'
    i = int(np.argmin(np.abs(umap.u_tilt - ut)))
    j = int(np.argmin(np.abs(umap.u_pan - up)))
    stage = max(umap.by_stage, key=lambda s: umap.by_stage[s][i, j])
    return (f'redo {stage.split(" ")[0]} with views near U1 = ({up:+.1f}, {ut:+.1f}) V: '
            f'{head}, {worst / median:.1f} x the median')


# ----------------------------------------------------------------------------- compute
def compute(stage: str, views: Sequence[CaptureView], calibration,
            progress: Callable | None = None, inputs=None) -> StageResult:
    """Run one calibration stage on captured views.

    The stage's solver, targets and options are those of its entry in
    :data:`calibration_tools.registry.REGISTRY`.

    Parameters
    ----------
    stage : str
        One of :data:`calibration_tools.stages.KNOWN_STAGES`.
    views : sequence of CaptureView
        Captured as :func:`calibration_tools.registry.plan` describes.
    calibration : reconstructor.calibration_file.Calibration
        The current calibration (the one the plan was made with).
    progress : callable, optional
        ``progress(done, total, message)``.
    inputs : dict, optional
        What the operator supplies for the stage (:func:`calibration_tools.registry.
        stage_inputs`), e.g. ``{'cell_reference': path}`` for ``cell_extrinsic``.

    Returns
    -------
    StageResult
        Merge it with :func:`calibration_tools.stages.apply_result`. Its
        ``extra['coverage']`` holds the stage's :func:`coverage` (also logged, as
        :func:`coverage_line`).

    Raises
    ------
    ValueError
        Unknown stage, no views, or a stage that cannot compute (the reason in the message).

    The same views and calibration give the same result to the last bit: the solver runs with
    OpenCV on one thread (:func:`opencv_single_thread`).
    """
    registry.stage(stage)
    views = list(views)
    if not views:
        raise ValueError(f'{stage}: no views')
    for i, v in enumerate(views):
        if not isinstance(v, CaptureView):
            raise ValueError(f'views[{i}] must be a CaptureView, got {type(v).__name__}')
    if not hasattr(calibration, 'model'):
        raise ValueError('calibration must be a reconstructor.calibration_file.Calibration')
    with opencv_single_thread():
        result = registry.run(stage, views, calibration, progress, inputs)
    result.extra['coverage'] = coverage(result, views)
    log.info(coverage_line(stage, result.extra['coverage']))
    return result
