"""SysIdEstimator: Algorithm 1 as a Drake LeafSystem, refreshed every t_p as in Algorithm 2.

Thin wrapper: the math is in estimation/. Inputs: `state` (q, v; the plant's state port, 2n)
and `measured_torque` (n): the torque held over [t_k, t_k+1] as sampled at t_k (in the real
arm the sensor reads the command the plant applies over the next step). Outputs (whole robot,
14n each): `theta0` (θ_r nominal with the identified θ_e), `theta_lower`, `theta_upper` (θ_r box
with [θ_e]); `consistent` (1: every enclosure so far met the others; 0 from the first
inconsistency on, latched — the published box is then the last consistent one, and a planner
should stop planning); plus `update_info` [updates, last update wall time s, cond(Y), consistent].

Input sanitation (`_accept`): a sample with a NaN/inf, a duplicate time stamp, or a time already
handed to the estimator is rejected; a late one still in the buffer is put in place; a gap
is noted (the estimator's segments never span it). None of these make the data violate a
declared bound, so `consistent` is not touched; each is an event. Optional input `samples`
(systems/plant/faults.py packets of timestamped samples) replaces state + measured_torque when connected.

Everything a run accumulates lives in the Context (abstract state `SysIdState`: the incremental
estimator, the samples since the last update, the update history), so two contexts of one diagram
never share data. One periodic unrestricted update at the sampling period (the plant rate) stores
(x_k, τ_k), τ_k applied over [t_k, t_k+1]: unrestricted updates run before the discrete ones at t_k,
so it sees what a logger sees (a discrete update would read the discrete MultibodyPlant's state
already advanced to x_k+1, paired with the command of t_k: tests/test_sysid_system.py). At every
multiple of t_p the same event hands the new samples (the one at t_p included) to the incremental
estimator (old segments are not recomputed) and refreshes the outputs (discrete state).
History, consistency, events and the final estimate are functions of the context.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, replace

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, Context, EventStatus, LeafSystem
from safesysid.systems.estimation import Estimate, EstimatorError, EstimatorSettings, IncrementalEstimator
from safesysid.systems.estimation.packets import packet_size, unpack
from safesysid.systems.model.inertial import NAMES
from safesysid.systems.model.robot_model import RobotModel

# summary.json estimate fields besides nominal/lower/upper: the data-driven box before physical
# pruning, the paper's first-order interval on the same data, and what A5 rested on
# (systems/estimation Estimate).
ESTIMATE_EXTRA = ("data_lower", "data_upper", "first_order_lower", "first_order_upper", "quadrature_assumption")


def estimate_update(
    estimator: IncrementalEstimator, data: np.ndarray, n: int
) -> tuple[IncrementalEstimator, Estimate | EstimatorError]:
    """Algorithm 1 on the rows [t, q, v, τ] of `data`, on a copy of `estimator` (the stored one is
    shared): (the advanced copy, its Estimate or the EstimatorError that skipped the update). The
    Estimate's update_time_s covers both the new rows (add: the quadrature certificate's cost sits
    there) and the update."""
    estimator = copy.deepcopy(
        estimator, {id(estimator.robot): estimator.robot, id(estimator.settings): estimator.settings}
    )
    try:
        start = time.perf_counter()
        estimator.add(data[:, 0], data[:, 1 : 1 + n], data[:, 1 + n : 1 + 2 * n], data[:, 1 + 2 * n :])
        est = estimator.update()
        est.update_time_s = time.perf_counter() - start
        return estimator, est
    except EstimatorError as err:
        return estimator, err


@dataclass(frozen=True)
class SysIdState:
    """The estimator's run data. Immutable once stored: an update replaces it with a new one
    built on a copy of the estimator, so Drake's state copies may share it."""

    estimator: IncrementalEstimator
    samples: tuple[np.ndarray, ...] = ()  # rows [t, q (n), v (n), τ (n)] since the last update
    history: tuple[dict, ...] = ()  # one dict per update instant (a skipped one has "skipped")
    handed_t: float = -np.inf  # time of the last sample handed to the estimator
    input_issues: tuple = ()  # (t, kind, detail) of each sample the input sanitation acted on

    def __deepcopy__(self, memo):
        return self


class SysIdEstimator(LeafSystem):
    def __init__(
        self,
        robot: RobotModel,
        settings: EstimatorSettings,
        sample_period_s: float,
        update_period_s: float,
        prior: tuple[np.ndarray, np.ndarray],
        prior_nominal: np.ndarray,
        *,
        stop_time_s: float = np.inf,
        step_period_s: float | None = None,
    ) -> None:
        """settings: the estimator's (EstimatorSettings.from_scenario); sample_period_s: the plant
        step; update_period_s: t_p; prior: (lower, upper) of θ_e; prior_nominal: θ_e published
        before the first update; stop_time_s: after it the estimator neither samples nor updates
        (the task phase: the controller has latched its box); step_period_s: how often the samples
        arrive (default: every sample period; over LCM with the controller beside the arm, in
        packets every arm.run_step_ms). app/online.py make_estimator_system takes them from a scenario."""
        super().__init__()
        self.robot = robot
        self.stop_time_s = float(stop_time_s)
        self.settings = settings
        self.sample_period_s = float(sample_period_s)
        self.update_period_s = float(update_period_s)
        self.step_period_s = self.sample_period_s if step_period_s is None else float(step_period_s)
        self._steps_per_update = int(round(self.update_period_s / self.step_period_s))
        if abs(self._steps_per_update * self.step_period_s - self.update_period_s) > 1e-9 * self.update_period_s:
            raise ValueError(
                f"estimator update period {self.update_period_s} s is not a multiple of the step "
                f"period {self.step_period_s} s"
            )
        self.prior = prior
        self.prior_nominal = prior_nominal
        n = robot.n
        self.n = n
        self._state_input = self.DeclareVectorInputPort("state", 2 * n)
        self._torque_input = self.DeclareVectorInputPort("measured_torque", n)
        # Optional: timestamped samples as delivered by a (faulty) link, faults.pack packets;
        # when connected it replaces state + measured_torque.
        self._samples_input = self.DeclareVectorInputPort("samples", packet_size(n))
        initial = self._initial_state()
        self._run = self.DeclareAbstractState(AbstractValue.Make(initial))
        first = initial.estimator.prior_estimate()
        self._groups = {
            "theta0": self.DeclareDiscreteState(BasicVector(first.theta)),
            "theta_lower": self.DeclareDiscreteState(BasicVector(np.nan_to_num(first.theta_lower, neginf=-1e30))),
            "theta_upper": self.DeclareDiscreteState(BasicVector(np.nan_to_num(first.theta_upper, posinf=1e30))),
            "update_info": self.DeclareDiscreteState(BasicVector(np.array([0.0, 0.0, np.inf, 1.0]))),
            "consistent": self.DeclareDiscreteState(BasicVector(np.array([1.0]))),
        }
        for name, index in self._groups.items():
            self.DeclareStateOutputPort(name, index)
        self.DeclareInitializationUnrestrictedUpdateEvent(self._on_initialize)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.step_period_s, 0.0, self._on_sample)

    def _initial_state(self):
        return SysIdState(
            IncrementalEstimator(self.robot, settings=self.settings, prior=self.prior, prior_nominal=self.prior_nominal)
        )

    def _write(self, state, est, updates):
        discrete, groups = state.get_mutable_discrete_state(), self._groups
        discrete.get_mutable_vector(groups["theta0"]).SetFromVector(est.theta)
        discrete.get_mutable_vector(groups["theta_lower"]).SetFromVector(np.nan_to_num(est.theta_lower, neginf=-1e30))
        discrete.get_mutable_vector(groups["theta_upper"]).SetFromVector(np.nan_to_num(est.theta_upper, posinf=1e30))
        info = [updates, est.update_time_s, est.cond_Y, float(est.consistent)]
        discrete.get_mutable_vector(groups["update_info"]).SetFromVector(np.array(info, float))
        discrete.get_mutable_vector(groups["consistent"]).SetFromVector(np.array([float(est.consistent)]))

    # -- events ------------------------------------------------------------------------------------
    def _on_initialize(self, context, state):
        initial = self._initial_state()
        state.get_mutable_abstract_state(int(self._run)).set_value(initial)
        self._write(state, initial.estimator.prior_estimate(), 0)
        return EventStatus.Succeeded()

    def _on_sample(self, context, state):
        t = context.get_time()
        if t > self.stop_time_s + 1e-12:
            return EventStatus.DidNothing()
        run = self._get(context)
        for row in self._arrived(context):
            run = self._accept(run, row)
        step = int(round(t / self.step_period_s))
        if step > 0 and step % self._steps_per_update == 0:
            run = self._update(t, run, state)
        state.get_mutable_abstract_state(int(self._run)).set_value(run)
        return EventStatus.Succeeded()

    def _arrived(self, context):
        """The rows [t, q, v, τ] that reach the estimator at this step."""
        if self._samples_input.HasValue(context):
            return unpack(self._samples_input.Eval(context), self.n)
        x = self._state_input.Eval(context)
        return [np.concatenate([[context.get_time()], x, self._torque_input.Eval(context)])]

    def _accept(self, run: SysIdState, row) -> SysIdState:
        """Input sanitation: the samples handed to the estimator are finite and strictly increasing
        in time; a bad one is rejected, a late one put in place. Each action is an input issue (events)."""
        t = float(row[0])

        def issue(kind, detail, samples=run.samples):
            return replace(run, samples=samples, input_issues=run.input_issues + ((t, kind, detail),))

        if not np.all(np.isfinite(row)):
            return issue("sample_nonfinite", "rejected (NaN or inf)")
        last = run.samples[-1][0] if run.samples else run.handed_t
        if t > last:
            return replace(run, samples=run.samples + (row,))
        if t <= run.handed_t:
            return issue("sample_out_of_order", "rejected (older than the data already estimated on)")
        times = np.array([r[0] for r in run.samples])
        k = int(np.searchsorted(times, t))
        if k < len(times) and times[k] == t:
            same = np.array_equal(run.samples[k], row)
            return issue("sample_duplicate", "rejected" + ("" if same else " (its values differ from the first)"))
        return issue("sample_out_of_order", "put in place", run.samples[:k] + (row,) + run.samples[k:])

    def _update(self, t, run: SysIdState, state) -> SysIdState:
        """Algorithm 1 on the new samples, on a copy of the estimator (the stored one is shared)."""
        if not run.samples:  # every sample of the period was lost or rejected
            return replace(run, history=run.history + ({"t": t, "skipped": "no valid samples"},))
        run, data = self._take(run)
        return self._apply(t, run, *estimate_update(run.estimator, data, self.n), state)

    def _take(self, run: SysIdState) -> tuple[SysIdState, np.ndarray]:
        """The run without its new samples (their gaps noted), and those samples as rows."""
        data = np.array(run.samples)
        times = data[:, 0] if np.isinf(run.handed_t) else np.concatenate([[run.handed_t], data[:, 0]])
        gaps = times[1:][np.diff(times) > 1.5 * self.sample_period_s]
        detail = "follow a gap (the estimator's segments never span one)"
        issues = run.input_issues + tuple((float(g), "sample_gap", detail) for g in gaps)
        return replace(run, samples=(), handed_t=data[-1, 0], input_issues=issues), data

    def _apply(self, t, run: SysIdState, estimator, outcome, state) -> SysIdState:
        """An update's outcome (an Estimate, or the EstimatorError that skipped it) into the run."""
        if isinstance(outcome, EstimatorError):  # not enough data yet (or bad samples): keep the outputs
            return replace(run, estimator=estimator, history=run.history + ({"t": t, "skipped": str(outcome)},))
        est = outcome
        record = {
            "t": t,
            "update_time_s": est.update_time_s,
            "cond_Y": est.cond_Y,
            "case": est.case,
            "consistent": est.consistent,
            "nominal": est.theta_e.tolist(),
            "lower": est.lower.tolist(),
            "upper": est.upper.tolist(),
            # the data's own least-squares centre and this update's enclosure (Theorem 2 box)
            "ls_centre": np.asarray(est.theta_ls).tolist(),
            "update_lower": np.asarray(est.update_lower).tolist(),
            "update_upper": np.asarray(est.update_upper).tolist(),
            # summary.json extras: the data-driven box before physical pruning, the paper's interval
            **{k: v for k, v in est.to_json().items() if k in ESTIMATE_EXTRA},
            "message": est.message,
            "problems": list(est.problems),
            "quadrature_ratio": est.quadrature_ratio,
        }
        new = replace(run, estimator=estimator, history=run.history + (record,))
        self._write(state, est, len(self.history_of(new)))
        return new

    def _get(self, context) -> SysIdState:
        return context.get_abstract_state(int(self._run)).get_value()

    @staticmethod
    def history_of(run: SysIdState) -> list[dict]:
        return [h for h in run.history if "skipped" not in h]

    # -- results for reports (functions of this system's context) ---------------------------------
    def estimator(self, context: Context) -> IncrementalEstimator:
        return self._get(context).estimator

    def samples(self, context: Context) -> np.ndarray:
        """Samples not yet handed to the estimator: (N, 1 + 3 n) rows [t, q, v, τ]."""
        return np.array(self._get(context).samples).reshape(-1, 1 + 3 * self.n)

    def update_times_s(self, context: Context) -> list[float]:
        return [h["update_time_s"] for h in self.history(context)]

    def skipped(self, context: Context) -> list[dict]:
        """One dict per update instant that gave no estimate: {t, skipped: why}."""
        return [h for h in self._get(context).history if "skipped" in h]

    def history(self, context: Context) -> list[dict]:
        """One dict per completed update (t, update_time_s, cond_Y, case, consistent, θ_e box)."""
        return self.history_of(self._get(context))

    def consistent(self, context: Context) -> bool:
        """False from the first update whose data contradicted a declared bound (latched)."""
        return self._get(context).estimator.consistent

    def events(self, context: Context) -> list[dict]:
        """[{t, kind, detail}]: the first inconsistent update ("inconsistent_estimate"), updates
        whose quadrature term was large ("quadrature_unresolved"), and what the input sanitation
        did (sample_nonfinite, sample_duplicate, sample_out_of_order, sample_gap; one per kind)."""
        out, seen = [], False
        for h in self.history(context):
            if not h["consistent"] and not seen:
                seen = True
                out.append({"t": h["t"], "kind": "inconsistent_estimate", "detail": h["message"]})
            if h["quadrature_ratio"] > self.settings.quadrature_warn_ratio:
                out.append(
                    {
                        "t": h["t"],
                        "kind": "quadrature_unresolved",
                        "detail": f"quadrature bound up to {h['quadrature_ratio']:.2f} of a row's torque radius",
                    }
                )
        return out + self._prior_events(self.history(context)) + self._input_events(self._get(context).input_issues)

    def _prior_events(self, history):
        """The first update whose least-squares centre lies outside the prior (A2) in a parameter
        the data determine better than the prior (enclosure narrower than the prior): not a proof
        that A2 fails (the data's enclosure still meets the prior, or `consistent` would be off),
        but the published bound there is the prior's assumption, not the data's."""
        if self.prior is None:
            return []
        lo, hi = (np.asarray(x, float) for x in self.prior)
        for h in history:
            centre = np.asarray(h.get("ls_centre", ()), float)
            if h["consistent"] and len(centre):
                # only where the data pin the parameter down better than the prior does
                determined = np.asarray(h["update_upper"]) - np.asarray(h["update_lower"]) < hi - lo
                out = np.flatnonzero(determined & ((centre < lo) | (centre > hi)))
                if len(out):
                    names = ", ".join(f"{NAMES[k]} = {centre[k]:.4g} (prior [{lo[k]:.4g}, {hi[k]:.4g}])" for k in out)
                    detail = (
                        f"the data's best fit is outside the prior: {names}; the published bound there is the prior's"
                    )
                    return [{"t": h["t"], "kind": "estimate_outside_prior", "detail": detail}]
        return []

    @staticmethod
    def _input_events(issues):
        """One event per kind and detail of input issue: its first time and how many samples."""
        first = {}
        for t, kind, detail in issues:
            first.setdefault((kind, detail), [t, 0])[1] += 1
        return [
            {"t": t, "kind": kind, "detail": f"{count} sample(s) {detail}, the first at {t:.3f} s"}
            for (kind, detail), (t, count) in first.items()
        ]

    def final_estimate(self, context: Context) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(θ_e0, lower, upper) of the last update, or the prior before the first one."""
        estimator = self._get(context).estimator
        est = estimator.estimate or estimator.prior_estimate()
        return est.theta_e.copy(), est.lower.copy(), est.upper.copy()
