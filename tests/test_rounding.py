"""One rounding rule for float sums and dot products: `intervals.dot_rounding(k)`.

A hand-written eps factor next to a sum or a dot product is how a fixed 8·eps came to widen a
98-term product (interval_dynamics.torque_bound) and an LP bound came to be padded relative to a
sum that cancels (estimation/enclosure.certified_lp_min): the scan below finds such factors
anywhere outside intervals.py; the few kept are listed with the reason they are not a sum's bound.
"""

import re
from fractions import Fraction
from pathlib import Path

import numpy as np
from safesysid.systems.estimation.enclosure import _lp_bound_rounding

ROOT = Path(__file__).resolve().parents[1]
EPS_TOKEN = re.compile(r"finfo\([^)]*\)\.eps|\bEPS\b|\b_U\b|\b_UP\b")
SUM_OR_DOT = re.compile(r"@|\bsum\(|einsum\(|\bdot\(|matmul\(")
# (file, a fragment of the line): why its eps factor is not a k-term sum's rounding bound.
KEPT = {
    (
        "systems/planner/affine_forms.py",
        "(self.r.sum(axis) + rounding * m) * _UP",
    ): "the sum's error is dot_rounding(k); _UP rounds the one addition of that error to r",
    (
        "systems/controller/armour.py",
        "np.sqrt(w_bar @ w_bar)) * _UP",
    ): "the control law (bit for bit with the compiled kernel): a 7-term norm, its rounding 2.3 eps < 8 eps",
    (
        "systems/estimation/enclosure.py",
        "4 * EPS * (S * n) * (np.abs(L) @ np.abs(Y2))",
    ): "4 k eps >= 2 dot_rounding(k) for k >= 2: the product L Y2 and the rounding of |L| |Y2| itself",
    (
        "systems/estimation/enclosure.py",
        "64 * EPS * (S * n + Dr2.shape[1])",
    ): "64 k eps >= dot_rounding(k) for every product in the hull's centre and radii (one pad for all of them)",
}


def eps_factors_next_to_sums(root=ROOT):
    """(file, line number, line) of every eps factor on a line with a sum or a dot product."""
    for path in sorted([*root.glob("systems/**/*.py"), *root.glob("app/**/*.py")]):
        rel = path.relative_to(root).as_posix()
        if rel == "systems/math/intervals.py":  # the helper itself
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#")[0]
            if EPS_TOKEN.search(code) and SUM_OR_DOT.search(code):
                yield rel, number, line.strip()


def test_no_hand_written_eps_factor_widens_a_sum_outside_dot_rounding():
    found = list(eps_factors_next_to_sums())
    unexplained = [f for f in found if not any(f[0] == path and frag in f[2] for path, frag in KEPT)]
    assert not unexplained, "use intervals.dot_rounding(k) for a k-term sum or product:\n" + "\n".join(
        f"{path}:{number}: {line}" for path, number, line in unexplained
    )


def test_the_scan_finds_a_hand_written_factor(tmp_path):
    """The scan has power: the fixed factor torque_bound used before is found."""
    fake = tmp_path / "systems"
    fake.mkdir()
    (fake / "x.py").write_text("err = 8 * np.finfo(float).eps * (wp.mag @ np.abs(theta0))\n")
    assert [f[:2] for f in eps_factors_next_to_sums(tmp_path)] == [("systems/x.py", 1)]


def test_lp_bound_pad_covers_the_rounding_where_the_reduced_costs_cancel():
    """certified_lp_min's bound Σ min(r l, r u) − yᵀb with r = c + Aᵀy: where r cancels (|r| << |c|)
    its rounding scales with |c| + |A|ᵀ|y|. Against exact rational arithmetic, the bound minus its pad
    never exceeds the exact value; the former pad (1e-12 of |r|·|x| + |y|·|b|) did, by up to 4.9e-11."""
    rng = np.random.default_rng(0)
    worst_old = worst = -np.inf
    for _ in range(150):
        n, m = 6, 8
        A = rng.normal(size=(m, n)) * 10.0 ** rng.integers(-3, 4, (m, 1))
        y = np.abs(rng.normal(size=m))
        c = -(A.T @ y) * (1 + rng.choice([0, 1e-15, -1e-15], n))  # r cancels to a few ulp of |c|
        b = rng.normal(size=m)
        lo, hi = -rng.uniform(1, 100, n), rng.uniform(1, 100, n)
        r = c + A.T @ y
        value = Fraction(np.sum(np.minimum(r * lo, r * hi)) - y @ b)
        r_exact = [Fraction(c[j]) + sum(Fraction(A[i, j]) * Fraction(y[i]) for i in range(m)) for j in range(n)]
        exact = sum(min(r_exact[j] * Fraction(lo[j]), r_exact[j] * Fraction(hi[j])) for j in range(n)) - sum(
            Fraction(y[i]) * Fraction(b[i]) for i in range(m)
        )
        x_mag = np.maximum(np.abs(lo), np.abs(hi))
        old = 1e-12 * (np.abs(r) @ x_mag + y @ np.abs(b)) + 1e-300
        worst_old = max(worst_old, float(value - Fraction(old) - exact))
        worst = max(worst, float(value - Fraction(_lp_bound_rounding(c, A, b, y, r, x_mag)) - exact))
    assert worst <= 0.0
    assert worst_old > 0.0  # the case has power: the former pad fell short
