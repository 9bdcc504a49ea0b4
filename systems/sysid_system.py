"""SysIdEstimator: Algorithm 1 as a Drake LeafSystem, refreshed every t_p as in Algorithm 2.

Thin wrapper: the math is in estimation/. Inputs: `state` (q, v; the plant's state port, 2n)
and `measured_torque` (n): the torque held over [t_k, t_k+1] as sampled at t_k (in the real
arm the sensor reads the command the plant applies over the next step). Outputs (whole robot,
14n each): `theta0` (θ_r nominal with the identified θ_e), `theta_lower`, `theta_upper` (θ_r box
with [θ_e]); `consistent` (1: every enclosure so far met the others; 0 from the first
inconsistency on, latched — the published box is then the last consistent one, and a planner
should stop planning); plus `update_info` [updates, last update wall time s, cond(Y), consistent].

Samples are stored at the sampling period (the plant rate) by a periodic PUBLISH event: it
sees what a logger sees, (x_k, τ_k) with τ_k applied over [t_k, t_k+1]. (A discrete update at
t_k would read the discrete MultibodyPlant's state already advanced to x_k+1, paired with the
command of t_k: tests/test_sysid_system.py.) At every multiple of t_p a discrete update hands
the new samples (the one at t_p included) to the incremental estimator (old segments are not
recomputed) and refreshes the outputs (discrete state). The sample buffer and the estimator
live in this system object (not in the Context): one simulation per instance at a time; an
initialization event resets them.
"""
from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

from .estimation import EstimatorError, EstimatorSettings, IncrementalEstimator


class SysIdEstimator(LeafSystem):
    def __init__(self, robot, scenario=None, settings: EstimatorSettings | None = None, sample_period_s=None,
                 update_period_s=None, prior=None, prior_nominal=None):
        super().__init__()
        if scenario is not None:
            settings = settings or EstimatorSettings.from_scenario(scenario)
            sample_period_s = sample_period_s or scenario.plant.time_step_s
            update_period_s = update_period_s or scenario.planner.replan_period_s
            ii = scenario.initial_interval
            prior = prior if prior is not None else (np.array(ii.lower, float), np.array(ii.upper, float))
            prior_nominal = prior_nominal if prior_nominal is not None else np.array(ii.nominal, float)
        self.robot = robot
        self.settings = settings or EstimatorSettings()
        self.sample_period_s = float(sample_period_s or 1e-3)
        self.update_period_s = float(update_period_s or 1.5)
        self.prior = prior
        self.prior_nominal = prior_nominal
        n = robot.n
        self.n = n
        self.DeclareVectorInputPort("state", 2 * n)
        self.DeclareVectorInputPort("measured_torque", n)
        self._reset()
        first = self._estimator.prior_estimate()
        self._groups = {
            "theta0": self.DeclareDiscreteState(BasicVector(first.theta)),
            "theta_lower": self.DeclareDiscreteState(BasicVector(np.nan_to_num(first.theta_lower, neginf=-1e30))),
            "theta_upper": self.DeclareDiscreteState(BasicVector(np.nan_to_num(first.theta_upper, posinf=1e30))),
            "update_info": self.DeclareDiscreteState(BasicVector(np.array([0.0, 0.0, np.inf, 1.0]))),
            "consistent": self.DeclareDiscreteState(BasicVector(np.array([1.0]))),
        }
        for name, index in self._groups.items():
            self.DeclareStateOutputPort(name, index)
        self.DeclareInitializationDiscreteUpdateEvent(self._on_initialize)
        self.DeclarePeriodicPublishEvent(self.sample_period_s, 0.0, self._on_sample)
        self.DeclarePeriodicDiscreteUpdateEvent(self.update_period_s, self.update_period_s, self._on_update)

    # -- state kept outside the Context ------------------------------------------------------------
    def _reset(self):
        self._estimator = IncrementalEstimator(self.robot, self.settings, self.prior, self.prior_nominal)
        self._buffer = []
        self._history = []

    def _write(self, discrete_state, est):
        groups = self._groups
        discrete_state.get_mutable_vector(groups["theta0"]).SetFromVector(est.theta)
        discrete_state.get_mutable_vector(groups["theta_lower"]).SetFromVector(np.nan_to_num(est.theta_lower, neginf=-1e30))
        discrete_state.get_mutable_vector(groups["theta_upper"]).SetFromVector(np.nan_to_num(est.theta_upper, posinf=1e30))
        info = [len(self._history), est.update_time_s, est.cond_Y, float(est.consistent)]
        discrete_state.get_mutable_vector(groups["update_info"]).SetFromVector(np.array(info, float))
        discrete_state.get_mutable_vector(groups["consistent"]).SetFromVector(np.array([float(est.consistent)]))

    def _on_initialize(self, context, discrete_state):
        self._reset()
        self._write(discrete_state, self._estimator.prior_estimate())
        return EventStatus.Succeeded()

    def _on_sample(self, context):
        x = self.get_input_port(0).Eval(context)
        tau = self.get_input_port(1).Eval(context)
        n = self.n
        self._buffer.append(np.concatenate([[context.get_time()], x[:n], x[n:2 * n], tau]))
        return EventStatus.Succeeded()

    def _on_update(self, context, discrete_state):
        t = context.get_time()
        if not self._buffer:
            return EventStatus.DidNothing()
        data = np.array(self._buffer)
        self._buffer = []
        n = self.n
        try:
            self._estimator.add(data[:, 0], data[:, 1:1 + n], data[:, 1 + n:1 + 2 * n], data[:, 1 + 2 * n:])
            est = self._estimator.update()
        except EstimatorError as err:  # not enough data yet (or bad samples): keep the outputs
            self._history.append({"t": t, "skipped": str(err)})
            return EventStatus.DidNothing()
        self._history.append({"t": t, "update_time_s": est.update_time_s, "cond_Y": est.cond_Y, "case": est.case,
                              "consistent": est.consistent, "nominal": est.theta_e.tolist(),
                              "lower": est.lower.tolist(), "upper": est.upper.tolist(), "message": est.message,
                              "problems": list(est.problems), "quadrature_ratio": est.quadrature_ratio})
        self._write(discrete_state, est)
        return EventStatus.Succeeded()

    # -- results for reports -----------------------------------------------------------------------
    @property
    def estimator(self):
        return self._estimator

    @property
    def update_times_s(self):
        return [h["update_time_s"] for h in self.history()]

    def history(self):
        """One dict per completed update (t, update_time_s, cond_Y, case, consistent, θ_e box)."""
        return [h for h in self._history if "skipped" not in h]

    @property
    def consistent(self):
        """False from the first update whose data contradicted a declared bound (latched)."""
        return self._estimator.consistent

    def events(self):
        """[{t, kind, detail}]: the first inconsistent update ("inconsistent_estimate") and
        updates whose quadrature term was large ("quadrature_unresolved")."""
        out, seen = [], False
        for h in self.history():
            if not h["consistent"] and not seen:
                seen = True
                out.append({"t": h["t"], "kind": "inconsistent_estimate", "detail": h["message"]})
            if h["quadrature_ratio"] > self.settings.quadrature_warn_ratio:
                out.append({"t": h["t"], "kind": "quadrature_unresolved",
                            "detail": f"quadrature bound up to {h['quadrature_ratio']:.2f} of a row's torque radius"})
        return out

    def final_estimate(self, ee_slice=None):
        """(θ_e0, lower, upper) of the last update, or the prior before the first one."""
        est = self._estimator.estimate or self._estimator.prior_estimate()
        return est.theta_e.copy(), est.lower.copy(), est.upper.copy()
