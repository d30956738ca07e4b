"""The physical mirror model: equal to the paper's without deviations, exact on the
simulator's rigs, fast enough, and refusing bad descriptions."""

import dataclasses
import math

import numpy as np
import pytest

from reconstructor.calibration_file import Calibration, load, save
from reconstructor.geometry.laser import laser_plane_v0_scalar
from reconstructor.geometry.rig import v0_T_v_scalar
from reconstructor.model import (
    PhysicalGeometry,
    RigModel,
    laser_plane_v0,
    nominal_example_rig,
    predict_pixels,
    triangulate,
    v0_T_v,
)

RNG = np.random.default_rng(20)


def _paper_rig():
    m = nominal_example_rig(dist=(-0.3, 2.0, 2e-4, -1e-4, 0.0))
    # a laser axis that misses the U2 = 0 plane, and non-linear galvos, as calibrations give
    return dataclasses.replace(
        m, laser_axis_point=m.laser_axis_point + np.array([0.0, 4e-4, -7e-4]),
        g1_pan=dataclasses.replace(m.g1_pan, poly=(1.2e-6, -2e-7)),
        g1_tilt=dataclasses.replace(m.g1_tilt, poly=(-1e-6, 1.5e-7)),
        g2_tilt=dataclasses.replace(m.g2_tilt, poly=(3e-7,)))


@pytest.mark.parametrize("psi", [math.pi / 4, -math.pi / 4, 0.3])
def test_without_deviations_the_physical_model_is_the_papers(psi):
    paper = _paper_rig()
    phys = dataclasses.replace(paper, physical=PhysicalGeometry(g2_tilt_normal_angle=psi))
    U = RNG.uniform(-10.0, 10.0, (200, 3))
    assert np.abs(v0_T_v(paper, U[:, 0], U[:, 1]) - v0_T_v(phys, U[:, 0], U[:, 1])).max() < 1e-12
    assert np.abs(laser_plane_v0(paper, U[:, 2]) - laser_plane_v0(phys, U[:, 2])).max() < 1e-12
    for up, ut, u2 in U[:10]:
        assert np.abs(v0_T_v_scalar(paper, up, ut) - v0_T_v_scalar(phys, up, ut)).max() < 1e-12
        assert np.abs(np.subtract(laser_plane_v0_scalar(paper, u2),
                                  laser_plane_v0_scalar(phys, u2))).max() < 1e-12
    uv = np.column_stack([RNG.uniform(0, 720, 500), RNG.uniform(0, 540, 500)])
    for up, ut, u2 in U[:5]:
        a = triangulate(paper, uv, up, ut, u2)
        b = triangulate(phys, uv, up, ut, u2)
        np.testing.assert_array_equal(a.valid, b.valid)
        # 1e-12 relative: some rays meet the plane metres away
        assert np.abs(a.p_v0 - b.p_v0).max() < 1e-12 * max(1.0, np.abs(a.p_v0).max())


def test_the_physical_model_is_exact_on_the_simulators_rigs():
    """With the rig's own parameters the model gives the simulator's ray-traced virtual
    cameras and laser sheets: nothing the physics does is left out."""
    sim = pytest.importorskip("galvoscan_sim.rig")
    from galvoscan_sim.rig_family import draw_rig

    rigs = [sim.load_rig("reference")]
    rigs += [sim.rig_from_dict(draw_rig(seed), f"seed {seed}") for seed in (3, 14)]
    for rig in rigs:
        tp = rig.true_model_parameters()
        data = {"intrinsics": dict(fx=tp.fx, fy=tp.fy, cx=tp.cx, cy=tp.cy,
                                   dist=list(tp.distortion), width=720, height=540),
                "model": "physical", **rig.physical_model_parameters()}
        model = RigModel.from_dict(data)
        paper = dataclasses.replace(model, physical=None)
        worst_phys = worst_paper = worst_plane = 0.0
        for up, ut in RNG.uniform(-10.0, 10.0, (20, 2)):
            th = rig.mirror_angles(np.array([up, ut, 0.0, ut]))
            T = rig.V0_T_V(th[0], th[1])
            worst_phys = max(worst_phys, np.abs(T - v0_T_v(model, up, ut)).max())
            worst_paper = max(worst_paper, np.abs(T[:3, 3] - v0_T_v(paper, up, ut)[:3, 3]).max())
            sheet = rig.laser_sheet_G(th[2], th[3]).transformed(np.linalg.inv(rig.G_T_V0))
            plane = sheet.plane / np.linalg.norm(sheet.plane[:3])
            worst_plane = max(worst_plane, np.abs(plane - laser_plane_v0(model, ut)).max())
        assert worst_phys < 1e-12, rig.name
        assert worst_plane < 1e-12, rig.name
        assert worst_paper > 1e-6, rig.name  # the imperfections are real: the paper misses them


def test_dict_round_trip_and_calibration_file(tmp_path):
    phys = PhysicalGeometry(camera_rotation=(1e-4, -2e-4, 3e-4), camera_offset=(2e-5, -1e-5),
                            g1_axes_angle=-2e-4, g1_pan_surface_offset=1.5e-4,
                            g1_tilt_surface_offset=-1e-4, g2_tilt_surface_offset=1.5e-4,
                            g2_tilt_normal_angle=-0.78)
    model = dataclasses.replace(_paper_rig(), physical=phys)
    data = model.to_dict()
    assert data["model"] == "physical"
    back = RigModel.from_dict(data)
    assert back.physical == phys and back.kind == "physical"
    assert "model" not in _paper_rig().to_dict()  # paper files read and write as before
    path = tmp_path / "cal.yaml"
    save(Calibration(model=model, source="calibrated"), path)
    loaded = load(path).model
    assert loaded.physical == phys
    U = RNG.uniform(-10.0, 10.0, (20, 2))
    np.testing.assert_array_equal(v0_T_v(loaded, U[:, 0], U[:, 1]),
                                  v0_T_v(model, U[:, 0], U[:, 1]))


@pytest.mark.parametrize("change, key", [
    ({"model": "exact"}, "model.model"),
    ({"physical": {"camera_rotation": [0, 0, 0]}}, "unknown key physical"),
])
def test_bad_model_kind_is_refused(change, key):
    data = {**_paper_rig().to_dict(), **change}
    with pytest.raises(ValueError, match=key):
        RigModel.from_dict(data)


@pytest.mark.parametrize("key, value, match", [
    ("g1_pan_surface_offset", float("nan"), "g1_pan_surface_offset must be finite"),
    ("g1_pan_surface_offset", 0.15, "g1_pan_surface_offset = 0.15 is beyond"),  # mm, not m
    ("camera_rotation", [0.0, 0.0, 30.0], "camera_rotation"),  # degrees, not rad
    ("camera_offset", [0.0], "camera_offset"),
    ("g2_tilt_normal_angle", "pi/4", "g2_tilt_normal_angle"),
])
def test_bad_physical_values_are_refused_with_the_key_named(key, value, match):
    data = dataclasses.replace(_paper_rig(), physical=PhysicalGeometry()).to_dict()
    data["physical"][key] = value
    with pytest.raises(ValueError, match=match):
        RigModel.from_dict(data)


def test_missing_physical_key_is_named():
    data = dataclasses.replace(_paper_rig(), physical=PhysicalGeometry()).to_dict()
    del data["physical"]["g1_axes_angle"]
    with pytest.raises(ValueError, match="missing key physical.g1_axes_angle"):
        RigModel.from_dict(data)


def test_predict_and_triangulate_round_trip_through_physical_mirrors():
    phys = PhysicalGeometry(camera_rotation=(5e-4, -1e-3, 6e-4), g1_axes_angle=-3e-4,
                            g1_pan_surface_offset=2e-4, g1_tilt_surface_offset=-1e-4,
                            g1_pan_normal_tilt=2e-4, g2_tilt_surface_offset=1.5e-4,
                            g2_tilt_normal_tilt=1e-4)
    model = dataclasses.replace(_paper_rig(), physical=phys)
    uv = np.column_stack([RNG.uniform(50, 670, 200), RNG.uniform(50, 490, 200)])
    for up, ut, u2 in RNG.uniform(-0.5, 0.5, (5, 3)):
        res = triangulate(model, uv, up, ut, u2)
        assert res.valid.sum() > 150
        back, ok = predict_pixels(model, res.p_v0[res.valid], up, ut)
        assert ok.all() and np.abs(back - uv[res.valid]).max() < 1e-6
        plane = laser_plane_v0(model, u2)
        assert np.abs(res.p_v0[res.valid] @ plane[:3] + plane[3]).max() < 1e-12
