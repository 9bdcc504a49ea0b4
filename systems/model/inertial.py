"""Inertial parameters of one rigid body, their physical consistency and log-Cholesky map.

Parameter order everywhere (NAMES below), inertia about the body-frame origin:
    theta = [m, m*cx, m*cy, m*cz, Ixx, Iyy, Izz, Ixy, Iyz, Ixz]
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from pydrake.multibody.tree import SpatialInertia

NAMES = ("m", "mcx", "mcy", "mcz", "Ixx", "Iyy", "Izz", "Ixy", "Iyz", "Ixz")
UNITS = ("kg", "kg m", "kg m", "kg m", "kg m^2", "kg m^2", "kg m^2", "kg m^2", "kg m^2", "kg m^2")


def inertia_matrix(theta: ArrayLike) -> np.ndarray:
    """3x3 rotational inertia about the body origin from theta (... x 10)."""
    t = np.asarray(theta, float)
    xx, yy, zz, xy, yz, xz = (t[..., k] for k in range(4, 10))
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)


def from_mass_com_inertia(mass: float, com: ArrayLike, inertia_about_com: ArrayLike) -> np.ndarray:
    """theta from mass, centre of mass and the inertia about the centre of mass (body frame)."""
    c = np.asarray(com, float)
    i_o = np.asarray(inertia_about_com, float) + mass * (c @ c * np.eye(3) - np.outer(c, c))
    return np.array([mass, *(mass * c), i_o[0, 0], i_o[1, 1], i_o[2, 2], i_o[0, 1], i_o[1, 2], i_o[0, 2]])


def from_spatial_inertia(spatial_inertia: SpatialInertia) -> np.ndarray:
    """theta from a Drake SpatialInertia (about the body origin, in the body frame)."""
    m = spatial_inertia.get_mass()
    h = m * np.asarray(spatial_inertia.get_com())
    i = spatial_inertia.CalcRotationalInertia().CopyToFullMatrix3()
    return np.array([m, *h, i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[1, 2], i[0, 2]])


def to_spatial_inertia(theta: ArrayLike) -> SpatialInertia:
    """Drake SpatialInertia about the body origin from theta (requires m > 0)."""
    from pydrake.multibody.tree import SpatialInertia, UnitInertia

    t = np.asarray(theta, float)
    m = t[0]
    com = t[1:4] / m
    i = inertia_matrix(t)
    unit = UnitInertia(i[0, 0] / m, i[1, 1] / m, i[2, 2] / m, i[0, 1] / m, i[0, 2] / m, i[1, 2] / m)
    return SpatialInertia(m, com, unit, skip_validity_check=True)


def shift_to(theta: ArrayLike, offset: ArrayLike, rotation: ArrayLike | None = None) -> np.ndarray:
    """theta of a body whose frame sits at `offset` (rotated by `rotation`, default none) in frame F, in F."""
    rotation = np.eye(3) if rotation is None else rotation
    t = np.asarray(theta, float)
    m, h_b, i_b = t[0], t[1:4], inertia_matrix(t)
    r = np.asarray(rotation, float)
    p = np.asarray(offset, float)
    # Inertia about the body origin -> about its com -> rotate -> about F's origin.
    c_b = h_b / m if m > 0 else np.zeros(3)
    i_c = i_b - m * (c_b @ c_b * np.eye(3) - np.outer(c_b, c_b))
    c_f = p + r @ c_b
    return from_mass_com_inertia(m, c_f, r @ i_c @ r.T) if m > 0 else np.zeros(10)


def pseudo_inertia(theta: ArrayLike) -> np.ndarray:
    """4x4 pseudo-inertia J = [[Sigma, h], [h^T, m]], Sigma = tr(I)/2 * 1 - I."""
    t = np.asarray(theta, float)
    i = inertia_matrix(t)
    sigma = 0.5 * np.trace(i, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) - i
    j = np.zeros(t.shape[:-1] + (4, 4))
    j[..., :3, :3] = sigma
    j[..., :3, 3] = t[..., 1:4]
    j[..., 3, :3] = t[..., 1:4]
    j[..., 3, 3] = t[..., 0]
    return j


def theta_from_pseudo_inertia(j: np.ndarray) -> np.ndarray:
    """Inverse of pseudo_inertia (linear)."""
    j = np.asarray(j, float)
    sigma = j[..., :3, :3]
    i = np.trace(sigma, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) - sigma
    return np.stack(
        [
            j[..., 3, 3],
            j[..., 0, 3],
            j[..., 1, 3],
            j[..., 2, 3],
            i[..., 0, 0],
            i[..., 1, 1],
            i[..., 2, 2],
            i[..., 0, 1],
            i[..., 1, 2],
            i[..., 0, 2],
        ],
        -1,
    )


def is_physically_consistent(theta: ArrayLike, tol: float = 0.0) -> bool:
    """LMI check: the pseudo-inertia is positive definite (min eigenvalue > tol)."""
    return bool(np.linalg.eigvalsh(pseudo_inertia(theta)).min() > tol)


# --- log-Cholesky map P(eta): pseudo-inertia = U U^T, U upper triangular --------------------
# eta = [alpha, d1, d2, d3, s12, s13, s23, s14, s24, s34]
_OFF_DIAGONAL = {4: (0, 1), 5: (0, 2), 6: (1, 2), 7: (0, 3), 8: (1, 3), 9: (2, 3)}


def _u_and_derivatives(eta):
    """U(eta) and its first (10,4,4) and second (10,10,4,4) derivatives."""
    eta = np.asarray(eta, float)
    a = np.exp(eta[0])
    base = np.zeros((4, 4))  # U / e^alpha
    d_base = np.zeros((10, 4, 4))
    for k in range(3):
        base[k, k] = np.exp(eta[1 + k])
        d_base[1 + k, k, k] = base[k, k]
    base[3, 3] = 1.0
    for k, (r, c) in _OFF_DIAGONAL.items():
        base[r, c] = eta[k]
        d_base[k, r, c] = 1.0
    u = a * base
    du = a * d_base
    du[0] = u
    ddu = np.zeros((10, 10, 4, 4))
    ddu[0, 0] = u
    ddu[0, 1:] = ddu[1:, 0] = du[1:]
    for k in range(3):  # d2 exp(d_k) / d d_k^2
        ddu[1 + k, 1 + k, k, k] = u[k, k]
    return u, du, ddu


def log_cholesky_to_theta(eta: ArrayLike) -> np.ndarray:
    """P(eta): physically consistent theta for any eta in R^10."""
    u, _, _ = _u_and_derivatives(eta)
    return theta_from_pseudo_inertia(u @ u.T)


def log_cholesky_jacobian(eta: ArrayLike) -> np.ndarray:
    """dP/deta (10 x 10), column k = dtheta/deta_k."""
    u, du, _ = _u_and_derivatives(eta)
    dj = du @ u.T
    return theta_from_pseudo_inertia(dj + np.swapaxes(dj, -1, -2)).T


def log_cholesky_hessian(eta: ArrayLike) -> np.ndarray:
    """d2P/deta2 (10 x 10 x 10): [i, k, l] = d2 theta_i / deta_k deta_l."""
    u, du, ddu = _u_and_derivatives(eta)
    ddj = ddu @ u.T + np.einsum("kab,lcb->klac", du, du)
    ddj = ddj + np.swapaxes(ddj, -1, -2)
    return np.moveaxis(theta_from_pseudo_inertia(ddj), -1, 0)


def theta_to_log_cholesky(theta: ArrayLike) -> np.ndarray:
    """P^{-1}: eta for a physically consistent theta (raises if the LMI fails)."""
    j = pseudo_inertia(theta)
    flip = np.eye(4)[::-1]
    try:
        lower = np.linalg.cholesky(flip @ j @ flip)
    except np.linalg.LinAlgError as err:
        raise ValueError("theta is not physically consistent (pseudo-inertia not positive definite)") from err
    u = flip @ lower @ flip  # upper triangular, U U^T = J
    a = u[3, 3]
    eta = np.zeros(10)
    eta[0] = np.log(a)
    eta[1:4] = np.log(np.diag(u)[:3] / a)
    for k, (r, c) in _OFF_DIAGONAL.items():
        eta[k] = u[r, c] / a
    return eta
