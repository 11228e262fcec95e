import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from slam.geometry import (
    exp_se3,
    inv_T,
    log_se3,
    log_so3,
    make_T,
    pose_to_tum,
    rotation_angle_deg,
    tum_to_pose,
)

finite = st.floats(-3.0, 3.0, allow_nan=False)
twist = st.tuples(*[st.floats(-1.5, 1.5)] * 3, *[finite] * 3).map(np.array)
quat = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1).map(np.array)


@settings(max_examples=200, deadline=None)
@given(twist)
def test_exp_log_round_trip(xi):
    T = exp_se3(xi)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(exp_se3(log_se3(T)), T, atol=1e-9)


# rotations of any angle, from a millionth of a radian to a hair short of half a turn
axis = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.1).map(np.array)
angle = st.one_of(st.floats(1e-9, 1e-3), st.floats(1e-3, 3.0), st.floats(3.0, np.pi - 1e-9))


@settings(max_examples=300, deadline=None)
@given(axis, angle, st.tuples(finite, finite, finite).map(np.array))
def test_exp_and_log_agree_with_scipy_at_every_angle(a, theta, v):
    w = a / np.linalg.norm(a) * theta
    R = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(exp_se3(np.concatenate([w, v]))[:3, :3], R, atol=1e-14)
    np.testing.assert_allclose(log_so3(R), w, atol=1e-9 * max(1.0, 1.0 / (np.pi - theta)))
    np.testing.assert_allclose(log_so3(R), Rotation.from_matrix(R).as_rotvec(), atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(twist)
def test_inverse_composes_to_identity(xi):
    T = exp_se3(xi)
    np.testing.assert_allclose(T @ inv_T(T), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(inv_T(T) @ T, np.eye(4), atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(quat, st.tuples(finite, finite, finite).map(np.array))
def test_tum_round_trip(q, t):
    T = make_T(Rotation.from_quat(q).as_matrix(), t)
    v = pose_to_tum(T)
    assert v[6] >= 0  # canonical hemisphere
    np.testing.assert_allclose(tum_to_pose(v), T, atol=1e-9)


def test_rotation_angle():
    T = make_T(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [1, 2, 3])
    assert abs(rotation_angle_deg(T) - 30.0) < 1e-9
