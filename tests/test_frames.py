import numpy as np
import pytest

from partinspect.frames import orthonormal_frame, plane_basis, reference_direction


@pytest.mark.parametrize("n", [[0, 0, 1], [1, 0, 0], [0.95, 0.1, 0.3], [0.3, 0.4, 0.866], [-0.2, -0.9, 0.1]])
def test_frames_are_orthonormal_right_handed_and_agree(n):
    n = np.asarray(n, float) / np.linalg.norm(n)
    F = orthonormal_frame(n)
    np.testing.assert_allclose(F @ F.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(F) == pytest.approx(1.0)
    np.testing.assert_allclose(F[2], n)
    np.testing.assert_allclose(F[0], reference_direction(n))
    B = plane_basis(n)
    np.testing.assert_allclose(B.T @ B, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(B, np.stack([F[1], -F[0]], 1), atol=1e-12)


def test_reference_direction_is_the_projected_world_x_axis_unless_normal_is_near_it():
    np.testing.assert_allclose(reference_direction([0, 0, 2.0]), [1, 0, 0])
    np.testing.assert_allclose(reference_direction([1.0, 0, 0]), [0, 1, 0])
