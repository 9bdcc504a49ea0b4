import numpy as np
from safesysid.systems.math import intervals
from safesysid.systems.math.intervals import Interval


def random_box(rng, shape, scale=3.0):
    c = rng.normal(scale=scale, size=shape)
    r = rng.uniform(0, 1.5, size=shape)
    return Interval(c - r, c + r)


def sample(box, rng):
    return box.lo + (box.hi - box.lo) * rng.uniform(size=box.shape)


def test_arithmetic_encloses_point_results():
    rng = np.random.default_rng(0)
    x, y = random_box(rng, 1000), random_box(rng, 1000)
    for _ in range(20):
        a, b = sample(x, rng), sample(y, rng)
        assert (x + y).contains(a + b).all() and (x - y).contains(a - b).all()
        assert (x * y).contains(a * b).all() and x.square().contains(a * a).all()
        assert intervals.sin(x).contains(np.sin(a)).all() and intervals.cos(x).contains(np.cos(a)).all()


def test_trig_is_tight_and_catches_extrema():
    box = Interval(np.array([0.0, 1.0, 3.0]), np.array([0.1, 2.0, 3.3]))
    s = intervals.sin(box)
    assert s.hi[1] == 1.0  # pi/2 inside [1, 2]
    assert np.all(s.width < [0.11, 0.17, 0.31])
    assert intervals.cos(Interval(3.0, 3.3)).lo == -1.0


def test_matmul_is_the_exact_hull():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(4, 6))
    x = random_box(rng, 6)
    y = intervals.matmul(a, x)
    corners = [sample(x, rng) for _ in range(200)]
    assert all(y.contains(a @ c).all() for c in corners)
    # attained: the vertex that maximizes row 0 reaches the upper bound
    vertex = np.where(a[0] > 0, x.hi, x.lo)
    assert np.isclose(a[0] @ vertex, y.hi[0], rtol=1e-12)


def test_intersection_and_empty():
    a, b = Interval(0.0, 2.0), Interval(1.0, 3.0)
    c = a.intersect(b)
    assert (c.lo, c.hi) == (1.0, 2.0)
    import pytest

    with pytest.raises(ValueError):
        Interval(0.0, 1.0).intersect(Interval(2.0, 3.0))


def test_sums_and_products_contain_the_exact_value_in_rational_arithmetic():
    """Interval.sum and matmul allow for the float sums' rounding (intervals.dot_rounding): numpy
    sums 100 copies of 1/3 to 1.59 ulp above the exact value (one ulp outward is not enough);
    random rows of length 98 (the controller's) and 2000."""
    from fractions import Fraction

    from safesysid.systems.math.intervals import matmul

    third = Interval(np.full(100, 1 / 3))
    exact = 100 * Fraction(1 / 3)
    total = third.sum()
    assert Fraction(float(total.lo)) <= exact <= Fraction(float(total.hi))
    rng = np.random.default_rng(4)
    for k in (98, 2000):
        a = rng.uniform(-1, 1, (3, k))
        lo = rng.uniform(-2, 2, k)
        box = Interval(lo, lo + rng.uniform(0, 1e-9, k) * (rng.random(k) < 0.5))
        hull = matmul(a, box)
        for x in (box.lo, box.hi):  # the exact products at the corners lie inside the hull
            for row, lo_k, hi_k in zip(a, hull.lo, hull.hi):
                value = sum(Fraction(ai) * Fraction(xi) for ai, xi in zip(row, x))
                assert Fraction(lo_k) <= value <= Fraction(hi_k)
