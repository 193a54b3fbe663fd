import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flightkit import frames as F
from flightkit.errors import TransformError
from flightkit.frames import Transform

RNG = np.random.default_rng(7)


def random_transform() -> Transform:
    return Transform(Rotation.random(random_state=int(RNG.integers(1 << 30))), RNG.normal(size=3))


def test_transform_inverse_round_trip() -> None:
    for _ in range(50):
        T_a_b = random_transform()
        assert (T_a_b @ T_a_b.inverse()).almost_equal(Transform.identity(), 1e-12, 1e-12)
        assert (T_a_b.inverse() @ T_a_b).almost_equal(Transform.identity(), 1e-12, 1e-12)


def test_composition_cancels_inner_frames() -> None:
    T_a_b, T_b_c = random_transform(), random_transform()
    p_c = RNG.normal(size=(10, 3))
    np.testing.assert_allclose((T_a_b @ T_b_c).apply(p_c), T_a_b.apply(T_b_c.apply(p_c)), atol=1e-12)


def test_matrix_round_trip_and_quaternion_orders() -> None:
    T = random_transform()
    np.testing.assert_allclose(Transform.from_matrix(T.as_matrix()).as_matrix(), T.as_matrix(), atol=1e-12)
    T2 = Transform.from_quat_wxyz(T.translation, T.quat_wxyz)
    assert T2.almost_equal(T)
    np.testing.assert_allclose(F.quat_xyzw_to_wxyz(F.quat_wxyz_to_xyzw([1, 2, 3, 4])), [1, 2, 3, 4])


def test_transform_maps_points_as_named() -> None:
    # Body 1 m east of the world origin, facing north (yaw +90 deg in ENU).
    T_world_body = Transform.from_xyz_yaw([1.0, 0.0, 0.0], math.pi / 2)
    # A point 1 m ahead of the body is at (1, 1, 0) in the world.
    np.testing.assert_allclose(T_world_body.apply([1.0, 0.0, 0.0]), [1.0, 1.0, 0.0], atol=1e-12)
    assert T_world_body.yaw_rad == pytest.approx(math.pi / 2)


def test_enu_ned_round_trip_and_values() -> None:
    v = RNG.normal(size=(20, 3))
    np.testing.assert_allclose(F.ned_to_enu(F.enu_to_ned(v)), v)
    np.testing.assert_allclose(F.enu_to_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    np.testing.assert_allclose(F.flu_to_frd([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    np.testing.assert_allclose(F.frd_to_flu(F.flu_to_frd(v)), v)


def test_attitude_conversion_consistent_with_vectors() -> None:
    for _ in range(20):
        R_enu_flu = Rotation.random(random_state=int(RNG.integers(1 << 30)))
        R_ned_frd = F.rotation_ned_frd_from_enu_flu(R_enu_flu)
        v_flu = RNG.normal(size=3)
        # Rotating a body vector then converting must equal converting then rotating.
        np.testing.assert_allclose(
            F.enu_to_ned(R_enu_flu.apply(v_flu)), R_ned_frd.apply(F.flu_to_frd(v_flu)), atol=1e-12
        )
        back = F.rotation_enu_flu_from_ned_frd(R_ned_frd)
        assert (back.inv() * R_enu_flu).magnitude() < 1e-12


def test_yaw_conversions() -> None:
    assert F.yaw_enu_to_ned(0.0) == pytest.approx(math.pi / 2)  # facing east
    assert F.yaw_enu_to_ned(math.pi / 2) == pytest.approx(0.0)  # facing north
    for yaw in np.linspace(-3.1, 3.1, 25):
        assert F.yaw_ned_to_enu(F.yaw_enu_to_ned(yaw)) == pytest.approx(yaw)
        # The NED attitude of a level body must have the converted yaw.
        R_ned_frd = F.rotation_ned_frd_from_enu_flu(Rotation.from_euler("z", yaw))
        assert F.yaw_from_rotation(R_ned_frd) == pytest.approx(F.yaw_enu_to_ned(yaw))


def test_wrap_and_diff() -> None:
    assert F.wrap_angle_rad(3 * math.pi) == pytest.approx(-math.pi)
    assert F.angle_diff_rad(math.radians(179), math.radians(-179)) == pytest.approx(math.radians(-2))
    unwrapped = F.unwrap_angles_rad([3.0, -3.0, -2.9])
    assert np.all(np.abs(np.diff(unwrapped)) < 1.0)


def test_world_to_body_yaw() -> None:
    v_world = np.array([0.0, 1.0, 0.5])  # north and up
    # Facing north, "north" is straight ahead.
    np.testing.assert_allclose(F.world_to_body_yaw(v_world, math.pi / 2), [1.0, 0.0, 0.5], atol=1e-12)
    # Facing east, north is to the left (+y in FLU).
    np.testing.assert_allclose(F.world_to_body_yaw(v_world, 0.0), [0.0, 1.0, 0.5], atol=1e-12)


def test_bad_inputs_raise() -> None:
    with pytest.raises(TransformError, match="3 elements"):
        Transform(translation=np.array([1.0, 2.0]))
    with pytest.raises(TransformError, match="finite"):
        Transform(translation=np.array([1.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="last dimension of 3"):  # a TransformError is also a ValueError
        F.enu_to_ned([1.0, 2.0])
    with pytest.raises(TransformError, match="4x4 or 3x4"):
        Transform.from_matrix(np.eye(3))


def test_is_identity_is_exact() -> None:
    assert Transform.identity().is_identity
    assert Transform(Rotation.from_quat([0.0, 0.0, 0.0, -1.0])).is_identity  # the same rotation, other sign
    assert not Transform.from_xyz_yaw([0.0, 0.0, 0.0], 1e-12).is_identity
    assert not Transform.from_xyz_yaw([1e-15, 0.0, 0.0], 0.0).is_identity
    T = Transform.from_xyz_yaw([1.0, 2.0, 0.5], 0.3)  # noqa: N806
    assert (Transform.identity() @ T).almost_equal(T, 0.0, 0.0)  # what skipping the composition relies on
