"""Surface materials: the BRDF against its reference maths, the reflected stripe against
geometric optics, the subsurface bias, and matte scenes unchanged."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from galvoscan_sim import Simulator, load_rig, load_scene, load_scene_text
from galvoscan_sim import materials as mt
from galvoscan_sim import raykernels as rk
from galvoscan_sim.config import ConfigError


def test_fresnel_against_known_values():
    # air/glass n = 1.5 at normal incidence: ((n - 1) / (n + 1))^2 = 0.04
    assert mt.fresnel(1.0, 1.5) == pytest.approx(0.04, abs=1e-12)
    # aluminium at 650 nm (Rakic 1995): R0 ~ 0.91; any conductor tends to 1 at grazing
    assert mt.material('machined_aluminium').normal_reflectance == pytest.approx(0.912,
                                                                                  abs=0.005)
    assert mt.fresnel(1e-6, 1.47, 7.79) == pytest.approx(1.0, abs=1e-4)
    # Brewster angle of a dielectric: p-polarised reflectance 0, so R = Rs / 2
    cb = math.cos(math.atan(1.5))
    st = math.sin(math.atan(1.5)) / 1.5
    ct = math.sqrt(1 - st * st)
    rs = ((cb - 1.5 * ct) / (cb + 1.5 * ct)) ** 2
    assert mt.fresnel(cb, 1.5) == pytest.approx(0.5 * rs, abs=1e-12)


def test_compiled_specular_term_matches_reference():
    rng = np.random.default_rng(4)
    for name in ('machined_aluminium', 'ground_steel', 'black_anodised', 'marble'):
        m = mt.material(name)
        row = m.packed()
        for _ in range(20):
            n = np.array([0.0, 0.0, -1.0])
            l, v = rng.normal(size=(2, 3)) + [0, 0, -1.5]
            l /= np.linalg.norm(l)
            v /= np.linalg.norm(v)
            ref = mt.specular_reflectance(m, n, l, v)
            got = rk.specular_term(row, *n, *l, *v)
            assert got == pytest.approx(ref, rel=1e-9, abs=1e-12)


def test_scene_material_key():
    scene = load_scene('stair_block_machined_aluminium')
    stair = scene.objects[scene.object_index('stair')]
    assert stair.material.name == 'machined_aluminium'
    assert stair.albedo == stair.material.albedo
    assert scene.specular and not scene.subsurface
    assert not load_scene('stair_block').specular
    with pytest.raises(ConfigError, match='material'):
        load_scene_text("""format_version: 1
name: bad
objects:
  - {type: plane, name: p, material: unobtainium, pose: {translation: [0, 0, 1]}}
""")


def _face(name, p, n, out, material, width=0.04, length=0.08, thick=0.01):
    R = Rotation.align_vectors([n, out], [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])[0]
    c = p + out * width / 2 - n * thick / 2
    fmt = ', '.join
    surface = f'material: {material}' if material else 'albedo: 0.6'
    return (f"  - type: box\n    name: {name}\n    pose: {{translation: [{fmt(map(str, c))}], "
            f"rotation_vector: [{fmt(map(str, R.as_rotvec()))}]}}\n"
            f"    size: [{width}, {length}, {thick}]\n    {surface}\n")


def _corner(mirror_material):
    """An inside corner at 660 mm: a left face of ``mirror_material`` and a matt right
    face; returns the scene, the left face's plane (n, point) and the right face's."""
    p = np.array([0.0, 0.0, 0.66])
    h = math.pi / 4
    left_out = np.array([-math.sin(h), 0.0, -math.cos(h)])
    left_n = np.array([math.cos(h), 0.0, -math.sin(h)])
    right_out = np.array([math.sin(h), 0.0, -math.cos(h)])
    right_n = np.array([-math.cos(h), 0.0, -math.sin(h)])
    text = ('format_version: 1\nname: corner\nobjects:\n'
            + _face('left', p, left_n, left_out, mirror_material)
            + _face('right', p, right_n, right_out, None))
    return load_scene_text(text), (left_n, p), (right_n, p)


def _expected_reflection_rows(sim, truth, mirror, receiver):
    """Rows per column where geometric optics puts the stripe mirrored by ``mirror`` on
    ``receiver`` (planes (n, point)): the laser's centre plane reflected through the
    mirror plane, cut with the receiver's plane, projected through the G1 mirrors."""
    nm, pm = mirror
    H = np.eye(3) - 2.0 * np.outer(nm, nm)
    plane = truth.laser_plane_W
    src = truth.laser_source_W
    src_m = src - 2.0 * (nm @ (src - pm)) * nm
    N = H @ plane[:3]
    e = -N @ src_m
    nr, pr = receiver
    direction = np.cross(N, nr)
    direction /= np.linalg.norm(direction)
    A = np.array([N, nr, direction])
    base = np.linalg.solve(A, [-e, nr @ pr, direction @ pr])
    pts = base + np.linspace(-0.06, 0.06, 4001)[:, None] * direction
    uv = sim.project_points(pts, truth.angles)
    ok = np.isfinite(uv).all(axis=1)
    uv = uv[ok]
    order = np.argsort(uv[:, 0])
    return uv[order, 0], uv[order, 1]


@pytest.mark.parametrize('u2', [-0.3, -0.15])
def test_mirrored_stripe_lands_where_geometric_optics_says(u2):
    rig = load_rig('ideal')
    scene, mirror, receiver = _corner('polished_aluminium')
    sim = Simulator(rig, scene, seed=2)
    frame = sim.render([0.0, 0.0, 0.0, u2])
    truth = frame.truth
    uu, vv = _expected_reflection_rows(sim, truth, mirror, receiver)
    refl = truth.reflection
    assert len(refl) > 100
    # the simulator's true reflected points lie on the geometric line
    v_geo = np.interp(refl.column, uu, vv)
    assert np.max(np.abs(refl.v - v_geo)) < 0.05
    # and the image shows the stripe there: intensity centroid within a few tenths of a px
    img = frame.image.astype(np.float64)
    direct_cols = set(truth.stripe.column[truth.stripe.object_index == 1].tolist())
    errors = []
    for c, v in zip(refl.column, v_geo, strict=True):
        r0 = int(round(v))
        if r0 < 8 or r0 > img.shape[0] - 9 or any(
                abs(vd - v) < 12 for vd in truth.stripe.v[truth.stripe.column == c]):
            continue
        w = img[r0 - 6:r0 + 7, c] - np.median(img[:, c])
        w = np.clip(w, 0, None)
        if w.sum() < 50:
            continue
        errors.append(np.sum(w * np.arange(r0 - 6, r0 + 7)) / w.sum() - v)
    assert len(errors) > 50, (len(errors), len(direct_cols))
    assert abs(np.median(errors)) < 0.3
    assert np.percentile(np.abs(errors), 90) < 0.8


def test_matte_corner_throws_no_stripe():
    rig = load_rig('ideal')
    scene, _, _ = _corner(None)
    frame = Simulator(rig, scene, seed=2).render([0.0, 0.0, 0.0, -0.3])
    assert len(frame.truth.reflection) == 0


def test_subsurface_biases_the_stripe():
    """Marble: the stripe's centre moves by the stated shift (materials.subsurface_shift)
    along the sheet normal; an opaque part of the same reflectance does not move."""
    rig = load_rig('ideal')
    rows = {}
    for surface in ('material: marble', 'albedo: 0.83'):
        scene = load_scene_text(f"""format_version: 1
name: slab
objects:
  - type: box
    name: slab
    pose: {{translation: [0.0, 0.0, 0.67], rotation_vector: [0.0, 0.0, 0.0]}}
    size: [0.2, 0.2, 0.04]
    {surface}
""")
        frame = Simulator(rig, scene, seed=5).render([0.0, 0.0, 0.0, 0.0])
        img = frame.image.astype(np.float64)
        s = frame.truth.stripe
        cols = s.column[(s.column > 200) & (s.column < 520)]
        v = np.interp(cols, s.column, s.v)
        cent = []
        for c, vt in zip(cols, v, strict=True):
            r0 = int(round(vt))
            w = np.clip(img[r0 - 15:r0 + 16, c] - 1.0, 0, None)
            cent.append(np.sum(w * np.arange(r0 - 15, r0 + 16)) / w.sum() - vt)
        rows[surface] = float(np.median(cent))
        geo = frame.truth
    assert abs(rows['albedo: 0.83']) < 0.1
    # the stated shift: the glow's centre moved along the sheet normal by
    # materials.subsurface_shift, i.e. on the face (normal -z) by that over the sheet
    # normal's in-face part; the image centroid moves by sss_fraction of it
    m = mt.material('marble')
    n = np.array([0.0, 0.0, -1.0])
    X = geo.stripe.points_W[len(geo.stripe) // 2]
    d = X - geo.laser_source_W
    d /= np.linalg.norm(d)
    N = geo.laser_plane_W[:3]
    shift = mt.subsurface_shift(m, n, d, N)
    assert abs(shift) > 0.05e-3
    Nt = N - (N @ n) * n
    moved = X + m.sss_fraction * shift * Nt / (Nt @ Nt)
    uv = Simulator(rig, load_scene('plane'), seed=5).project_points(np.array([X, moved]),
                                                                    geo.angles)
    assert rows['material: marble'] == pytest.approx(uv[1, 1] - uv[0, 1], rel=0.25)
