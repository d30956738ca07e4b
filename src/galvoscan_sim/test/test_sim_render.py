"""Simulated frames: determinism, ground-truth consistency, occlusion, laser shadowing."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from galvoscan_sim import Simulator, load_rig, load_scene, load_scene_text, patterns
from galvoscan_sim import raykernels as rk

IDEAL = load_rig('ideal')
REFERENCE = load_rig('reference')

WALL = """
format_version: 1
name: wall_test
objects:
  - type: plane
    name: wall
    pose: {translation: [0.0, 0.0, 0.70]}
    albedo: 0.6
"""
OCCLUDER = """
  - type: box
    name: occluder
    pose: {translation: [-0.025, 0.0, 0.60]}
    size: [0.05, 0.02, 0.02]
    albedo: 0.5
"""
BAR = """
  - type: box
    name: bar
    pose: {translation: [0.01, 0.15, 0.35]}
    size: [0.04, 0.02, 0.02]
    albedo: 0.5
"""


def aimed(rig, distance):
    return np.array([0.0, 0.0, 0.0, patterns.aim_laser(rig, 0.0, 0.0, distance)])


def check_truth(sim, frame):
    """The stripe truth lies on the true sheet and the surface and projects onto its pixel."""
    tr = frame.truth
    s = tr.stripe
    assert len(s) > 0
    assert np.all(np.abs(s.u - s.column) < 1e-6)
    # on the actual laser sheet's centre plane
    pi = tr.laser_plane_W
    assert np.max(np.abs(s.points_W @ pi[:3] + pi[3])) < 1e-9
    # consistent V0 coordinates
    W_T_V0 = tr.W_T_V0
    back = s.points_V0 @ W_T_V0[:3, :3].T + W_T_V0[:3, 3]
    assert np.allclose(back, s.points_W, atol=1e-12)
    # projecting through the mirrors lands on (u, v)
    uv = sim.project_points(s.points_W, tr.angles)
    assert np.max(np.abs(uv - np.stack([s.u, s.v], 1))) < 1e-6
    # tracing the pixel (u, v) off the mirrors (numpy reference tracer) hits that point
    hits = sim.trace_pixels(np.stack([s.u, s.v], 1), tr.angles)
    assert np.array_equal(hits.obj, s.object_index)
    assert np.max(np.linalg.norm(hits.points - s.points_W, axis=1)) < 1e-8


@pytest.mark.parametrize('scene', ['stair_block', 'stair_block_turned'])
@pytest.mark.parametrize('rig', [IDEAL, REFERENCE], ids=['ideal', 'reference'])
def test_stair_block_truth_is_consistent(rig, scene):
    sim = Simulator(rig, load_scene(scene), seed=4)
    for volts in ([0.0, 0.0, 0.0, 0.0], [0.8, -0.6, 0.3, -0.5]):
        frame = sim.render(volts)
        check_truth(sim, frame)
    # both stair faces show, 30 mm apart along the stair's axis
    frame = sim.render([0.0, 0.0, 0.0, 0.0])
    s = frame.truth.stripe
    stair = sim.scene.objects[0]
    local = (s.points_W - stair.W_T_O[:3, 3]) @ stair.W_T_O[:3, :3]
    top = np.abs(s.normals_W @ stair.W_T_O[:3, 2]) > 0.999
    assert top.sum() > 500
    levels = np.unique(np.round(local[top, 2], 9))
    assert levels.tolist() == pytest.approx([-0.05, -0.02], abs=1e-9)
    # the rest lies on the riser x = 0 between the two levels (seen edge-on in
    # stair_block, turned to show in stair_block_turned)
    riser = local[~top]
    assert len(riser) > 50 if scene == 'stair_block_turned' else len(riser) < 20
    assert np.allclose(riser[:, 0], 0.0, atol=1e-9)
    assert np.all((riser[:, 2] > -0.05 - 1e-9) & (riser[:, 2] < -0.02 + 1e-9))


def test_sphere_truth_is_consistent():
    sim = Simulator(REFERENCE, load_scene('sphere'), seed=1)
    frame = sim.render([0.0, 0.0, 0.0, 0.0])
    check_truth(sim, frame)
    c = sim.scene.objects[0].W_T_O[:3, 3]
    r = np.linalg.norm(frame.truth.stripe.points_W - c, axis=1)
    assert np.allclose(r, 0.0254, atol=1e-12)


def test_stripe_in_the_image_is_where_the_truth_says():
    """Ideal rig, no noise: the stripe's intensity centroid per column is at the true v."""
    sim = Simulator(IDEAL, load_scene('stair_block'), seed=0)
    frame = sim.render([0.0, 0.0, 0.0, 0.0])
    img = frame.image.astype(float)
    s = frame.truth.stripe
    errs = []
    stair = sim.scene.objects[0]
    top = np.abs(s.normals_W @ stair.W_T_O[:3, 2]) > 0.999
    jump = np.flatnonzero(np.abs(np.diff(s.v)) > 2.0)
    edge = np.concatenate([s.column[~top], s.column[jump], [-100]])
    for c, v in zip(s.column[5:-5:7], s.v[5:-5:7], strict=True):
        if np.min(np.abs(edge - c)) < 10:    # keep away from the step's edges
            continue
        r0 = int(round(v))
        rows = np.arange(r0 - 12, r0 + 13)
        w = img[rows, c] - 2.0    # black level
        w[w < 0] = 0
        errs.append(float((w * rows).sum() / w.sum() - v))
    errs = np.abs(errs)
    assert np.max(img) > 60 and np.max(errs) < 0.15


def test_same_seed_same_frames_different_seed_different_noise():
    scene = load_scene('stair_block')
    volts = patterns.synchronised(REFERENCE, [0.0], 0.0, steps=3, tilt_step=0.05)
    a = [f for f in Simulator(REFERENCE, scene, seed=7).scan(volts)]
    b = [f for f in Simulator(REFERENCE, scene, seed=7).scan(volts)]
    c = [f for f in Simulator(REFERENCE, scene, seed=8).scan(volts)]
    for fa, fb, fc in zip(a, b, c, strict=True):
        assert np.array_equal(fa.image, fb.image)
        assert np.array_equal(fa.truth.angles, fb.truth.angles)
        assert np.array_equal(fa.truth.stripe.v, fb.truth.stripe.v)
        assert not np.array_equal(fa.image, fc.image)
        assert not np.array_equal(fa.truth.angles, fc.truth.angles)   # jitter differs
    # a frame can be regenerated from its index alone
    again = Simulator(REFERENCE, scene, seed=7).render(volts[2], frame_index=2)
    assert np.array_equal(again.image, a[2].image)
    # exact_noise mode is deterministic too
    e1 = Simulator(REFERENCE, scene, seed=7, exact_noise=True).render(volts[0])
    e2 = Simulator(REFERENCE, scene, seed=7, exact_noise=True).render(volts[0])
    assert np.array_equal(e1.image, e2.image)


def test_truth_angles_follow_voltages_and_jitter():
    sim = Simulator(REFERENCE, load_scene('plane'), seed=2)
    frame = sim.render([1.0, -2.0, 0.5, 0.25])
    tr = frame.truth
    assert np.all(np.abs(tr.voltages_applied - tr.voltages_commanded) <= REFERENCE.dac.lsb / 2)
    no_jitter = REFERENCE.mirror_angles(tr.voltages_applied)
    dev = tr.angles - no_jitter
    assert np.all(np.abs(dev) < 6 * 8e-6) and np.any(dev != 0)
    assert np.allclose(tr.V0_T_V, np.linalg.inv(tr.W_T_V0) @ tr.W_T_V, atol=1e-12)


def test_the_rig_without_jitter_keeps_its_geometry_and_loses_only_the_scatter():
    quiet = REFERENCE.without_jitter()
    volts = [1.0, -2.0, 0.5, 0.25]
    frames = [Simulator(quiet, load_scene('plane'), seed=s).render(volts) for s in (2, 3)]
    for f in frames:  # every seed: the response itself, to the last bit
        assert np.array_equal(f.truth.angles, REFERENCE.mirror_angles(f.truth.voltages_applied))
    loud = Simulator(REFERENCE, load_scene('plane'), seed=2).render(volts)
    assert not np.array_equal(loud.truth.angles, frames[0].truth.angles)
    for a, b in ((quiet.true_model_parameters(), REFERENCE.true_model_parameters()),
                 (quiet.physical_model_parameters(), REFERENCE.physical_model_parameters())):
        a, b = (x.__dict__ if hasattr(x, '__dict__') else x for x in (a, b))
        assert a.keys() == b.keys()
        for key in a:
            assert np.array_equal(np.asarray(a[key]), np.asarray(b[key])), key
    assert REFERENCE.g1.pan_drive.jitter > 0  # the original is left as it was


def test_occluded_wall_points_have_no_truth_and_no_stripe():
    rig = IDEAL
    volts = aimed(rig, 0.70)
    free = Simulator(rig, load_scene_text(WALL), seed=0).render(volts)
    sim = Simulator(rig, load_scene_text(WALL + OCCLUDER), seed=0)
    frame = sim.render(volts)
    check_truth(sim, frame)
    s_free, s = free.truth.stripe, frame.truth.stripe
    assert len(s_free) == 720
    # the occluder covers x < 0 (left half of the image); it is not in the sheet
    assert np.all(s.object_index == 0)
    assert np.all(s.points_W[:, 0] >= 0.0)
    assert 300 < len(s) < 420
    img = frame.image.astype(int)
    left = img[:, 20:300].max(axis=0)
    right = img[:, 420:700].max(axis=0)
    assert left.max() < 10 and right.min() > 50


def _segment_hits_box(p, q, center, half):
    """Independent slab test: does the segment p->q cross the axis-aligned box?"""
    d = q - p
    with np.errstate(divide='ignore'):
        t1 = (center - half - p) / d
        t2 = (center + half - p) / d
    lo = np.minimum(t1, t2).max()
    hi = np.maximum(t1, t2).min()
    return lo <= hi and hi > 0 and lo < 1


def test_laser_shadow_leaves_seen_points_dark():
    rig = IDEAL
    volts = aimed(rig, 0.70)
    free = Simulator(rig, load_scene_text(WALL), seed=0).render(volts)
    sim = Simulator(rig, load_scene_text(WALL + BAR), seed=0)
    frame = sim.render(volts)
    s_free, s = free.truth.stripe, frame.truth.stripe
    apex = frame.truth.laser_source_W
    shadowed = np.array([_segment_hits_box(p, apex, np.array([0.01, 0.15, 0.35]),
                                           np.array([0.02, 0.01, 0.01]))
                         for p in s_free.points_W])
    assert 100 < shadowed.sum() < 620       # the bar shadows part of the stripe
    assert np.array_equal(s.column, s_free.column[~shadowed])
    # the bar is outside the camera's view: nothing of it in the image, and the shadowed
    # columns are dark where the free stripe was bright
    img, ref = frame.image.astype(int), free.image.astype(int)
    cols = s_free.column[shadowed][5:-5]
    assert ref[:, cols].max(axis=0).min() > 50
    assert img[:, cols].max() < 10
    lit = s.column[5:-5]
    assert np.array_equal(img[:, lit], ref[:, lit])


def test_laser_off_has_no_stripe():
    sim = Simulator(REFERENCE, load_scene('stair_block'), seed=0)
    on = sim.render([0.0, 0.0, 0.0, 0.0])
    off = sim.render([0.0, 0.0, 0.0, 0.0], laser_on=False)
    assert len(off.truth.stripe) == 0 and not off.truth.laser_on
    assert np.all(np.isnan(off.truth.laser_plane_W))
    assert off.image.max() < 30 < on.image.max()


def test_saturation_on_a_white_plate_in_the_reference_rig_only():
    text = WALL.replace('albedo: 0.6', 'albedo: 1.0')
    ref = Simulator(REFERENCE, load_scene_text(text), seed=0).render(aimed(REFERENCE, 0.7))
    ideal = Simulator(IDEAL, load_scene_text(text), seed=0).render(aimed(IDEAL, 0.7))
    assert (ref.image == 255).sum() > 20
    assert ideal.image.max() < 255


def test_circle_board_view_shows_circles_where_they_project():
    sim = Simulator(IDEAL, load_scene('circle_board'), seed=0)
    volts = np.array([0.5, -0.3, 0.0, 0.0])
    frame = sim.calibration_frame(volts)
    img = frame.image.astype(float)
    board = sim.scene.objects[0]
    fp = board.feature_points()
    uv = sim.project_points(fp['world_points'], frame.truth.angles)
    inside = ((uv[:, 0] > 80) & (uv[:, 0] < 640) & (uv[:, 1] > 80) & (uv[:, 1] < 460))
    assert inside.sum() >= 2 and fp['big'][inside].any()
    for (u, v), diam in zip(uv[inside], fp['diameters'][inside], strict=True):
        r = int(diam / 2 * 7801 / 0.65 * 1.3)
        win = img[int(v) - r:int(v) + r + 1, int(u) - r:int(u) + r + 1]
        dark = np.clip(win.max() - win, 0, None)
        yy, xx = np.mgrid[int(v) - r:int(v) + r + 1, int(u) - r:int(u) + r + 1]
        cu, cv = (dark * xx).sum() / dark.sum(), (dark * yy).sum() / dark.sum()
        assert abs(cu - u) < 0.3 and abs(cv - v) < 0.3
    assert img.max() > 150 and img.min() < 20


def test_checkerboard_corners_project_into_the_view():
    sim = Simulator(IDEAL, load_scene('checkerboard'), seed=0)
    frame = sim.calibration_frame([0.0, 0.0, 0.0, 0.0])
    fp = sim.scene.objects[0].feature_points()
    uv = sim.project_points(fp['world_points'], frame.truth.angles)
    assert len(uv) == 11 * 8
    assert np.all((uv > 0) & (uv < [720, 540]))
    img = frame.image.astype(float)
    # around each inner corner the four quadrants alternate dark / light
    for u, v in uv[::9]:
        u, v = int(round(u)), int(round(v))
        q = [img[v - 8:v - 3, u - 8:u - 3].mean(), img[v - 8:v - 3, u + 3:u + 8].mean(),
             img[v + 3:v + 8, u + 3:u + 8].mean(), img[v + 3:v + 8, u - 8:u - 3].mean()]
        assert abs(q[0] - q[2]) < 30 and abs(q[1] - q[3]) < 30 and abs(q[0] - q[1]) > 80


def test_synchronised_scan_keeps_the_stripe_in_view():
    rig = REFERENCE
    volts = patterns.synchronised(rig, [-1.0, 1.0], -0.5, steps=6, tilt_step=0.05,
                                  reaim_every=1)
    assert volts.shape == (12, 4)
    assert np.allclose(np.diff(volts[:6, 1]), 0.05)
    sim = Simulator(rig, load_scene('plane'), seed=0)
    rows = []
    for frame in sim.scan(volts):
        s = frame.truth.stripe
        rows.append(s.v[np.argmin(np.abs(s.column - 360))])
    # aimed at 650 mm along each view's optical axis: near the centre row, and the same
    # row for every tilt step of a pan position
    assert np.all(np.abs(np.array(rows) - rig.camera.cy) < 20.0)
    assert np.ptp(rows[:6]) < 4.0 and np.ptp(rows[6:]) < 4.0
    # with equal steps only (the paper's), the stripe drifts ~10 px per 0.1 deg step
    equal = patterns.synchronised(rig, [0.0], -0.5, steps=6, tilt_step=0.05)
    drift = [f.truth.stripe.v[360] for f in sim.scan(equal)]
    assert 30.0 < np.ptp(drift) < 90.0
    grid = patterns.g1_grid([-1.0, 0.0, 1.0], [-2.0, 2.0])
    assert grid.shape == (6, 4) and np.all(grid[:, 2:] == 0)
    sweep = patterns.g2_sweep(np.arange(5) * 0.1, u1=(0.5, 0.5))
    assert np.allclose(sweep[:, 3], np.arange(5) * 0.1) and np.all(sweep[:, :2] == 0.5)
    with pytest.raises(ValueError, match='range'):
        patterns.synchronised(rig, [0.0], 9.9, steps=10, tilt_step=0.05)


def test_compiled_tracer_matches_numpy_reference():
    text = WALL + OCCLUDER + """
  - type: sphere
    name: ball
    pose: {translation: [0.02, -0.01, 0.62]}
    radius: 0.01
    albedo: 0.7
  - type: stair_block
    name: stair
    pose: {translation: [0.0, 0.03, 0.68], rotation_vector: [0.2, -0.3, 0.1]}
    size: [0.05, 0.04, 0.01]
    step_height: 0.01
    albedo: 0.6
  - type: plane
    name: card
    pose: {translation: [0.03, 0.02, 0.64], rotation_vector: [0.0, 0.5, 0.0]}
    size: [0.02, 0.03]
    albedo: 0.8
"""
    scene = load_scene_text(text)
    rng = np.random.default_rng(3)
    n = 4000
    o = rng.normal(0.0, 0.02, (n, 3))
    d = np.column_stack([rng.normal(0, 0.08, n), rng.normal(0, 0.08, n), np.ones(n)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    ref = scene.intersect(o, d)
    ptype, pobj, R, T, prm = scene.packed()
    t = np.empty(n)
    prim = np.empty(n, np.int64)
    axis = np.empty(n, np.int64)
    cols = [np.ascontiguousarray(a) for a in (*o.T, *d.T)]
    rk.soa_closest(ptype, R, T, prm, *cols, t, prim, axis)
    obj = np.where(prim >= 0, pobj[np.maximum(prim, 0)], -1)
    assert set(ref.obj.tolist()) == {0, 1, 2, 3, 4}    # every object is hit
    assert np.array_equal(obj, ref.obj)
    hit = ref.obj >= 0
    assert np.allclose(t[hit], ref.t[hit], rtol=0, atol=1e-12)
    for i in np.flatnonzero(hit)[::7]:
        p = o[i] + t[i] * d[i]
        nrm = rk._hit_normal(ptype, R, T, prm, prim[i], axis[i], *p, *d[i])
        assert np.allclose(nrm, ref.normal[i], atol=1e-12)
    tmax = np.where(hit, ref.t * rng.uniform(0.5, 1.5, n), 1.0)
    expected = scene.occluded(o, d, tmax)
    assert 0 < expected.sum() < n
    blocked = np.empty(n, np.bool_)
    rk.trace_blocked(ptype, R, T, prm, o, d, tmax, blocked)
    assert np.array_equal(blocked, expected)
    rk.soa_blocked(ptype, R, T, prm, *cols, tmax, blocked)
    assert np.array_equal(blocked, expected)


def test_compiled_mirror_tracing_matches_numpy():
    rig = REFERENCE
    sim = Simulator(rig, load_scene('plane'), seed=0)
    geo = sim.geometry(rig.mirror_angles(np.array([2.0, -3.0, 0.0, 0.0])))
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.04, 0.04, (500, 2))
    o = np.empty((500, 3))
    d = np.empty((500, 3))
    rk.camera_rays(geo.extra['cam'], xy, o, d)
    o_G, d_G = rig.trace_camera_rays(xy, geo.angles[0], geo.angles[1])
    W = rig.W_T_G
    assert np.allclose(o, o_G @ W[:3, :3].T + W[:3, 3], atol=1e-14)
    assert np.allclose(d, d_G @ W[:3, :3].T, atol=1e-14)


STAIR_REF = Simulator(REFERENCE, load_scene('stair_block'), seed=11)


@settings(max_examples=8, deadline=None)
@given(st.floats(-0.4, 0.4), st.floats(-0.4, 0.4), st.floats(-2.0, 2.0), st.floats(-0.3, 0.3))
def test_truth_is_consistent_for_any_voltages(u1p, u1t, u2p, du2):
    """Property: wherever the stripe falls, its truth is on the sheet and the surface and
    projects onto its pixel (reference rig, every imperfection on)."""
    u2t = patterns.aim_laser(REFERENCE, u1p, u1t, 0.66, u2p) + du2
    frame = STAIR_REF.render([u1p, u1t, u2p, u2t])
    if len(frame.truth.stripe):
        check_truth(STAIR_REF, frame)


def test_scan_is_lazy_and_checks_its_input():
    sim = Simulator(IDEAL, load_scene('plane'), seed=0)
    volts = patterns.g2_sweep([0.0, 0.1, 0.2])
    it = sim.scan(volts)
    first = next(it)
    assert first.truth.index == 0 and first.image.shape == (540, 720)
    assert [f.truth.index for f in it] == [1, 2]
    with pytest.raises(ValueError, match='shape'):
        next(sim.scan(np.zeros((3, 3))))
    with pytest.raises(ValueError, match='range'):
        next(sim.scan(np.array([[0.0, 0.0, 0.0, 12.0]])))
    with pytest.raises(ValueError, match='voltages'):
        sim.render([0.0, 0.0])
