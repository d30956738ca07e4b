"""Physical geometry of the simulated rig: mirrors, virtual camera, laser sheet, DAC.

The ideal rig is checked against docs/design.md section 2's matrices written out here; the
reference rig is checked for self-consistency (ray tracing vs point reflection) and for
the imperfections actually changing the geometry.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from galvoscan_sim import Simulator, load_rig, load_scene
from galvoscan_sim.rig import trace_off_planes
from galvoscan_sim.spatial import reflection_transform, rotation_about

IDEAL = load_rig('ideal')
REFERENCE = load_rig('reference')
_SIM = []


def _plane_sim():
    if not _SIM:
        _SIM.append(Simulator(REFERENCE, load_scene('plane'), seed=0))
    return _SIM[0]
angles = st.floats(math.radians(25.0), math.radians(65.0))
volts = st.floats(-10.0, 10.0)


def design_G_T_V(t1, t2, l, d):
    """docs/design.md: G_T_V = Tilt(theta2) @ Pan(theta1) @ M0."""
    c1, s1, c2, s2 = math.cos(2 * t1), math.sin(2 * t1), math.cos(2 * t2), math.sin(2 * t2)
    tilt = np.array([[1, 0, 0, 0], [0, c2, s2, d * (1 - c2)], [0, s2, -c2, -d * s2],
                     [0, 0, 0, 1]])
    pan = np.array([[-c1, s1, 0, 0], [s1, c1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    m0 = np.array([[0, 0, 1, -l], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
    return tilt @ pan @ m0


@settings(max_examples=40, deadline=None)
@given(angles, angles)
def test_ideal_mirror_reflections_are_designs_pan_and_tilt(t1, t2):
    n1, c1 = IDEAL.g1.pan.plane(t1)
    n2, c2 = IDEAL.g1.tilt.plane(t2)
    P = reflection_transform(n1, c1)
    T = reflection_transform(n2, c2)
    c, s = math.cos(2 * t1), math.sin(2 * t1)
    assert np.allclose(P[:3, :3], [[-c, s, 0], [s, c, 0], [0, 0, 1]], atol=1e-15)
    assert np.allclose(P[:3, 3], 0.0, atol=1e-15)
    d = IDEAL.d
    c, s = math.cos(2 * t2), math.sin(2 * t2)
    assert np.allclose(T[:3, :3], [[1, 0, 0], [0, c, s], [0, s, -c]], atol=1e-15)
    assert np.allclose(T[:3, 3], [0, d * (1 - c), -d * s], atol=1e-15)


@settings(max_examples=40, deadline=None)
@given(angles, angles)
def test_ideal_virtual_camera_is_designs_product(t1, t2):
    G_T_V = IDEAL.G_T_V(t1, t2)
    assert np.allclose(G_T_V, design_G_T_V(t1, t2, IDEAL.l, IDEAL.d), atol=1e-14)
    assert np.linalg.det(G_T_V[:3, :3]) == pytest.approx(1.0)


def test_design_entry_row2_col3_is_sin2t1_cos2t2_not_the_papers():
    t1, t2 = math.radians(40.0), math.radians(52.0)
    T = IDEAL.G_T_V(t1, t2)
    assert T[1, 2] == pytest.approx(math.sin(2 * t1) * math.cos(2 * t2), abs=1e-15)
    assert abs(T[1, 2] - math.sin(2 * t1) * math.sin(2 * t2)) > 0.1


def test_v0_is_at_zero_volts_and_looks_along_g_z():
    th = IDEAL.mirror_angles(np.zeros(4))
    assert th[:2] == pytest.approx([math.pi / 4, math.pi / 4])
    G_T_V0 = IDEAL.G_T_V0
    assert np.allclose(G_T_V0[:3, :3], np.eye(3), atol=1e-15)
    assert np.allclose(G_T_V0[:3, 3], [0.0, IDEAL.d, -(IDEAL.l + IDEAL.d)], atol=1e-15)
    # the rig files put W at the nominal V0
    assert np.allclose(IDEAL.W_T_V0, np.eye(4), atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(volts, volts, st.floats(-0.05, 0.05), st.floats(-0.05, 0.05),
       st.floats(0.3, 2.0))
def test_traced_pixel_rays_agree_with_point_reflection(u1, u2, x, y, s):
    """Reference rig (all imperfections on): a point on a ray traced off the mirrors
    projects back, through the reflected (virtual) camera, onto the pixel's ray."""
    rig = REFERENCE
    th = rig.mirror_angles(rig.applied_voltages(np.array([u1, u2, 0.0, 0.0])))
    o, d = rig.trace_camera_rays(np.array([[x, y]]), th[0], th[1])
    p_G = o[0] + s * d[0]
    V_T_G = np.linalg.inv(rig.G_T_V(th[0], th[1]))
    p_V = V_T_G[:3, :3] @ p_G + V_T_G[:3, 3]
    assert p_V[0] / p_V[2] == pytest.approx(x, abs=1e-12)
    assert p_V[1] / p_V[2] == pytest.approx(y, abs=1e-12)


def test_imperfections_move_the_virtual_camera():
    th = REFERENCE.mirror_angles(np.zeros(4))
    ideal_pose = design_G_T_V(th[0], th[1], REFERENCE.l, REFERENCE.d)
    diff = np.abs(REFERENCE.G_T_V(th[0], th[1]) - ideal_pose)
    assert diff[:3, 3].max() > 1e-5          # > 10 um: offsets and tilts matter
    assert diff[:3, :3].max() > 1e-4          # > 0.1 mrad
    assert diff[:3, 3].max() < 2e-3 and diff[:3, :3].max() < 1e-2   # but stay plausible


def test_surface_offset_shifts_the_mirror_plane():
    n, c = REFERENCE.g1.pan.plane(math.pi / 4)
    n0, c0 = IDEAL.g1.pan.plane(math.pi / 4)
    # the reference pan surface sits 0.15 mm in front of its axis (towards the light)
    assert c0 == pytest.approx(0.0, abs=1e-15)
    axis_point = REFERENCE.g1.pan.axis_point
    assert float(n @ axis_point) - c == pytest.approx(0.00015, abs=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.floats(-10.0, 10.0))
def test_ideal_laser_plane_turns_2k2U_about_the_tilt_axis(u):
    rig = IDEAL
    p = rig.true_model_parameters()
    th = rig.mirror_angles(np.array([0.0, 0.0, 0.0, u]))
    sheet = rig.laser_sheet_G(th[2], th[3]).transformed(np.linalg.inv(rig.G_T_V0))
    n_expected = rotation_about(p.n, 2.0 * p.k2 * u) @ p.pi0[:3]
    assert np.allclose(sheet.plane[:3], n_expected, atol=1e-12)
    assert sheet.plane[3] == pytest.approx(-n_expected @ p.P, abs=1e-12)


def test_ideal_g2_pan_only_slides_the_stripe_along_itself():
    planes = []
    for u in (-5.0, 0.0, 5.0):
        th = IDEAL.mirror_angles(np.array([0.0, 0.0, u, 1.0]))
        planes.append(IDEAL.laser_sheet_G(th[2], th[3]).plane)
    assert np.allclose(planes[0], planes[1], atol=1e-13)
    assert np.allclose(planes[2], planes[1], atol=1e-13)


def test_reference_fan_does_not_contain_the_tilt_axis():
    """Mounting error: the planes at different U2_tilt no longer share one line."""
    rig = REFERENCE
    V0_T_G = np.linalg.inv(rig.G_T_V0)
    planes = []
    for u in np.linspace(-3, 3, 7):
        th = rig.mirror_angles(np.array([0.0, 0.0, 0.0, u]))
        planes.append(rig.laser_sheet_G(th[2], th[3]).transformed(V0_T_G).plane)
    planes = np.array(planes)
    p = rig.true_model_parameters()
    # distance of the true axis point P from each plane: zero for the ideal rig
    dist = np.abs(planes[:, :3] @ p.P + planes[:, 3])
    assert dist.max() > 1e-5
    # and G2 pan now tilts the sheet too
    th0 = rig.mirror_angles(np.zeros(4))
    th1 = rig.mirror_angles(np.array([0.0, 0.0, 5.0, 0.0]))
    n0 = rig.laser_sheet_G(th0[2], th0[3]).plane[:3]
    n1 = rig.laser_sheet_G(th1[2], th1[3]).plane[:3]
    assert np.linalg.norm(n1 - n0) > 1e-5


def test_layout_triangulation_angle_and_coverage():
    rig = IDEAL
    p = rig.true_model_parameters()
    # the sheet at U2 = 0 crosses V0's optical axis near 650 mm
    z = -p.pi0[3] / p.pi0[2]
    assert z == pytest.approx(0.65, abs=0.01)
    # triangulation angle between the optical axis and the sheet at that point
    P = np.array([0.0, 0.0, z])
    th = rig.mirror_angles(np.zeros(4))
    sheet = rig.laser_sheet_G(th[2], th[3]).transformed(np.linalg.inv(rig.G_T_V0))
    beam = P - sheet.source
    tri = math.degrees(math.acos(beam @ [0, 0, 1] / np.linalg.norm(beam)))
    assert 20.0 <= tri <= 30.0
    # the fan's wedge covers +-650 mm at 650 mm (the 1300 mm range)
    for x in (-0.65, 0.65):
        q = np.array([x, 0.0, z])
        q = q - (sheet.plane[:3] @ q + sheet.plane[3]) * sheet.plane[:3]
        assert np.all(sheet.edge_normals @ (q - sheet.source) > 0)
    # G1 (+-40 deg optical, pivoting at the mirrors ~0.1 m in front of V0) steers the
    # optical axis over ~950 x 910 mm at 650 mm
    reach = []
    for u in ((-10, 0), (10, 0), (0, -10), (0, 10)):
        t = rig.mirror_angles(np.array([u[0], u[1], 0.0, 0.0]))
        G_T_V = rig.G_T_V(t[0], t[1])
        V0_T_V = np.linalg.inv(rig.G_T_V0) @ G_T_V
        c, a = V0_T_V[:3, 3], V0_T_V[:3, 2]
        reach.append(c + (0.65 - c[2]) / a[2] * a)
    reach = np.array(reach)
    assert reach[1, 0] - reach[0, 0] > 0.9 and abs(reach[3, 1] - reach[2, 1]) > 0.9


def test_laser_rays_are_traced_off_the_g2_mirrors():
    """The sheet's apex, hit points and reflected rays come from real ray tracing."""
    rig = REFERENCE
    th = rig.mirror_angles(np.array([0.0, 0.0, 1.0, -2.0]))
    planes = [rig.g2.pan.plane(th[2]), rig.g2.tilt.plane(th[3])]
    L = rig.laser
    dirs = np.array([L.direction, np.cos(0.3) * L.direction + np.sin(0.3) * L.spread_direction])
    hits, out, ok = trace_off_planes(np.tile(L.position, (2, 1)), dirs, planes)
    assert ok.all()
    sheet = rig.laser_sheet_G(th[2], th[3])
    R, t = rig.G_T_G2[:3, :3], rig.G_T_G2[:3, 3]
    for h, d in zip(hits, out, strict=True):
        for s in (0.0, 0.3, 1.0):
            q = R @ (h + s * d) + t
            assert abs(sheet.plane[:3] @ q + sheet.plane[3]) < 1e-12
        # the ray leaves from the tilt mirror, in line with the virtual apex
        q = R @ h + t
        assert np.linalg.norm(np.cross(q - sheet.source, R @ d)) < 1e-12


def test_dac_quantisation():
    dac = IDEAL.dac
    assert dac.lsb == pytest.approx(20.0 / 65536)
    assert dac.quantize(0.0) == 0.0
    q = dac.quantize(np.array([1.0, -3.3, 9.99]))
    assert np.all(np.abs(q - [1.0, -3.3, 9.99]) <= dac.lsb / 2)
    assert np.allclose(q / dac.lsb, np.round(q / dac.lsb))
    with pytest.raises(ValueError, match='range'):
        dac.quantize(10.5)


def test_true_parameters_of_the_ideal_rig_are_the_nominal_ones():
    p = IDEAL.true_model_parameters()
    assert p.exact
    assert (p.l, p.d) == (IDEAL.l, IDEAL.d)
    assert p.theta0_pan == pytest.approx(math.pi / 4) and p.theta0_tilt == pytest.approx(
        math.pi / 4)
    assert p.k_pan == pytest.approx(math.radians(2.0))
    assert np.allclose(p.n, [1.0, 0.0, 0.0], atol=1e-12)
    # the G2 tilt axis, 100 mm behind V0's origin on the line from the 650 mm crossing
    # at 24.8 deg (rigs/ideal.yaml)
    assert np.allclose(p.P, [0.0, 0.30 * 0.75 / 0.65, -0.10], atol=1e-12)
    q = REFERENCE.true_model_parameters()
    assert not q.exact
    # best linear gain absorbs the gain error and the cubic term's linear part
    assert q.k_pan != pytest.approx(p.k_pan, rel=1e-4)
    assert abs(q.n @ [1.0, 0.0, 0.0]) > 0.999


def test_jitter_moves_angles_only_with_draws():
    z = np.array([1.0, -1.0, 2.0, 0.5])
    a0 = REFERENCE.mirror_angles(np.zeros(4))
    a1 = REFERENCE.mirror_angles(np.zeros(4), z)
    assert np.allclose(a1 - a0, 8e-6 * z)
    assert np.array_equal(IDEAL.mirror_angles(np.zeros(4), z), IDEAL.mirror_angles(np.zeros(4)))


@settings(max_examples=30, deadline=None)
@given(st.floats(-10.0, 10.0), st.floats(-10.0, 10.0))
def test_compiled_laser_sheet_matches_the_reference(u_pan, u_tilt):
    sim = _plane_sim()
    th = REFERENCE.mirror_angles(np.array([0.0, 0.0, u_pan, u_tilt]))
    ref = REFERENCE.laser_sheet_G(th[2], th[3]).transformed(REFERENCE.W_T_G)
    sheet = sim.geometry(th).sheet
    assert np.allclose(sheet.plane, ref.plane, atol=1e-13)
    assert np.allclose(sheet.source, ref.source, atol=1e-13)
    assert np.allclose(sheet.central, ref.central, atol=1e-13)
    assert np.allclose(sheet.edge_normals, ref.edge_normals, atol=1e-13)
    assert np.allclose(sheet.mirror_plane, ref.mirror_plane, atol=1e-13)
