"""Identification of the circles of many circle-board views while refining the model (no rclpy).

:func:`identify_views` runs :func:`calibration_tools.circle_board.identify_view` over all
views in rounds:

0. The board orientation and plane come from per-view PnP mapped into V0 with the
   approximate model (:func:`board_pose_from_views`); the views that show a large circle then
   fix the board's position modulo the 7-circle sub-pattern.
1. Each round labels every view, refines the model and the board pose(s) on the accepted
   views (robust loss) and repeats until the accepted labels stop changing.
2. Finally every view is verified against the refined model: all its circles must reproject
   within a tolerance derived from the residuals (a wrong label is a whole pitch, ~240 px,
   away), their sizes must match the board, and labels must be unique and on the board.
   Anything else is rejected with the reason.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from reconstructor.model import RigModel, v0_T_v

from .board_fit import (
    RefineResult,
    ViewObservation,
    _as_pose_dict,
    _as_transform,
    _rotation_angle,
    _transform,
    pnp_view,
    refine,
)
from .board_geometry import pixels_to_board
from .board_layout import CircleBoard
from .circle_board import CircleDetections, ViewIdentification, identify_view


# ------------------------------------------------------------------------------ identification
@dataclass
class IdentificationResult:
    """Result of :func:`identify_views`.

    Attributes
    ----------
    views : list of ViewIdentification
        One per input view, in input order.
    model : RigModel
        Model refined during identification.
    board_poses : dict of int to ndarray, shape (4, 4)
    refinement : RefineResult or None
        Last refinement on the accepted views.
    verify_px : float
        Reprojection tolerance of the final verification, pixels.
    rounds : int
    """

    views: list
    model: RigModel
    board_poses: dict
    refinement: RefineResult | None
    verify_px: float
    rounds: int
    log: list = field(default_factory=list)


def _lattice_shift(offsets, period, tol: float = 0.35):
    """Consensus of lattice offsets modulo ``period``: (shift shape (2,), supporting views).

    The offset agreed on by most views (within ``tol`` pitches, wrapped by the period) is
    averaged over its supporters; a view with a misjudged large circle does not move it.
    """
    offs = np.asarray(offsets, dtype=np.float64)
    best = None
    for o in offs:
        d = (offs - o + period / 2.0) % period - period / 2.0
        inl = np.all(np.abs(d) < tol, axis=1)
        if best is None or inl.sum() > best[0]:
            best = (int(inl.sum()), o + d[inl].mean(axis=0))
    return best[1], best[0]


def _mean_rotation(Rs) -> np.ndarray:
    """Chordal L2 mean of rotation matrices (projection of their sum onto SO(3))."""
    U_, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U_ @ Vt))])
    return U_ @ D @ Vt


def board_pose_from_views(
    detections: Sequence[CircleDetections],
    voltages,
    model: RigModel,
    board: CircleBoard,
    prior,
    *,
    min_circles: int = 4,
    max_outlier_deg: float = 3.0,
) -> tuple[np.ndarray, int]:
    """Board orientation and plane from per-view PnP, keeping the prior's in-plane position.

    Each view with at least ``min_circles`` circles is labelled relative to its first circle
    (lattice steps predicted with the prior, which need only be right to ~10 degrees), its
    board pose is solved by PnP and mapped into V0 with the approximate model. The mean
    orientation and median plane offset of those views replace the prior's; the prior's
    board origin is moved along its V0 ray onto the new plane. The position along the board
    stays the prior's (it is fixed modulo the sub-pattern by the large circles later).

    Parameters
    ----------
    detections : sequence of CircleDetections
    voltages : array_like, shape (n, 2), volts
    model : RigModel
    board : CircleBoard
    prior : array_like, shape (4, 4)
        Approximate ``V0_T_W``, metres.
    min_circles : int
    max_outlier_deg : float
        Views whose orientation differs more from the mean are left out.

    Returns
    -------
    V0_T_W : ndarray, shape (4, 4)
    n_views : int
        Views used (0: the prior is returned unchanged).
    """
    prior = _as_transform(prior, "prior")
    U = np.asarray(voltages, dtype=np.float64)
    if U.shape != (len(detections), 2):
        raise ValueError(f"voltages must have shape ({len(detections)}, 2), got {U.shape}")
    Rs, ts = [], []
    for det, u in zip(detections, U, strict=True):
        if len(det) < min_circles:
            continue
        xy = pixels_to_board(model, det.centres, u[0], u[1], prior)
        if not np.isfinite(xy).all():
            continue
        frac = board.lattice_coords(xy)
        rel = frac - frac[0]
        lab = np.rint(rel)
        if np.abs(rel - lab).max() > 0.3 or len({tuple(r) for r in lab}) != len(lab):
            continue
        rc = lab + np.rint(frac[0])
        P = np.column_stack([
            (rc[:, 1] - board.centre_col) * board.pitch,
            (rc[:, 0] - board.centre_row) * board.pitch,
            np.zeros(len(rc)),
        ])
        radii = np.where(board.is_large_rc(rc[:, 0], rc[:, 1]) & det.large & det.size_known,
                         board.large_diameter / 2.0, board.small_diameter / 2.0)
        try:
            V_T_W, _ = pnp_view(model.intrinsics, P, radii, det.centres)
        except (ValueError, cv2.error):
            continue
        T = v0_T_v(model, u[0], u[1]) @ V_T_W
        Rs.append(T[:3, :3])
        ts.append(T[:3, 3])
    if not Rs:
        return prior.copy(), 0
    Rs = np.array(Rs)
    ts = np.array(ts)
    R = _mean_rotation(Rs)
    for _ in range(2):
        ang = np.degrees(_rotation_angle(np.swapaxes(Rs, -1, -2) @ R))
        keep = ang <= max_outlier_deg
        if keep.sum() == 0:
            return prior.copy(), 0
        R = _mean_rotation(Rs[keep])
    n = R[:, 2]
    offset = float(np.median(ts[keep] @ n))  # plane: n . x = offset
    o = prior[:3, 3]
    denom = float(n @ o)
    t = o * (offset / denom) if abs(denom) > 1e-9 else o
    return _transform(R, t), int(keep.sum())


def identify_views(
    detections: Sequence[CircleDetections],
    voltages,
    model: RigModel,
    board: CircleBoard,
    board_poses,
    *,
    pose_index=None,
    refine_mirrors: bool = True,
    refine_theta0: bool = True,
    refine_poly: int = 0,
    max_offset_pitch: float = 0.25,
    verify_sigma: float = 8.0,
    verify_floor_px: float = 2.0,
    verify_max_pitch: float = 0.2,
    max_rounds: int = 8,
    min_anchors: int = 2,
    progress: Callable | None = None,
) -> IdentificationResult:
    """Identify the circles of many views of the board while refining the model.

    Round 0 fixes the board position modulo the sub-pattern period with the views that show
    a large circle; each later round labels every view with :func:`identify_view`, refines
    the model and board poses on the accepted views (robust loss), and repeats until the
    accepted labels stop changing. Finally every view is verified against the refined model:
    its circles must reproject within ``verify_px`` (``verify_sigma`` robust sigmas, at least
    ``verify_floor_px``, at most ``verify_max_pitch`` pitches) or the view is rejected.

    Parameters
    ----------
    detections : sequence of CircleDetections
    voltages : array_like, shape (n, 2), volts
        (U1_pan, U1_tilt) per view.
    model : RigModel
        Approximate model (nominal rig data).
    board : CircleBoard
    board_poses : ndarray shape (4, 4), or dict of int to ndarray shape (4, 4)
        Approximate ``V0_T_W`` per board pose (metres); its position on the board needs to
        be right to within 3 pitches for absolute labels (large circles fix the rest).
    pose_index : array_like of int, shape (n,), optional
        Board pose of each view (default all 0).
    refine_mirrors, refine_theta0, refine_poly
        As :func:`refine`.
    max_offset_pitch : float
        Largest prediction error accepted when labelling a view without a large circle.
    verify_sigma, verify_floor_px, verify_max_pitch : float
        Final reprojection tolerance (see above).
    max_rounds : int
    min_anchors : int
        Views showing a large circle that must agree on a board pose's lattice position.
        Without them, labels could be consistently off by whole pitches (harmless for the
        fit, but not the board's true circles), so every view of that pose is rejected.
        0 accepts labels that rest on the prior alone (the log says so).
    progress : callable, optional
        ``progress(done, total, message)`` after each round.

    Returns
    -------
    IdentificationResult
    """
    views, poses = _check_views(detections, voltages, board_poses, pose_index, board,
                                min_anchors)
    cfg = _Settings(refine_mirrors, refine_theta0, refine_poly, max_offset_pitch,
                    verify_sigma, verify_floor_px, verify_max_pitch, max_rounds, min_anchors)
    log: list[str] = []
    # Round 0: board orientation and plane from per-view PnP, then the lattice position
    # of each board pose from the large-circle views.
    _orient_poses(views, model, board, poses, log)
    _anchor_poses(views, model, board, poses, min_anchors, log)
    m, rounds, ref = _label_and_refine(views, model, board, poses, cfg, progress, log)
    ids, m, ref, verify_px = _verify(views, m, board, poses, ref, cfg)
    log.append(f"verification: tolerance {verify_px:.2f} px, "
               f"{sum(v.accepted for v in ids)}/{views.n} views accepted")
    return IdentificationResult(ids, m, poses, ref, verify_px, rounds, log)


@dataclass(frozen=True)
class _Settings:
    """Keyword settings of :func:`identify_views` used by its steps."""

    refine_mirrors: bool
    refine_theta0: bool
    refine_poly: int
    max_offset_pitch: float
    verify_sigma: float
    verify_floor_px: float
    verify_max_pitch: float
    max_rounds: int
    min_anchors: int


@dataclass
class _ViewSet:
    """The views being identified; ``unverified`` maps a refused board pose to the reason."""

    detections: Sequence[CircleDetections]
    U: np.ndarray
    pidx: np.ndarray
    board: CircleBoard
    unverified: dict[int, str] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.detections)

    def label_all(self, m, ps, **kw) -> list:
        """:func:`identify_view` of every view with model ``m`` and board poses ``ps``."""
        out = []
        for i, det in enumerate(self.detections):
            p = int(self.pidx[i])
            if p in self.unverified:
                out.append(ViewIdentification(False, np.full(len(det), -1, np.int64),
                                              self.unverified[p]))
            elif len(det):
                out.append(identify_view(det, self.U[i, 0], self.U[i, 1], m, ps[p], self.board,
                                         **kw))
            else:
                out.append(identify_view(det, 0.0, 0.0, m, ps[p], self.board))
        return out

    def accepted(self, ids) -> list[int]:
        return [i for i in range(self.n) if ids[i].accepted]

    def observations(self, ids, accepted) -> list[ViewObservation]:
        return _observations(ids, self.detections, self.U, self.pidx, accepted)


def _check_views(detections, voltages, board_poses, pose_index, board, min_anchors):
    """Validated inputs of :func:`identify_views`: (_ViewSet, board poses dict)."""
    n = len(detections)
    U = np.asarray(voltages, dtype=np.float64)
    if U.shape != (n, 2) or not np.isfinite(U).all():
        raise ValueError(f"voltages must have shape ({n}, 2) and be finite, got {U.shape}")
    pidx = np.zeros(n, dtype=np.int64) if pose_index is None else np.asarray(pose_index)
    if pidx.shape != (n,):
        raise ValueError(f"pose_index must have shape ({n},), got {pidx.shape}")
    poses = _as_pose_dict(board_poses)
    for p in set(pidx.tolist()):
        if p not in poses:
            raise ValueError(f"pose_index {p} has no entry in board_poses")
    if min_anchors < 0:
        raise ValueError(f"min_anchors must be >= 0, got {min_anchors}")
    return _ViewSet(detections, U, pidx, board), poses


def _orient_poses(views: _ViewSet, model, board, poses, log) -> None:
    """Round 0, first half: each board pose's orientation and plane from per-view PnP."""
    for p in sorted(poses):
        sel = np.flatnonzero(views.pidx == p)
        poses[p], used = board_pose_from_views(
            [views.detections[i] for i in sel], views.U[sel], model, board, poses[p]
        )
        log.append(f"pose {p}: orientation from {used} PnP views")


def _anchor_poses(views: _ViewSet, model, board, poses, min_anchors, log) -> None:
    """Round 0, second half: shift each board pose onto the lattice its large circles show.

    A pose with fewer than ``min_anchors`` agreeing large-circle views is marked unverified
    (``min_anchors`` 0: it keeps its prior position).
    """
    period = board.sub_pattern
    ids = views.label_all(model, poses, max_offset_pitch=0.49, max_spread_pitch=0.25)
    for p in sorted(poses):
        offs = [ids[i].offset_pitch for i in range(views.n)
                if views.pidx[i] == p and ids[i].accepted and ids[i].mode == "large"]
        shift, support = _lattice_shift(offs, period) if offs else (np.zeros(2), 0)
        if support < max(min_anchors, 1):
            what = (f"{support} agreeing view(s) with a large circle" if offs
                    else "no view with a large circle")
            if min_anchors > 0:
                views.unverified[p] = (f"board pose {p}: {what}, need {min_anchors}; circle "
                                       "identities cannot be verified")
                log.append(views.unverified[p])
            else:
                log.append(f"pose {p}: {what}; relying on the pose prior")
            continue
        delta = np.array([shift[1], shift[0], 0.0]) * board.pitch  # (row, col) -> (x, y)
        poses[p] = poses[p] @ _transform(np.eye(3), -delta)
        log.append(f"pose {p}: {support} of {len(offs)} large-circle views agree; board "
                   f"prior shifted by ({shift[0]:+.2f}, {shift[1]:+.2f}) pitch (row, col)")


def _refine_accepted(model, obs, board, poses, **kw) -> RefineResult:
    """Robust :func:`refine` on the accepted views; updates ``poses`` with the result."""
    ref = refine(
        model, obs, board, {p: poses[p] for p in sorted({o.pose_index for o in obs})},
        loss="soft_l1", **kw,
    )
    poses.update(ref.board_poses)
    return ref


def _label_and_refine(views: _ViewSet, model, board, poses, cfg: _Settings, progress, log):
    """Rounds of labelling and refining until the accepted labels stop changing.

    Returns (model, rounds, last RefineResult or None); ``poses`` is updated in place.
    """
    n = views.n
    m = model
    prev = None
    rounds = 0
    ref = None
    for rounds in range(1, cfg.max_rounds + 1):
        ids = views.label_all(m, poses, max_offset_pitch=cfg.max_offset_pitch)
        accepted = views.accepted(ids)
        key = tuple((i, tuple(ids[i].index)) for i in accepted)
        if progress is not None:
            progress(rounds, cfg.max_rounds, f"identification round {rounds}: "
                     f"{len(accepted)}/{n} views labelled")
        if key == prev:
            break
        prev = key
        obs = views.observations(ids, accepted)
        n_pts = sum(len(o.index) for o in obs)
        if n_pts < 12:
            log.append(f"round {rounds}: only {n_pts} labelled circles, cannot refine")
            break
        spread = np.ptp(views.U[accepted], axis=0) if accepted else np.zeros(2)
        enough = len(accepted) >= 6 and spread.min() > 1.0
        ref = _refine_accepted(
            m, obs, board, poses,
            refine_l_d=enough and rounds >= 2,
            refine_mirrors=cfg.refine_mirrors and enough,
            refine_theta0=cfg.refine_theta0 and enough and rounds >= 2,
            refine_poly=cfg.refine_poly if (enough and rounds >= 3) else 0,
            f_scale_px=2.0,
        )
        m = ref.model
        log.append(f"round {rounds}: {len(accepted)} views labelled, robust fit rms "
                   f"{ref.rms_px:.3f} px")
    return m, rounds, ref


def _verify(views: _ViewSet, model, board, poses, ref, cfg: _Settings):
    """Final verification against the refined model, with a tolerance from the residuals.

    Returns (identifications, model, last RefineResult, tolerance in pixels).
    """
    m = model
    pitch_px = _pitch_px(m, board, poses)
    ids = views.label_all(m, poses, max_offset_pitch=cfg.max_offset_pitch)
    verify_px = cfg.verify_floor_px
    for _ in range(3):
        accepted = views.accepted(ids)
        if not accepted:
            break
        obs = views.observations(ids, accepted)
        enough = len(accepted) >= 6
        ref = _refine_accepted(
            m, obs, board, poses,
            refine_l_d=enough, refine_mirrors=cfg.refine_mirrors and enough,
            refine_theta0=cfg.refine_theta0 and enough,
            refine_poly=cfg.refine_poly if enough else 0,
            f_scale_px=max(verify_px / 4.0, 0.5),
        )
        m = ref.model
        res = np.concatenate(ref.residuals_px)
        sigma = 1.4826 * float(np.median(np.abs(res - np.median(res, axis=0))))
        verify_px = float(np.clip(cfg.verify_sigma * sigma, cfg.verify_floor_px,
                                  cfg.verify_max_pitch * pitch_px))
        ids = views.label_all(m, poses, max_offset_pitch=cfg.max_offset_pitch,
                              max_residual_px=verify_px)
        if views.accepted(ids) == accepted:
            break
    return ids, m, ref, verify_px


def _observations(ids, detections, U, pidx, accepted):
    return [
        ViewObservation(U[i], ids[i].index, detections[i].centres, int(pidx[i]), i)
        for i in accepted
    ]


def _pitch_px(model: RigModel, board: CircleBoard, poses) -> float:
    """Board pitch in pixels at the V0 view of the nearest board pose."""
    z = min(float(T[2, 3]) for T in poses.values())
    return model.intrinsics.fx * board.pitch / max(z, 1e-3)
