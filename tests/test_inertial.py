import numpy as np
import pytest
from safesysid.systems.model import inertial


def test_identity_parameters():
    assert np.allclose(inertial.log_cholesky_to_theta(np.zeros(10)), [1, 0, 0, 0, 2, 2, 2, 0, 0, 0])


@pytest.mark.parametrize("seed", range(5))
def test_jacobian_and_hessian_match_finite_differences(seed):
    eta = np.random.default_rng(seed).normal(scale=0.6, size=10)
    h = 1e-6
    eye = np.eye(10)
    jac_fd = np.stack(
        [
            (inertial.log_cholesky_to_theta(eta + h * e) - inertial.log_cholesky_to_theta(eta - h * e)) / (2 * h)
            for e in eye
        ],
        1,
    )
    assert np.allclose(inertial.log_cholesky_jacobian(eta), jac_fd, atol=1e-7)
    hess_fd = np.stack(
        [
            (inertial.log_cholesky_jacobian(eta + h * e) - inertial.log_cholesky_jacobian(eta - h * e)) / (2 * h)
            for e in eye
        ],
        2,
    )
    assert np.allclose(inertial.log_cholesky_hessian(eta), hess_fd, atol=1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_round_trip(seed):
    eta = np.random.default_rng(seed).normal(size=10)
    theta = inertial.log_cholesky_to_theta(eta)
    assert inertial.is_physically_consistent(theta)
    assert np.allclose(inertial.theta_to_log_cholesky(theta), eta, atol=1e-10)
    assert np.allclose(inertial.from_spatial_inertia(inertial.to_spatial_inertia(theta)), theta)


def test_lmi_rejects_invalid_inertias():
    valid = inertial.from_mass_com_inertia(2.0, [0.01, 0, -0.1], np.diag([0.01, 0.012, 0.005]))
    assert inertial.is_physically_consistent(valid)
    triangle_violation = inertial.from_mass_com_inertia(2.0, [0, 0, 0], np.diag([0.01, 0.01, 0.05]))
    negative_mass = valid * np.r_[-1, np.ones(9)]
    com_outside = inertial.from_mass_com_inertia(2.0, [0, 0, 0], np.diag([0.01, 0.01, 0.01]))
    com_outside[1] = 2.0 * 1.0  # 1 m away with tiny inertia
    for bad in (triangle_violation, negative_mass, com_outside):
        assert not inertial.is_physically_consistent(bad)
        with pytest.raises(ValueError):
            inertial.theta_to_log_cholesky(bad)


def test_shift_matches_parallel_axis():
    theta_c = inertial.from_mass_com_inertia(3.0, [0, 0, 0], np.diag([0.02, 0.03, 0.04]))
    shifted = inertial.shift_to(theta_c, [0, 0, -0.2])
    assert np.allclose(shifted, inertial.from_mass_com_inertia(3.0, [0, 0, -0.2], np.diag([0.02, 0.03, 0.04])))
