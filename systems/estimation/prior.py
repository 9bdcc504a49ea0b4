"""The end-effector prior of a robot that declares none: derived from a declared payload range.

A payload is any rigid body of mass in [m_lo, m_hi] whose matter lies in a box of half extents
h around a centre c, axes those of the end-effector frame (e.g. centred on the grasp point). Every
entry of its theta about the frame origin is then bounded entry by entry (theta order of
systems/model/inertial.py NAMES):
- m in [m_lo, m_hi];
- m c_i in m [c_i - h_i, c_i + h_i] (the centre of mass lies in the box);
- each inertia-tensor entry is the integral over the payload of a quadratic in the point r
  (Ixx = y^2 + z^2, Ixy = -x y, ...), so it lies in m x [min, max] of that quadratic over the box
  (sums of squares of intervals, products of intervals: exact bounds of each term).
The prior is the end-effector body's own theta plus that box; the nominal adds a point mass of
the mid mass at c (a payload the range allows, so nominal is inside the box).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.model import inertial


def _interval_times(a, b):
    """[lo, hi] of x y over x in a = [a0, a1], y in b = [b0, b1] (interval product)."""
    products = [a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]]
    return min(products), max(products)


def _square(a):
    """[min, max] of x^2 over x in a = [a0, a1]."""
    low = 0.0 if a[0] <= 0.0 <= a[1] else min(a[0] ** 2, a[1] ** 2)
    return low, max(a[0] ** 2, a[1] ** 2)


def payload_box(
    mass_range_kg: ArrayLike, centre_m: ArrayLike, half_extent_m: ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of the theta of any payload in the range, about the frame origin."""
    m_lo, m_hi = (float(x) for x in mass_range_kg)
    c, h = np.asarray(centre_m, float), np.asarray(half_extent_m, float)
    coord = [(c[i] - h[i], c[i] + h[i]) for i in range(3)]
    squares = [_square(a) for a in coord]
    per_unit_mass = list(coord)  # first moment / m
    for axis in range(3):  # Ixx, Iyy, Izz: the sum of the other two squares
        j, k = (i for i in range(3) if i != axis)
        per_unit_mass.append((squares[j][0] + squares[k][0], squares[j][1] + squares[k][1]))
    for i, j in ((0, 1), (1, 2), (0, 2)):  # Ixy, Iyz, Ixz = -integral of the product
        lo, hi = _interval_times(coord[i], coord[j])
        per_unit_mass.append((-hi, -lo))
    lower, upper = [m_lo], [m_hi]
    for lo, hi in per_unit_mass:
        ends = _interval_times((m_lo, m_hi), (lo, hi))
        lower.append(ends[0])
        upper.append(ends[1])
    return np.array(lower), np.array(upper)


def payload_range_prior(
    body_theta: ArrayLike, mass_range_kg: ArrayLike, *, centre_m: ArrayLike, half_extent_m: ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(nominal, lower, upper) of the end effector (its body plus any payload in the range)."""
    body = np.asarray(body_theta, float)
    lower, upper = payload_box(mass_range_kg, centre_m, half_extent_m)
    mid_mass = 0.5 * (float(mass_range_kg[0]) + float(mass_range_kg[1]))
    point = inertial.from_mass_com_inertia(mid_mass, centre_m, np.zeros((3, 3))) if mid_mass > 0 else np.zeros(10)
    return body + point, body + lower, body + upper
