"""The LeafSystems of the simulated arm's signal path (station.py's add_real_arm wires them; the
module docstring there gives the path and each effect): joint friction, the motor-side encoders of
quasi-static elasticity, the elastic transmission of dynamic elasticity, noisy velocities, a
whole-step delay and the torque sensor."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, Context, LeafSystem


class JointFriction(LeafSystem):
    """Generalized force on the joints: applied torque minus joint friction (the model's law
    Fc tanh(v / vs) + Fv v + beta, sign(v) when vs = 0; plus plant.effects' load-dependent
    mu |tau| and Stribeck Fs exp(-(v / vs_s)^2) terms with the same sign law)."""

    def __init__(self, coulomb, viscous, offset, smoothing, *, load_mu=0.0, stribeck=0.0, stribeck_vs=1.0):
        super().__init__()
        self.coulomb, self.viscous, self.offset = (np.asarray(x, float) for x in (coulomb, viscous, offset))
        self.smoothing = float(smoothing)
        self.load_mu, self.stribeck = np.asarray(load_mu, float), np.asarray(stribeck, float)
        self.stribeck_vs = float(stribeck_vs)
        n = self.n = len(self.coulomb)
        self.applied = self.DeclareVectorInputPort("applied_torque", n)
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.DeclareVectorOutputPort(
            "actuation", BasicVector(n), self._calc, prerequisites_of_calc={self.all_input_ports_ticket()}
        )

    def _calc(self, context, output):
        v = self.state.Eval(context)[self.n :]
        law = np.tanh(v / self.smoothing) if self.smoothing > 0 else np.sign(v)
        applied = self.applied.Eval(context)
        extra = (self.load_mu * np.abs(applied) + self.stribeck * np.exp(-((v / self.stribeck_vs) ** 2))) * law
        output.SetFromVector(applied - (self.coulomb * law + self.viscous * v + self.offset) - extra)


class SeriesElasticEncoders(LeafSystem):
    """Motor-side encoders: q + tau_s / K (quasi-static series elasticity), v unchanged. tau_s is
    the transmitted torque of the plant step that just ended (one step behind, held in a state
    pushed by a periodic unrestricted update as StepDelay does): the deflection the last applied
    torque left in the spring. Reading the current step's torque would close an algebraic loop
    through the controller (encoders -> command -> transmitted torque -> encoders). The first
    reading holds the torque transmitted at initialization (with the encoders reading q). Stable
    under feedback while K exceeds the controller's position gain (station.py)."""

    def __init__(self, stiffness, time_step):
        super().__init__()
        self.stiffness = np.asarray(stiffness, float)
        n = self.n = len(self.stiffness)
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.transmitted = self.DeclareVectorInputPort("transmitted_torque", n)
        self._last = self.DeclareDiscreteState(n)  # transmitted torque of the last plant step
        self.DeclareVectorOutputPort(
            "measured_state", BasicVector(2 * n), self._calc, {self.state.ticket(), self.xd_ticket()}
        )
        self.DeclareInitializationUnrestrictedUpdateEvent(self._hold)
        self.DeclarePeriodicUnrestrictedUpdateEvent(time_step, 0.0, self._hold)

    def _calc(self, context, output):
        x = self.state.Eval(context).copy()
        x[: self.n] += context.get_discrete_state(self._last).get_value() / self.stiffness
        output.SetFromVector(x)

    def _hold(self, context, state):
        state.get_mutable_discrete_state(self._last).SetFromVector(self.transmitted.Eval(context))


class ElasticTransmission(LeafSystem):
    """Series-elastic joints, dynamically (Spong's flexible-joint model): per joint a motor of
    inertia B (the armature) drives the link through a spring K and a damper D,

        B w_m' = drive - tau_s,   tau_s = K (theta_m - q) + D (w_m - v),   M(q) v' + C + g = tau_s,

    drive = applied torque minus the friction at the motor's velocity (JointFriction fed with
    `motor_state`). Discrete state (theta_m, w_m), symplectic Euler at the plant's step, in step
    with the plant's own update: both are unrestricted updates, so both read the state at the
    start of the step (a discrete update would run after the plant stepped). The damper's
    -D v on the link is the plant's joint damping (implicit in Drake's discrete solver: a light
    link would make it unstable here), so `link_actuation` = K (theta_m - q) + D w_m."""

    def __init__(self, stiffness, damping, inertia, time_step):
        super().__init__()
        self.stiffness, self.damping, self.inertia = (np.asarray(x, float) for x in (stiffness, damping, inertia))
        n = self.n = len(self.stiffness)
        self.h = float(time_step)
        self.drive = self.DeclareVectorInputPort("drive", n)
        self.link_state = self.DeclareVectorInputPort("link_state", 2 * n)
        self._motor = motor = self.DeclareDiscreteState(2 * n)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.h, 0.0, self._step)
        self.DeclareStateOutputPort("motor_state", motor)
        self.DeclareVectorOutputPort("link_actuation", BasicVector(n), self._calc)

    def spring_torque(self, motor: np.ndarray, link: np.ndarray) -> np.ndarray:
        n = self.n
        return self.stiffness * (motor[:n] - link[:n]) + self.damping * (motor[n:] - link[n:])

    def _calc(self, context, output):
        motor, link = context.get_discrete_state_vector().value(), self.link_state.Eval(context)
        output.SetFromVector(self.spring_torque(motor, link) + self.damping * link[self.n :])

    def _step(self, context, state):
        motor = context.get_discrete_state_vector().value()
        tau_s = self.spring_torque(motor, self.link_state.Eval(context))
        w = motor[self.n :] + self.h * (self.drive.Eval(context) - tau_s) / self.inertia
        state.get_mutable_discrete_state(self._motor).SetFromVector(np.concatenate([motor[: self.n] + self.h * w, w]))

    def set_equilibrium(self, context: Context, q: np.ndarray, v: np.ndarray, *, link_torque: np.ndarray) -> None:
        """Motor state that carries `link_torque` (the link's gravity at rest) with the link at (q, v)."""
        context.SetDiscreteState(np.concatenate([q + link_torque / self.stiffness, v]))


class NoisyVelocity(LeafSystem):
    """Encoders whose velocity reading is v + bound (2 u - 1), u the `unit_noise` input (n draws of
    U(0, 1) per step); positions unchanged."""

    def __init__(self, n, bound):
        super().__init__()
        self.n, self.bound = n, float(bound)
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.unit_noise = self.DeclareVectorInputPort("unit_noise", n)
        self.DeclareVectorOutputPort("measured_state", BasicVector(2 * n), self._calc)

    def _calc(self, context, output):
        x = self.state.Eval(context).copy()
        x[self.n :] += self.bound * (2.0 * self.unit_noise.Eval(context) - 1.0)
        output.SetFromVector(x)


class StepDelay(LeafSystem):
    """The input `steps` plant steps late, zero before: a FIFO pushed by a periodic unrestricted
    update. Drake's discrete MultibodyPlant (1.51) steps in the unrestricted phase too, so each
    entry is the value of the context the plant's own step read (the torque it received, what
    the estimator and the referee sample). DiscreteTimeDelay and ZeroOrderHold sample in the
    discrete phase, after the plant has stepped: a state-feedback torque re-evaluated at the
    next state, never applied (tests/test_plant_friction.py test_late_*)."""

    def __init__(self, time_step: float, steps: int, n: int) -> None:
        super().__init__()
        self.n = n
        self.input = self.DeclareVectorInputPort("input", n)
        self._fifo = self.DeclareDiscreteState(steps * n)  # oldest first
        self.DeclareVectorOutputPort("delayed", BasicVector(n), self._calc, {self.xd_ticket()})
        self.DeclarePeriodicUnrestrictedUpdateEvent(time_step, 0.0, self._push)

    def _calc(self, context, output):
        output.SetFromVector(context.get_discrete_state(self._fifo).get_value()[: self.n])

    def _push(self, context, state):
        fifo = context.get_discrete_state(self._fifo).get_value()
        state.get_mutable_discrete_state(self._fifo).SetFromVector(
            np.concatenate([fifo[self.n :], self.input.Eval(context)])
        )


class TorqueSensor(LeafSystem):
    """scale * (tau + w) + offset, w = (2 u - 1)(ratio |tau| + floor), u the `unit_noise` input
    (n draws of U(0, 1) per step, from Drake's RandomSource in the station; the input exists only
    when noisy); with lag_s > 0 the signal is first low-passed, lag_s y' + y = raw, exact for a
    torque held over each step: y_k = a y_(k-1) + (1 - a) raw_(k-1), a = exp(-h / lag_s), raw_(k-1) the
    reading of the step [t_(k-1), t_k) that just ended, starting steady; the output is the filter
    state (reading the current step's torque again would lead the continuous law by one step)."""

    def __init__(self, n, time_step, ratio, floor, scale, offset, noisy, *, lag_s=0.0):
        super().__init__()
        self.ratio, self.floor = float(ratio), float(floor)
        self.scale, self.offset = np.asarray(scale, float), np.asarray(offset, float)
        self.torque = self.DeclareVectorInputPort("torque", n)
        self.unit_noise = self.DeclareVectorInputPort("unit_noise", n) if noisy else None
        self.DeclareVectorOutputPort("measured_torque", BasicVector(n), self._calc)
        self._keep = np.exp(-time_step / lag_s) if lag_s > 0 else 0.0
        if lag_s > 0:
            # Unrestricted (not discrete) updates: at t_k they run before the noise source redraws,
            # so the filter sees the reading a logger or the estimator sees at t_k.
            self._filtered = self.DeclareDiscreteState(n)
            self.DeclareInitializationUnrestrictedUpdateEvent(self._start)
            self.DeclarePeriodicUnrestrictedUpdateEvent(time_step, 0.0, self._step)

    def _raw(self, context):
        tau = self.torque.Eval(context)
        if self.unit_noise is not None:
            tau = tau + (2.0 * self.unit_noise.Eval(context) - 1.0) * (self.ratio * np.abs(tau) + self.floor)
        return self.scale * tau + self.offset

    def _lagged(self, context):
        previous = context.get_discrete_state(self._filtered).get_value()
        return self._keep * previous + (1.0 - self._keep) * self._raw(context)

    def _start(self, context, state):
        state.get_mutable_discrete_state(self._filtered).SetFromVector(self._raw(context))

    def _step(self, context, state):
        # At t_k the update reads the pre-update context: the reading held over [t_(k-1), t_k).
        state.get_mutable_discrete_state(self._filtered).SetFromVector(self._lagged(context))

    def _calc(self, context, output):
        output.SetFromVector(
            context.get_discrete_state(self._filtered).get_value() if self._keep else self._raw(context)
        )
