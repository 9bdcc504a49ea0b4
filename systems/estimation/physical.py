"""Prior physical knowledge of the payload: pruning an interval box with the density-realizability
LMI (Wensing, Kim & Slotine 2017, "Linear matrix inequalities for physically consistent inertial
parameter identification").

For a body of mass density ρ, the pseudo-inertia J(θ) = ∫ [x; 1][x; 1]ᵀ ρ dV (linear in θ,
`inertial.pseudo_inertia`) is ⪰ 0; if the body lies inside the region {x : [x; 1]ᵀ Q [x; 1] ≥ 0}
(an ellipsoid, or a slab: a degenerate ellipsoid), then tr(J Q) = ∫ [x; 1]ᵀ Q [x; 1] ρ dV ≥ 0. A
box is the intersection of three slabs, so it gives three such constraints.

The identified body θ_e is the end-effector link (gripper) plus the payload. The volume bounds the
payload only, θ_p = θ_e − θ_g, with the gripper's own θ_g in its declared box (nominal ± the
robot-parameter box, assumption A1 extended to the gripper). Without a volume only J(θ_e) ⪰ 0 is
used (assumption A2: the payload is physically consistent).

Pruning: each parameter's new bound is min / max of θ_e[i] over {box, LMIs}, an SDP. It is solved
from OUTSIDE by cutting planes: J ⪰ 0 ⇔ vᵀJ(θ)v ≥ 0 for all v, and any finite set of v gives a
linear relaxation, so every LP bound of the loop (certified by weak duality,
`enclosure.certified_lp_min`) is already a rigorous outer bound; the loop only tightens it (a cut
at the eigenvector of each negative eigenvalue of the LP's minimiser). No SDP solver answer has to
be trusted.
"""

from __future__ import annotations

import numpy as np
from safesysid.systems.model import inertial

from .enclosure import certified_lp_min
from .settings import BoundingVolume

MAX_KEPT_CUTS = 200  # cutting planes carried to the next call (the LPs stay small)
_J_BASIS = np.stack([inertial.pseudo_inertia(e) for e in np.eye(10)])  # (10, 4, 4): J(θ) = Σ θ_j J_j


def _linear_form(M):
    """Row g with g·θ = tr(J(θ) M) (M symmetric)."""
    return np.einsum("jkl,kl->j", _J_BASIS, M)


def prune_box(
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    volume: BoundingVolume | None = None,
    gripper: tuple[np.ndarray, np.ndarray] | None = None,
    max_cuts: int = 5,
    tol: float = 1e-10,
    cuts: list | None = None,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Outer bound of {θ_e ∈ [lo, hi] : J(θ_e) ⪰ 0, and with a volume J(θ_p) ⪰ 0, tr(J(θ_p) Q) ≥ 0}.

    θ_p = θ_e − θ_g, θ_g ∈ gripper = (lower, upper) (None: the volume contains the whole θ_e).
    cuts: a list the cutting planes found are appended to and reused from (they hold for every box:
    an estimator passes the same list at every update, and later updates need fewer LPs).
    Returns (lo, hi, feasible): each bound is a certified LP bound of a cutting-plane relaxation,
    intersected with the input; feasible False when the LP proves the set empty (the data box
    contradicts the physical knowledge).
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    with_g = volume is not None and gripper is not None
    nv = 20 if with_g else 10
    lo_x = np.concatenate([lo, gripper[0]]) if with_g else lo.copy()
    hi_x = np.concatenate([hi, gripper[1]]) if with_g else hi.copy()
    # Each constraint is g·θ_body ≥ 0 on a body: θ_e (index 0) or θ_p = θ_e − θ_g (index 1).
    to_x = [np.hstack([np.eye(10), np.zeros((10, 10))]) if with_g else np.eye(10)]
    to_x.append(np.hstack([np.eye(10), -np.eye(10)]) if with_g else np.eye(10))
    rows = [(0, _linear_form(np.outer(e, e))) for e in np.eye(4)]  # diagonal of J ≥ 0 to start
    if volume is not None:
        rows += [(1, _linear_form(Q)) for Q in volume.forms()]
        if with_g:
            rows += [(1, _linear_form(np.outer(e, e))) for e in np.eye(4)]
    cuts = [] if cuts is None else cuts
    rows += cuts
    bodies = [0, 1] if (volume is not None and with_g) else [0]

    def a_ub():
        return np.array([-g @ to_x[b] for b, g in rows])

    out_lo, out_hi = lo.copy(), hi.copy()
    for i in range(10):
        for sign in (1.0, -1.0):
            c = np.zeros(nv)
            c[i] = sign
            best = -np.inf
            for _ in range(max_cuts):
                sol = []
                A = a_ub()
                status, bound = certified_lp_min(c, A, np.zeros(len(A)), lo_x, hi_x, solution=sol)
                if status == "infeasible":
                    return lo, hi, False
                if status != "ok":
                    break
                best = max(best, bound)
                added = False
                for b in bodies:
                    lam, vec = np.linalg.eigh(inertial.pseudo_inertia(to_x[b] @ sol[0]))
                    scale = max(np.abs(lam).max(), 1e-12)
                    for k in np.flatnonzero(lam < -tol * scale):
                        cut = (b, _linear_form(np.outer(vec[:, k], vec[:, k])))
                        rows.append(cut)
                        cuts.append(cut)
                        added = True
                if not added:
                    break
            if np.isfinite(best):
                if sign > 0:
                    out_lo[i] = max(out_lo[i], best)
                else:
                    out_hi[i] = min(out_hi[i], -best)
    del cuts[:-MAX_KEPT_CUTS]
    if np.any(out_lo > out_hi):
        return lo, hi, False
    return out_lo, out_hi, True
