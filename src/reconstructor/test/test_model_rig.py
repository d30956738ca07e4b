"""RigModel: construction checks and the dict form used by the calibration file."""

import copy
import dataclasses
import math

import numpy as np
import pytest
import yaml

from reconstructor.model import CameraIntrinsics, MirrorParams, RigModel, nominal_example_rig


def example_model():
    base = nominal_example_rig(dist=(-0.25, 2.0, 1e-4, -1e-4, -20.0))
    return dataclasses.replace(
        base,
        g1_pan=MirrorParams(0.786, 0.0349, (2e-5, -1e-6)),
        g1_tilt=MirrorParams(0.784, -0.0351, ()),
        g2_tilt=MirrorParams(0.7, 0.035, (1e-5,)),
        laser_axis_dir=[0.99, 0.02, -0.0004],
        laser_plane_v0=[0.0, -0.9, 0.44, -0.28],
    )


def assert_same_model(a, b, atol=0.0):
    assert a.intrinsics == b.intrinsics
    assert (a.g1_pan, a.g1_tilt, a.g2_tilt) == (b.g1_pan, b.g1_tilt, b.g2_tilt)
    assert (a.l, a.d) == (b.l, b.d)
    for name in ("laser_plane_v0", "laser_axis_dir", "laser_axis_point"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=atol, rtol=0)


def test_dict_round_trip_is_plain_and_exact():
    model = example_model()
    data = model.to_dict()
    # Plain Python types only (YAML-safe), SI values as given.
    text = yaml.safe_dump(data)
    loaded = yaml.safe_load(text)
    assert loaded == data
    back = RigModel.from_dict(loaded)
    # The stored normal was already unit; re-normalising may move the last bit only.
    assert_same_model(back, model, atol=1e-16)
    assert data["l"] == 0.08345 and data["d"] == 0.02214
    assert data["intrinsics"]["dist"] == [-0.25, 2.0, 1e-4, -1e-4, -20.0]
    assert data["g1_pan"] == {"theta0": 0.786, "k": 0.0349, "poly": [2e-5, -1e-6]}
    assert back.correction is None


def test_construction_normalises_plane_and_axis():
    model = example_model()
    n = np.array([0.0, -0.9, 0.44])
    np.testing.assert_allclose(model.laser_plane_v0, [0, -0.9, 0.44, -0.28] / np.linalg.norm(n))
    np.testing.assert_allclose(np.linalg.norm(model.laser_axis_dir), 1.0, rtol=1e-15)
    with pytest.raises(ValueError):
        model.laser_axis_point[0] = 1.0  # read-only: the model is immutable


KEYS = [
    "intrinsics",
    "g1_pan",
    "g1_tilt",
    "l",
    "d",
    "laser_plane_v0",
    "laser_axis_dir",
    "laser_axis_point",
    "g2_tilt",
    "intrinsics.fx",
    "intrinsics.dist",
    "intrinsics.width",
    "g1_tilt.k",
    "g2_tilt.poly",
]


def _at(data, dotted):
    *parents, last = dotted.split(".")
    for p in parents:
        data = data[p]
    return data, last


@pytest.mark.parametrize("key", KEYS)
def test_from_dict_missing_key_names_it(key):
    data = copy.deepcopy(example_model().to_dict())
    parent, last = _at(data, key)
    del parent[last]
    with pytest.raises(ValueError, match=f"missing key {key}"):
        RigModel.from_dict(data)


@pytest.mark.parametrize(
    "key, value",
    [
        ("l", math.nan),
        ("d", math.inf),
        ("intrinsics.cy", math.nan),
        ("g1_pan.theta0", math.nan),
        ("g2_tilt.poly", [1e-5, math.nan]),
        ("laser_plane_v0", [0.0, 1.0, math.nan, 0.2]),
        ("laser_axis_point", [0.0, -math.inf, 0.2]),
        ("intrinsics.dist", [0.0, 0.0, 0.0, 0.0, math.nan]),
    ],
)
def test_from_dict_rejects_non_finite_naming_the_key(key, value):
    data = copy.deepcopy(example_model().to_dict())
    parent, last = _at(data, key)
    parent[last] = value
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        RigModel.from_dict(data)


@pytest.mark.parametrize(
    "key, value",
    [
        ("laser_plane_v0", [0.0, 1.0, 0.2]),
        ("laser_axis_dir", [1.0, 0.0, 0.0, 0.0]),
        ("laser_axis_point", 0.3),
        ("intrinsics.dist", [0.1, 0.0, 0.0, 0.0]),
        ("l", [0.08]),
        ("l", "0.08"),
        ("g1_pan.poly", 1e-5),
        ("intrinsics.width", 720.5),
        ("intrinsics.fx", -5.0),
        ("laser_plane_v0", [0.0, 0.0, 0.0, 1.0]),
        ("laser_axis_dir", [0.0, 0.0, 0.0]),
        ("g1_tilt", [0.7, 0.03]),
    ],
)
def test_from_dict_rejects_wrong_shape_or_value_naming_the_key(key, value):
    data = copy.deepcopy(example_model().to_dict())
    parent, last = _at(data, key)
    parent[last] = value
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        RigModel.from_dict(data)


def test_from_dict_rejects_unknown_keys():
    data = example_model().to_dict()
    data["units"] = "mm"
    with pytest.raises(ValueError, match="unknown key units"):
        RigModel.from_dict(data)
    data = example_model().to_dict()
    data["g2_tilt"]["offset"] = 0.0
    with pytest.raises(ValueError, match=r"unknown key g2_tilt\.offset"):
        RigModel.from_dict(data)


def test_constructor_type_checks():
    m = nominal_example_rig()
    with pytest.raises(ValueError, match="intrinsics"):
        dataclasses.replace(m, intrinsics={"fx": 1.0})
    with pytest.raises(ValueError, match="g2_tilt"):
        dataclasses.replace(m, g2_tilt=(0.7, 0.03))
    with pytest.raises(ValueError, match="laser_axis_point"):
        dataclasses.replace(m, laser_axis_point=[0.0, 0.0])


def test_nominal_example_is_close_to_the_paper_values():
    m = nominal_example_rig()
    assert isinstance(m.intrinsics, CameraIntrinsics)
    assert (m.intrinsics.fx, m.intrinsics.fy, m.intrinsics.cx, m.intrinsics.cy) == (
        7801.38,
        7798.24,
        359.51,
        269.54,
    )
    assert (m.l, m.d) == (0.08345, 0.02214)
    assert m.g1_pan.k == pytest.approx(math.radians(20.0) / 10.0)
    assert m.g1_pan.theta0 == m.g1_tilt.theta0 == pytest.approx(math.pi / 4)
    # The U2 = 0 plane contains the axis and the V0 optical-axis point at the stand-off.
    pi = m.laser_plane_v0
    assert pi[:3] @ m.laser_axis_point + pi[3] == pytest.approx(0.0, abs=1e-15)
    assert pi[:3] @ m.laser_axis_dir == pytest.approx(0.0, abs=1e-15)
    assert pi[2] * 0.65 + pi[3] == pytest.approx(0.0, abs=1e-15)
