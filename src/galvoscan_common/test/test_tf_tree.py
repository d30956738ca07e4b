"""galvoscan_common.tf_tree: conversions against scipy, lookups against brute force, refusals."""

import math

import numpy as np
import pytest
from geometry_msgs.msg import TransformStamped
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from tf2_msgs.msg import TFMessage

from galvoscan_common.tf_tree import (
    ConnectivityError,
    ExtrapolationError,
    LoopError,
    TfBuffer,
    TfError,
    UnknownFrameError,
    check_rigid,
    matrix_from_quaternion,
    quaternion_from_matrix,
    tq_from_transform,
    transform_from_tq,
)

S = 1_000_000_000  # ns per second


def random_transform(rng, scale=1.0):
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.normal(0.0, scale, 3)
    return T


def rot_z(angle, t=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.0, 0.0, angle]).as_matrix()
    T[:3, 3] = t
    return T


# ---- conversions ------------------------------------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10**6))
def test_quaternion_matches_scipy_both_ways(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng)
    q = quaternion_from_matrix(R.as_matrix())
    ref = R.as_quat()  # x, y, z, w
    ref = -ref if ref[3] < 0 else ref
    np.testing.assert_allclose(q, ref, atol=1e-12)
    assert q[3] >= 0.0
    np.testing.assert_allclose(matrix_from_quaternion(ref), R.as_matrix(), atol=1e-12)


@pytest.mark.parametrize('rotvec', [
    (math.pi, 0, 0), (0, math.pi, 0), (0, 0, math.pi), (math.pi / math.sqrt(2),) * 2 + (0,),
    (0, 0, 0), (1e-9, 0, 0), (0, 0, math.pi - 1e-9)])
def test_quaternion_near_half_turns_and_identity(rotvec):
    # trace near -1 (half turns) and near 3 (identity) are where naive formulas lose digits
    R = Rotation.from_rotvec(rotvec).as_matrix()
    np.testing.assert_allclose(matrix_from_quaternion(quaternion_from_matrix(R)), R,
                               atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10**6))
def test_transform_and_translation_quaternion_round_trip(seed):
    T = random_transform(np.random.default_rng(seed), 5.0)
    t, q = tq_from_transform(T)
    np.testing.assert_allclose(transform_from_tq(t, q), T, atol=1e-12)


def test_denormalised_quaternions_and_bad_translations_are_refused():
    with pytest.raises(ValueError, match='not normalised'):
        transform_from_tq((0, 0, 0), (0, 0, 0, 2))
    with pytest.raises(ValueError, match='finite'):
        transform_from_tq((0, 0, 0), (0, 0, math.nan, 1))
    with pytest.raises(ValueError, match='translation'):
        transform_from_tq((0, math.inf, 0), (0, 0, 0, 1))
    # slightly off unit length (a float32 round trip) is normalised, as tf2 does
    q = np.array([0.1, 0.2, 0.3, 0.9], np.float32)
    q = q / np.linalg.norm(q)
    np.testing.assert_allclose(np.linalg.det(matrix_from_quaternion(q)), 1.0, atol=1e-12)


def test_check_rigid_accepts_rigid_and_names_what_is_wrong():
    T = random_transform(np.random.default_rng(3))
    np.testing.assert_array_equal(check_rigid(T), T)
    np.testing.assert_array_equal(check_rigid(T.ravel().tolist(), 'cell_T_v0'), T)
    reflection = T.copy()
    reflection[:3, 0] *= -1
    with pytest.raises(ValueError, match=r'cell_T_v0: rotation block has determinant -1'):
        check_rigid(reflection, 'cell_T_v0')
    scaled = T.copy()
    scaled[:3, :3] *= 1.001
    with pytest.raises(ValueError, match='not orthonormal'):
        check_rigid(scaled)
    nan = T.copy()
    nan[0, 3] = math.nan
    with pytest.raises(ValueError, match='finite'):
        check_rigid(nan)
    row = T.copy()
    row[3, 0] = 0.5
    with pytest.raises(ValueError, match='last row'):
        check_rigid(row)
    with pytest.raises(ValueError, match='4x4'):
        check_rigid(np.eye(3))
    with pytest.raises(ValueError, match='numbers'):
        check_rigid([['a'] * 4] * 4)


# ---- lookups ----------------------------------------------------------------------------------
def random_tree(rng, n):
    """Frames f0..f{n-1}; f0 and f1 roots of two trees; each other frame's parent earlier."""
    parents = {f'f{i}': f'f{rng.integers(0, i) if i > 2 else 0}' for i in range(2, n)}
    edges = {child: random_transform(rng) for child in parents}
    return parents, edges


def root_T(parents, edges, frame):
    """Brute force: root_T_frame by recursion over the parents."""
    if frame not in parents:
        return np.eye(4), frame
    up, root = root_T(parents, edges, parents[frame])
    return up @ edges[frame], root


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10**6), st.integers(3, 12))
def test_lookup_equals_composition_through_the_root(seed, n):
    rng = np.random.default_rng(seed)
    parents, edges = random_tree(rng, n)
    buf = TfBuffer()
    for child in rng.permutation(list(parents)):  # insertion order does not matter
        buf.set_transform(parents[child], child, edges[child], static=True)
    frames = sorted(buf.frames())
    for _ in range(10):
        a, b = rng.choice(frames, 2)
        Ta, ra = root_T(parents, edges, a)
        Tb, rb = root_T(parents, edges, b)
        if ra != rb:
            with pytest.raises(ConnectivityError, match='not connected'):
                buf.lookup(a, b)
            continue
        a_T_b = buf.lookup(a, b)
        np.testing.assert_allclose(a_T_b, np.linalg.inv(Ta) @ Tb, atol=1e-9)
        np.testing.assert_allclose(a_T_b @ buf.lookup(b, a), np.eye(4), atol=1e-9)


def test_same_frame_is_identity_and_unknown_frames_are_named():
    buf = TfBuffer()
    buf.set_transform('world', 'v0', rot_z(0.3, (1, 2, 3)), static=True)
    np.testing.assert_array_equal(buf.lookup('v0', 'v0'), np.eye(4))
    with pytest.raises(UnknownFrameError, match=r"frame 'camera' does not exist \(known: v0, "
                                                r"world\)"):
        buf.lookup('world', 'camera')
    assert not buf.can_transform('world', 'camera')
    assert buf.can_transform('world', 'v0')
    assert buf.parent('v0') == 'world' and buf.parent('world') is None


def test_interpolation_between_samples_and_extrapolation_limits():
    buf = TfBuffer(extrapolation_tolerance=S // 100)
    buf.set_transform('world', 'v0', np.eye(4), static=True)
    buf.set_transform('v0', 'v', rot_z(0.0, (0, 0, 0)), stamp=10 * S)
    buf.set_transform('v0', 'v', rot_z(0.4, (0.2, 0, 0)), stamp=11 * S)
    mid = buf.lookup('world', 'v', 10 * S + S // 4)
    np.testing.assert_allclose(mid, rot_z(0.1, (0.05, 0, 0)), atol=1e-12)
    # no time: the newest sample
    np.testing.assert_allclose(buf.lookup('world', 'v'), rot_z(0.4, (0.2, 0, 0)), atol=1e-12)
    # within the tolerance: the end sample; beyond it: an error naming both times
    np.testing.assert_allclose(buf.lookup('world', 'v', 11 * S + S // 200),
                               rot_z(0.4, (0.2, 0, 0)), atol=1e-12)
    with pytest.raises(ExtrapolationError, match=r'v0 -> v at 11.020000000 s: after the newest'):
        buf.lookup('world', 'v', 11 * S + S // 50)
    with pytest.raises(ExtrapolationError, match='before the oldest'):
        buf.lookup('v', 'world', 9 * S)
    # static edges hold at every time
    np.testing.assert_array_equal(buf.lookup('world', 'v0', 123), np.eye(4))


def test_slerp_takes_the_shorter_arc():
    buf = TfBuffer()
    buf.set_transform('a', 'b', rot_z(math.pi - 0.1), stamp=0)
    buf.set_transform('a', 'b', rot_z(-math.pi + 0.1), stamp=2)  # 0.2 rad further, not 6.08
    np.testing.assert_allclose(buf.lookup('a', 'b', 1), rot_z(math.pi), atol=1e-12)


def test_no_time_is_the_latest_time_every_stamped_edge_has():
    buf = TfBuffer()
    for stamp, x in ((1 * S, 0.0), (2 * S, 1.0), (3 * S, 2.0)):
        buf.set_transform('world', 'a', rot_z(0, (x, 0, 0)), stamp=stamp)
    buf.set_transform('a', 'b', rot_z(0, (0, 1, 0)), stamp=1 * S)
    buf.set_transform('a', 'b', rot_z(0, (0, 3, 0)), stamp=2 * S)
    assert buf.latest_common_time('world', 'b') == 2 * S
    np.testing.assert_allclose(buf.lookup('world', 'b')[:3, 3], (1.0, 3.0, 0.0))
    # one edge alone: its own newest sample
    np.testing.assert_allclose(buf.lookup('world', 'a')[:3, 3], (2.0, 0.0, 0.0))


def test_history_is_bounded_sorted_and_replaced_on_equal_stamps():
    buf = TfBuffer(max_history=3, cache_time=10 * S)
    for k in (5, 1, 3, 2, 4):  # out of order
        buf.set_transform('p', 'c', rot_z(0, (k, 0, 0)), stamp=k * S)
    # the three newest are kept, in order
    with pytest.raises(ExtrapolationError, match='samples from 3.000000000 to 5.000000000 s'):
        buf.lookup('p', 'c', 2 * S)
    np.testing.assert_allclose(buf.lookup('p', 'c', 3 * S + S // 2)[:3, 3], (3.5, 0, 0))
    buf.set_transform('p', 'c', rot_z(0, (9, 0, 0)), stamp=5 * S)
    np.testing.assert_allclose(buf.lookup('p', 'c', 5 * S)[:3, 3], (9, 0, 0))
    # older than cache_time before the newest: dropped
    buf = TfBuffer(cache_time=2 * S)
    for k in range(6):
        buf.set_transform('p', 'c', np.eye(4), stamp=k * S)
    with pytest.raises(ExtrapolationError, match='samples from 3.000000000 to 5.000000000 s'):
        buf.lookup('p', 'c', 2 * S)


def test_reparenting_and_static_replace_the_history():
    buf = TfBuffer()
    buf.set_transform('a', 'c', rot_z(0, (1, 0, 0)), stamp=S)
    buf.set_transform('b', 'c', rot_z(0, (2, 0, 0)), stamp=2 * S)
    assert buf.parent('c') == 'b'
    buf.set_transform('b', 'c', rot_z(0, (3, 0, 0)), static=True)
    np.testing.assert_allclose(buf.lookup('b', 'c', 7)[:3, 3], (3, 0, 0))


def test_bad_transforms_are_refused_and_change_nothing():
    buf = TfBuffer()
    buf.set_transform('world', 'v0', np.eye(4), static=True)
    buf.set_transform('v0', 'v', np.eye(4), stamp=S)
    before = buf.lookup('world', 'v')
    with pytest.raises(LoopError, match='v -> world would close a loop: v already descends '
                                      'from world'):
        buf.set_transform('v', 'world', np.eye(4), static=True)
    with pytest.raises(LoopError):
        buf.set_transform('v', 'v0', np.eye(4), stamp=2 * S)
    with pytest.raises(TfError, match='to itself'):
        buf.set_transform('v', 'v', np.eye(4))
    with pytest.raises(ValueError, match="no leading '/'"):
        buf.set_transform('/world', 'x', np.eye(4))
    with pytest.raises(ValueError, match='non-empty'):
        buf.set_transform('world', '', np.eye(4))
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(TfError, match='world_T_x: rotation block has determinant -1'):
        buf.set_transform('world', 'x', mirror)
    assert buf.frames() == {'world', 'v0', 'v'}
    np.testing.assert_array_equal(buf.lookup('world', 'v'), before)


def _tf(parent, child, sec, t, q):
    msg = TransformStamped()
    msg.header.frame_id, msg.child_frame_id = parent, child
    msg.header.stamp.sec = sec
    (msg.transform.translation.x, msg.transform.translation.y,
     msg.transform.translation.z) = t
    (msg.transform.rotation.x, msg.transform.rotation.y, msg.transform.rotation.z,
     msg.transform.rotation.w) = q
    return msg


def test_tf_messages_fill_the_buffer_whole_or_not_at_all():
    T = random_transform(np.random.default_rng(5))
    t, q = tq_from_transform(T)
    msg = TFMessage(transforms=[_tf('world', 'v0', 0, t, q),
                                _tf('v0', 'v', 4, (0.0, 0.1, 0.0), (0.0, 0.0, 0.0, 1.0))])
    buf = TfBuffer()
    buf.set_message(msg.transforms, static=False)
    np.testing.assert_allclose(buf.lookup('world', 'v0'), T, atol=1e-12)
    assert buf.latest_common_time('world', 'v') == 0  # world -> v0 stamped at 0 s
    bad = TFMessage(transforms=[_tf('v0', 'a', 5, (0, 0, 0), (0, 0, 0, 1)),
                                _tf('v0', 'b', 5, (0, 0, 0), (0.0, 0.0, 0.0, 0.0))])
    with pytest.raises(TfError, match=r'transforms\[1\] \(v0 -> b\): quaternion .* not '
                                      r'normalised'):
        buf.set_message(bad.transforms)
    looped = TFMessage(transforms=[_tf('v0', 'a', 5, (0, 0, 0), (0, 0, 0, 1)),
                                   _tf('a', 'world', 5, (0, 0, 0), (0, 0, 0, 1))])
    with pytest.raises(LoopError):
        buf.set_message(looped.transforms)
    assert buf.frames() == {'world', 'v0', 'v'}
