"""The laser's bundle adjustment (calibration_tools.laser_bundle): stripe points of a known
physical laser are fitted back within their stated uncertainty; a capture that cannot
determine the laser is refused with a reason, not answered with numbers."""

import dataclasses

import numpy as np
import pytest

from calibration_tools.laser_bundle import fit_laser_bundle
from reconstructor.model import MirrorParams, laser_plane_v0

sim = pytest.importorskip("galvoscan.simulated_rig")
rigs = pytest.importorskip("galvoscan_sim")

ROWS = np.linspace(-7.0, 5.0, 9)


def _truth():
    return sim.truth_model(rigs.load_rig("reference"), kind="physical")


def _stripes(model, rows, rng, noise=8e-6, view_shift=4e-6, jitter_v=0.0):
    """Per row and offset, four board-sized segments of the model's laser plane (two depths,
    two sides), points moved along the plane's normal by per-point and per-view noise; with
    ``jitter_v`` each view's sheet is the one of a voltage off by that much (1 sigma), as a
    galvo that scatters from frame to frame draws it."""
    out = []
    for u in rows:
        for du in (-0.05, 0.05):
            pl = laser_plane_v0(model, u + du)
            n, e = pl[:3], pl[3]
            along = np.cross(n, [0.0, 0.0, 1.0])
            along /= np.linalg.norm(along)
            for z in (0.6, 0.7):
                for x in (-0.02, 0.02):
                    if jitter_v:
                        pl = laser_plane_v0(model, u + du + rng.normal(0.0, jitter_v))
                        n, e = pl[:3], pl[3]
                    p0 = np.array([x, 0.0, z])
                    p0 = p0 - (n @ p0 + e) * n  # onto the plane
                    s = np.linspace(-0.015, 0.015, 60)
                    pts = p0 + s[:, None] * along
                    shift = rng.normal(0.0, view_shift) + rng.normal(0.0, noise, len(s))
                    # each board its own G1 voltages, shared by its two lit frames
                    out.append((pts + shift[:, None] * n, float(u + du), 10.0 * x + z,
                                float(u) / 10.0))
    return out


def _start(truth):
    """The staged laser: the plane, the axis and the response each a little off."""
    pl = np.asarray(truth.laser_plane_v0) + [2e-4, -1e-4, 2e-4, 5e-5]
    pl[:3] /= np.linalg.norm(pl[:3])
    n = np.asarray(truth.laser_axis_dir) + [0.0, 5e-4, -3e-4]
    n /= np.linalg.norm(n)
    g2 = truth.g2_tilt
    return dataclasses.replace(
        truth, laser_plane_v0=pl, laser_axis_dir=n,
        laser_axis_point=np.asarray(truth.laser_axis_point) + [0.0, 3e-4, -2e-4],
        g2_tilt=MirrorParams(g2.theta0, g2.k * 1.001, (0.0,)))


def test_the_bundle_recovers_a_known_laser_within_its_stated_uncertainty():
    truth = _truth()
    rng = np.random.default_rng(3)
    b = fit_laser_bundle(_start(truth), _stripes(truth, ROWS, rng))
    assert b.poly_degree == 3 and b.views == len(ROWS) * 2 * 4
    sd = dict(zip(b.names, np.sqrt(np.diag(b.covariance)), strict=True))
    got = b.updates
    want = {"laser_plane_v0": truth.laser_plane_v0, "laser_axis_dir": truth.laser_axis_dir,
            "g2_tilt.k": [truth.g2_tilt.k]}
    z = []
    for key, values in want.items():
        fitted = [got["g2_tilt"]["k"]] if key == "g2_tilt.k" else got[key]
        for j, (a, t) in enumerate(zip(fitted, values, strict=True)):
            name = key if key == "g2_tilt.k" else f"{key}[{j}]"
            if sd[name] > 1e-12:
                z.append(abs(a - t) / sd[name])
    assert max(z) < 4.0, z
    # the laser planes themselves, over the rows and beyond them, against the truth
    fitted = dataclasses.replace(
        truth, laser_plane_v0=np.array(got["laser_plane_v0"]),
        laser_axis_dir=np.array(got["laser_axis_dir"]),
        laser_axis_point=np.array(got["laser_axis_point"]),
        g2_tilt=MirrorParams(truth.g2_tilt.theta0, got["g2_tilt"]["k"],
                             tuple(got["g2_tilt"]["poly"])))
    for u in np.linspace(-7.0, 5.0, 13):
        a, t = laser_plane_v0(fitted, u), laser_plane_v0(truth, u)
        # where the true sheet draws its stripe on a wall at 650 mm: off the fitted plane by
        x = np.array([-0.035, 0.0, 0.035])  # where the boards were
        y = -(t[0] * x + t[2] * 0.65 + t[3]) / t[1]
        stripe = np.column_stack([x, y, np.full(3, 0.65)])
        gap = np.abs(stripe @ a[:3] + a[3])
        assert gap.max() < 15e-6, (u, gap.max())  # a few views' noise (4 um each)
    # the start was 10 times further off
    assert b.rms_start_m > 3 * b.rms_m


def test_views_at_one_voltage_are_refused_as_unobservable():
    truth = _truth()
    rng = np.random.default_rng(4)
    stripes = _stripes(truth, [2.0] * 9, rng)
    stripes = [(p, 2.0, a, c) for p, _, a, c in stripes]  # every view at one G2 voltage
    with pytest.raises(ValueError, match="do not determine"):
        fit_laser_bundle(_start(truth), stripes)


def test_bad_input_is_refused():
    truth = _truth()
    rng = np.random.default_rng(5)
    with pytest.raises(ValueError, match="at least 12"):
        fit_laser_bundle(_start(truth), _stripes(truth, [0.0], rng)[:8])
    paper = dataclasses.replace(truth, physical=None)
    with pytest.raises(ValueError, match="physical"):
        fit_laser_bundle(paper, _stripes(truth, ROWS, rng))
    with pytest.raises(ValueError, match="poly_degree"):
        fit_laser_bundle(_start(truth), _stripes(truth, ROWS, rng), poly_degree=0)


def test_the_bundle_measures_g2s_frame_noise():
    """Sheets drawn at voltages scattered by 2.3e-4 V (8 urad on a 2 deg/V galvo) from frame
    to frame: the bundle's per-view offsets give that scatter back; without it, next to
    nothing (the per-point noise is taken out)."""
    truth = _truth()
    rows = np.linspace(-7.0, 5.0, 13)
    sigma = 2.3e-4
    noisy = fit_laser_bundle(_start(truth), _stripes(truth, rows, np.random.default_rng(6),
                                                     view_shift=0.0, jitter_v=sigma))
    assert noisy.frame_noise_u2_V == pytest.approx(sigma, rel=0.25), noisy.frame_noise_u2_V
    quiet = fit_laser_bundle(_start(truth), _stripes(truth, rows, np.random.default_rng(6),
                                                     view_shift=0.0))
    assert quiet.frame_noise_u2_V < 0.25 * sigma, quiet.frame_noise_u2_V


def test_more_frames_of_the_same_boards_do_not_make_the_laser_better_known():
    """Each board's pose error is shared by all its lit frames: three times the frames of the
    same boards leave the stated uncertainty about where it was (the views of one board are
    one sample), where counting frames as independent would shrink it by sqrt(3)."""
    truth = _truth()

    def stripes(copies, seed):
        rng = np.random.default_rng(seed)
        out = []
        for p, u2, a, b in _stripes(truth, ROWS, rng, noise=2e-6, view_shift=0.0):
            pl = laser_plane_v0(truth, u2)
            board = np.random.default_rng(int(abs(a * 1e3 + b * 1e5))).normal(0.0, 8e-6)
            for _ in range(copies):
                move = board + rng.normal(0.0, 1e-6, len(p))
                out.append((p + move[:, None] * pl[:3], u2, a, b))
        return out

    def sd(b):
        return float(np.sqrt(b.covariance[b.names.index("laser_plane_v0[3]"),
                                          b.names.index("laser_plane_v0[3]")]))

    one = fit_laser_bundle(_start(truth), stripes(1, 8))
    three = fit_laser_bundle(_start(truth), stripes(3, 8))
    assert 0.8 < sd(three) / sd(one) < 1.25, (sd(one), sd(three))
