"""Joint correction (Algorithm 1) on synthetic clouds with known error transforms: recovery,
interpolation, the paper's errors, skipped and unconverged nodes, chaining of positions."""

import logging
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration_tools.joint_correction import NodeCloud, compute_joint_correction
from calibration_tools.registration import apply_transform

PLANE = np.array([0.0, 0.908, 0.419, -0.2724]) / np.linalg.norm([0.0, 0.908, 0.419])
R_SPHERE = 0.01
WALL_Z = 0.67
MIRROR = np.array([0.0, 0.0, -0.1])  # the model error turns views about a point near G1


def _curve(x_centre=0.0, step=8e-5):
    """The true stripe: circle arc on the sphere plus the wall on both sides, ordered by x."""
    c = np.array([x_centre, 0.0, 0.66])
    n = PLANE[:3]
    d = n @ c + PLANE[3]
    cc, rc = c - d * n, math.sqrt(R_SPHERE ** 2 - d ** 2)
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.cross(n, e1)
    t = np.linspace(0, 2 * math.pi, int(2 * math.pi * rc / step), endpoint=False)
    arc = cc + rc * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2))
    arc = arc[np.sum((arc - c) * (0 - arc), axis=1) > 0.3 * R_SPHERE * 0.66]
    y_wall = -(PLANE[2] * WALL_Z + PLANE[3]) / PLANE[1]
    x = np.arange(-0.04, 0.04, step) + x_centre
    x = x[np.abs(x - x_centre) > rc + 5e-4]
    wall = np.column_stack([x, np.full_like(x, y_wall), np.full_like(x, WALL_Z)])
    pts = np.vstack([arc, wall])
    return pts[np.argsort(pts[:, 0])]


def _error(u_pan, u_tilt):
    """Model error at G1 voltages: a rotation about the mirror point plus a shift (V0c_T_V0)."""
    rv = np.array([1.5e-3 * u_tilt + 8e-4 * u_pan ** 2, 2e-3 * u_pan, 4e-4 * u_tilt])
    R = Rotation.from_rotvec(rv).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = MIRROR - R @ MIRROR + np.array([5e-5 * u_pan, -3e-5 * u_tilt, 0.0])
    return T


def _node(curve, u_pan, u_tilt, pose=0, rng=None, noise=2e-6, keep=None):
    x_view = 0.045 * u_pan
    pts = curve[np.abs(curve[:, 0] - x_view) < 0.028]
    if keep is not None:
        pts = pts[keep(pts)]
    pts = apply_transform(np.linalg.inv(_error(u_pan, u_tilt)), pts)
    if rng is not None:
        pts = pts + rng.normal(0, noise, pts.shape)
    return NodeCloud(pose, u_pan, u_tilt, pts, np.zeros(len(pts), dtype=np.int64))


PANS = (-0.3, 0.0, 0.3)
TILTS = (-0.2, 0.0, 0.2)


def _grid_nodes(rng, curve=None, special=None):
    curve = _curve() if curve is None else curve
    special = special or {}
    nodes = []
    for p in PANS:
        for t in TILTS:
            nodes.append(special.get((p, t), lambda c, p, t: _node(c, p, t, rng=rng))(
                curve, p, t))
    return nodes


def test_corrections_recover_the_model_errors_and_interpolate():
    rng = np.random.default_rng(0)
    curve = _curve()
    nodes = _grid_nodes(rng, curve)
    res = compute_joint_correction(nodes, sphere_radius=R_SPHERE)
    assert all(r.status in ('registered', 'reference') for r in res.nodes)
    assert res.table.valid.all()
    for node, r in zip(nodes, res.nodes, strict=True):
        # Corrected cloud = true curve, to the noise.
        corrected = apply_transform(r.transform, node.points)
        truth = apply_transform(_error(node.u1_pan, node.u1_tilt), node.points)
        assert np.sqrt(np.mean(np.sum((corrected - truth) ** 2, axis=1))) < 3e-6
    # Between nodes the table interpolates the error; what is left is the error's curvature:
    # linear interpolation over h = 0.3 V of a rotation with d2/dU2 = 1.6e-3 rad/V^2 is off
    # by up to h^2 / 8 * 1.6e-3 rad, about 0.8 m from the mirror point at the stripe.
    bound = 0.8 * 0.3 ** 2 / 8 * 1.6e-3 + 3e-6
    for up, ut in ((0.15, 0.1), (-0.2, -0.05), (0.05, 0.17)):
        node = _node(curve, up, ut)
        got = apply_transform(res.table.V0c_T_V0(up, ut), node.points)
        want = apply_transform(_error(up, ut), node.points)
        assert np.abs(got - want).max() < bound
    # The paper's errors: large before, noise-sized after; Error3 uses the matched pairs.
    assert res.errors['error1_rms_m'] > 1e-4 and res.errors['error3_rms_m'] > 1e-4
    assert res.errors['error2_dense_rms_m'] < 5 * 2e-6  # two clouds' 3-D noise of 2 um
    assert res.errors['error2_rms_m'] < res.errors['error1_rms_m'] / 5


def test_sphere_registration_gives_the_translation_only():
    rng = np.random.default_rng(1)
    nodes = _grid_nodes(rng)
    res = compute_joint_correction(nodes, sphere_radius=R_SPHERE, registration='sphere')
    for node, r in zip(nodes, res.nodes, strict=True):
        np.testing.assert_allclose(r.transform[:3, :3], np.eye(3))
        # It moves the node's sphere centre onto the reference's (true) centre.
        E = _error(node.u1_pan, node.u1_tilt)
        centre_node = apply_transform(np.linalg.inv(E), [[0.0, 0.0, 0.66]])[0]
        assert np.linalg.norm(apply_transform(r.transform, [centre_node])[0]
                              - [0.0, 0.0, 0.66]) < 2e-6


def test_bad_nodes_are_skipped_with_a_reason_and_not_stored(caplog):
    rng = np.random.default_rng(2)
    few = (0.3, 0.2)
    occluded = (-0.3, 0.0)   # part of the arc hidden behind something
    no_sphere = (0.0, -0.2)  # the view sees only the wall
    blocker = (0.3, -0.2)    # something in front: the stripe lies on it for part of the arc

    def occlude(c, p, t):
        return _node(c, p, t, rng=rng, keep=lambda q: ~((q[:, 2] < 0.665) & (q[:, 0] > 0.0)))

    def front(c, p, t):
        node = _node(c, p, t, rng=rng, keep=lambda q: ~((q[:, 2] < 0.665) & (q[:, 0] > 0.002)))
        extra = np.column_stack([np.linspace(0.002, 0.008, 80), np.full(80, 0.02),
                                 np.full(80, 0.60)])
        node.points = np.vstack([node.points, extra])
        node.frame_ids = np.zeros(len(node.points), dtype=np.int64)
        return node

    special = {
        few: lambda c, p, t: _node(c, p, t, rng=rng, keep=lambda q: np.arange(len(q)) < 60),
        occluded: occlude,
        no_sphere: lambda c, p, t: _node(c, p, t, rng=rng, keep=lambda q: q[:, 2] > 0.669),
        blocker: front,
    }
    with caplog.at_level(logging.WARNING, logger='galvoscan.calibration.joint_correction'):
        res = compute_joint_correction(_grid_nodes(rng, special=special),
                                       sphere_radius=R_SPHERE)
    by_v = {(round(r.u1_pan, 3), round(r.u1_tilt, 3)): r for r in res.nodes}
    assert by_v[few].status == 'skipped' and '60 points < 100' in by_v[few].reason
    assert by_v[occluded].status == 'skipped' and 'occluded' in by_v[occluded].reason
    assert by_v[no_sphere].status == 'skipped' and 'sphere' in by_v[no_sphere].reason
    assert by_v[blocker].status == 'skipped'
    assert sum(r.status == 'registered' for r in res.nodes) == 4
    for key in (few, occluded, no_sphere, blocker):
        i, j = PANS.index(key[0]), TILTS.index(key[1])
        assert not res.table.valid[i, j]
        assert by_v[key].transform is None
        assert by_v[key].reason in caplog.text


def test_unconverged_icp_is_reported_and_not_stored():
    rng = np.random.default_rng(3)
    curve = _curve()

    def copy_of_reference(c, p, t):  # no error at all: converges in one step
        node = _node(c, 0.0, 0.0)
        node.u1_pan, node.u1_tilt = p, t
        return node

    nodes = _grid_nodes(rng, curve, special={(0.0, 0.2): copy_of_reference,
                                             (0.0, 0.0): lambda c, p, t: _node(c, p, t)})
    res = compute_joint_correction(nodes, sphere_radius=R_SPHERE, icp_max_iterations=1,
                                   icp_tolerance=1e-12)
    assert [r.status for r in res.nodes].count('registered') == 1
    bad = [r for r in res.nodes if r.status == 'not_converged']
    assert len(bad) == 7 and all('did not converge' in r.reason for r in bad)
    for r in bad:
        i, j = PANS.index(round(r.u1_pan, 3)), TILTS.index(round(r.u1_tilt, 3))
        assert not res.table.valid[i, j] and r.transform is None


def test_positions_chain_through_a_shared_node():
    rng = np.random.default_rng(4)
    first = [_node(_curve(0.0), p, 0.0, 0, rng) for p in (0.0, 0.3)]
    # The sphere moved 13.5 mm along the stripe; the new view grid shares U1_pan = 0.3 V.
    moved = _curve(0.0135)
    second = [_node(moved, p, 0.0, 1, rng) for p in (0.3, 0.6)]
    lonely = [_node(_curve(0.03), 0.9, 0.0, 2, rng)]  # nothing to chain to
    res = compute_joint_correction(first + second + lonely, sphere_radius=R_SPHERE)
    far = next(r for r in res.nodes if r.pose_index == 1 and abs(r.u1_pan - 0.6) < 1e-9)
    assert far.status == 'registered'
    node = second[1]
    got = apply_transform(far.transform, node.points)
    want = apply_transform(_error(0.6, 0.0), node.points)
    assert np.abs(got - want).max() < 1e-5
    last = res.nodes[-1]
    assert last.status == 'skipped' and 'chain' in last.reason
    np.testing.assert_array_equal(res.table.valid[:, 0], [True, True, True, False])


def test_nothing_registered_is_an_error_naming_the_reasons():
    rng = np.random.default_rng(5)
    nodes = [_node(_curve(), p, 0.0, rng=rng, keep=lambda q: np.arange(len(q)) < 30)
             for p in (0.0, 0.3)]
    with pytest.raises(ValueError, match='no node could be registered.*30 points < 100'):
        compute_joint_correction(nodes, sphere_radius=R_SPHERE)
    with pytest.raises(ValueError, match='registration must be one of'):
        compute_joint_correction(nodes, sphere_radius=R_SPHERE, registration='magic')
