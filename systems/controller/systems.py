"""Controllers as Drake LeafSystems, all behind the same ports.

Inputs:  desired (3 n: q_d, qd_d, qdd_d), state (2 n: q, v), theta0 (14 n),
         theta_lower (14 n), theta_upper (14 n).       Output: torque (n), commanded.
All laws evaluate at the step's inputs (direct feedthrough, cached once per step).

- ArmourController: the robust passivity law of systems/controller/armour.py (extra output
  'diagnostics' = [V_bar, h, lambda, |r|, |w_bar|]).
- GravityPidController ("grav-pid"): u = g(q; theta0) + beta + Kp e + Ki int e + Kd edot, the
  handbook PID with gravity compensation (Siciliano et al., Robotics, sec. 8.5.2 + integral).
- AdaptiveController ("adap-1"; output 'estimate' = theta_hat_e): Slotine-Li,
  u = Wp(q, qd, qd_a, qdd_a) theta_hat + K_D r, r = qd_a - qd; the 10 end-effector parameters
  adapt, d theta_hat_e/dt = Gamma Wp_e^T r,
  integrated at the plant step and projected on [theta_e] (box projection with diagonal Gamma
  keeps the Lyapunov argument and bounds the estimate); theta_hat_e = theta0_e + delta, so an
  estimator's new theta0 moves the estimate with it.
- AdaptiveRobustController ("adap-2"): adaptive robust control in the style of Yao-Tomizuka:
  the adaptive law above plus a smoothed robust term v_i = w_bar_i(theta_hat) sat(r_i / phi),
  w_bar = |Wp| max(theta_hi - theta_hat, theta_hat - theta_lo) the worst model error over the box.
Gains come from ControllerGains (from the scenario via gains_from_scenario).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, Context, LeafSystem, ValueProducer
from safesysid.systems.config import ScenarioError
from safesysid.systems.controller.armour import ArmourGains, ArmourOutput, armour_control, tracking_errors, wrap_error
from safesysid.systems.controller.armour_fast import FastArmourLaw, FastControllerDynamics
from safesysid.systems.math.intervals import Interval

if TYPE_CHECKING:
    from safesysid.systems.config import Scenario
    from safesysid.systems.model.robot_model import RobotModel

_log = logging.getLogger(__name__)


@dataclass
class ControllerGains:
    armour: ArmourGains
    pid_kp: np.ndarray
    pid_ki: np.ndarray
    pid_kd: np.ndarray
    adaptive_kd: np.ndarray
    adaptive_gamma: np.ndarray
    robust_boundary: float
    extra: dict[str, Any] = field(default_factory=dict)


def _fit(values, n, name):
    arr = np.asarray(values, float)
    if arr.size == 0:
        raise ScenarioError(
            f"controller.{name}: unset (load_scenario, robot_from_scenario or add_real_arm fill it from the robot)"
        )
    if arr.size == 1:
        return np.full(n, float(arr.reshape(-1)[0]))
    if arr.shape != (n,):
        raise ScenarioError(f"controller.{name}: needs {n} values, got {arr.size}")
    return arr


def gains_from_scenario(scenario: Scenario, n: int) -> ControllerGains:
    """Gains from scenario.controller (defaults and units: systems/config.py, class Controller)."""
    c = scenario.controller
    return ControllerGains(
        armour=ArmourGains(_fit(c.Kr, n, "Kr"), float(c.alpha), float(c.V_max)),
        pid_kp=_fit(c.pid_kp_Nm_rad, n, "pid_kp_Nm_rad"),
        pid_ki=_fit(c.pid_ki_Nm_rad_s, n, "pid_ki_Nm_rad_s"),
        pid_kd=_fit(c.pid_kd_Nms_rad, n, "pid_kd_Nms_rad"),
        adaptive_kd=_fit(c.adaptive_kd_Nms_rad, n, "adaptive_kd_Nms_rad"),
        adaptive_gamma=_fit(c.adaptive_gamma, 10, "adaptive_gamma"),
        robust_boundary=float(c.adaptive_boundary_rad_s),
    )


class ControllerBase(LeafSystem):
    """Common ports; subclasses implement _torque(context, q, v, q_d, qd_d, qdd_d, theta0, box)."""

    def __init__(self, robot: RobotModel, gains: ControllerGains) -> None:
        super().__init__()
        self.robot, self.gains, self.n = robot, gains, robot.n
        n, p = robot.n, 14 * robot.n
        self.dyn = FastControllerDynamics(robot)
        self.desired = self.DeclareVectorInputPort("desired", 3 * n)
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.theta0 = self.DeclareVectorInputPort("theta0", p)
        self.theta_lower = self.DeclareVectorInputPort("theta_lower", p)
        self.theta_upper = self.DeclareVectorInputPort("theta_upper", p)
        self.torque_output = self.DeclareVectorOutputPort("torque", BasicVector(n), self._calc_torque)

    def _raw_inputs(self, context):
        """(q, v, q_d, qd_d, qdd_d, theta0, theta_lower, theta_upper), unchecked."""
        n = self.n
        x = self.state.Eval(context)
        d = self.desired.Eval(context)
        return (
            x[:n],
            x[n:],
            d[:n],
            d[n : 2 * n],
            d[2 * n :],
            self.theta0.Eval(context),
            self.theta_lower.Eval(context),
            self.theta_upper.Eval(context),
        )

    def _inputs(self, context):
        *signals, lo, hi = self._raw_inputs(context)
        return (*signals, Interval(lo, hi))

    def _declare_step_update(self, update):
        """update(context, state) every self.time_step in the plant's phase: Drake's discrete
        MultibodyPlant (1.51) steps in an unrestricted update, so a discrete update would read the
        state after the step (x_k+1 at t_k); this one reads the sample the plant's step used."""
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.time_step, 0.0, update)

    def _declare_step_cache(self, name, calc):
        """A cache entry holding any Python object, recomputed when an input changes."""
        return self.DeclareCacheEntry(
            name,
            ValueProducer(allocate=lambda: AbstractValue.Make(object()), calc=calc),
            {self.all_input_ports_ticket()},
        )

    def _calc_torque(self, context, output):
        output.SetFromVector(self._torque(context, *self._inputs(context)))


class ArmourController(ControllerBase):
    """The robust passivity law (armour.armour_control); extra output 'diagnostics'."""

    def __init__(self, robot: RobotModel, gains: ControllerGains) -> None:
        super().__init__(robot, gains)
        # One evaluation of the law per step, shared by the torque and diagnostics outputs.
        self._law = self._declare_step_cache("law", self._calc_law)
        self._fast_law = FastArmourLaw(self.dyn, gains.armour)  # caches what depends on [theta] only
        self.DeclareVectorOutputPort("diagnostics", BasicVector(5), self._calc_diag)

    def _calc_law(self, context, value):
        *args, theta0, lo, hi = self._raw_inputs(context)
        armour = self.gains.armour
        out = self._fast_law(*args, theta0, lo, hi)  # None when theta0 or [theta] is not finite, or lo > hi
        if out is None or not np.isfinite(out.u).all():
            # Bad parameter input (an estimator failure): never command NaN. Fall back to the
            # model's nominal parameters, logged; the guarantee is void until inputs recover.
            _log.warning("ArmourController at t=%.4f s: invalid theta inputs, nominal model used", context.get_time())
            out = armour_control(self.dyn, armour, *args, self.robot.theta, Interval(self.robot.theta))
        value.set_value(out)

    def law(self, context: Context) -> ArmourOutput:
        """ArmourOutput of the current step (u, tau_nom, v, w_bar, V_bar, h, lam, err)."""
        return self._law.Eval(context)

    def _torque(self, context, *args):
        return self.law(context).u

    def _calc_torque(self, context, output):
        output.SetFromVector(self._torque(context))  # the law reads its inputs itself (no second pass)

    def _calc_diag(self, context, output):
        out = self.law(context)
        norms = [math.sqrt(out.err.r @ out.err.r), math.sqrt(out.w_bar @ out.w_bar)]  # = np.linalg.norm, cheaper
        output.SetFromVector([out.V_bar, out.h, out.lam, *norms])


class GravityPidController(ControllerBase):
    """u = g(q; theta0) + Kp e + Ki int e + Kd edot; the integral is discrete state, stepped every
    time_step in the plant's phase (_declare_step_update)."""

    def __init__(self, robot: RobotModel, gains: ControllerGains, time_step: float) -> None:
        super().__init__(robot, gains)
        self.time_step = float(time_step)
        self._integral = self.DeclareDiscreteState(robot.n)
        self._declare_step_update(self._update)

    def _errors(self, q, v, q_d, qd_d):
        return wrap_error(q_d - q, self.robot.joint_params.continuous), qd_d - v

    def _torque(self, context, q, v, q_d, qd_d, qdd_d, theta0, box):
        g = self.gains
        e, edot = self._errors(q, v, q_d, qd_d)
        z = context.get_discrete_state(self._integral).get_value()
        return self.dyn.gravity(q, theta0) + g.pid_kp * e + g.pid_ki * z + g.pid_kd * edot

    def _update(self, context, state):
        q, v, q_d, qd_d, *_ = self._inputs(context)
        e, _ = self._errors(q, v, q_d, qd_d)
        z = context.get_discrete_state(self._integral).get_value()
        state.get_mutable_discrete_state(self._integral).SetFromVector(z + self.time_step * e)


class AdaptiveController(ControllerBase):
    """adap-1 (robust=False) or adap-2 (robust=True); the adapted offset theta_hat_e - theta0_e
    is discrete state, stepped every time_step in the plant's phase (_declare_step_update)."""

    def __init__(self, robot: RobotModel, gains: ControllerGains, time_step: float, *, robust: bool = False) -> None:
        super().__init__(robot, gains)
        self.time_step, self.robust, self.ee = float(time_step), bool(robust), robot.ee_slice
        self._delta = self.DeclareDiscreteState(10)  # theta_hat_e - theta0_e
        self._declare_step_update(self._update)
        # Errors and regressor depend on the inputs only: shared by output and update.
        self._regressor = self._declare_step_cache("errors_and_regressor", self._calc_regressor)
        self.set_name("adaptive_robust_controller" if robust else "adaptive_controller")
        # What the adaptive law identifies (paper Fig. 6 plots its mass): theta_hat_e (10).
        self.DeclareVectorOutputPort(
            "estimate", BasicVector(10), self._calc_estimate, {self.all_input_ports_ticket(), self.xd_ticket()}
        )

    def _calc_estimate(self, context, output):
        *_, theta0, box = self._inputs(context)
        output.SetFromVector(self.estimate(context, theta0, box)[self.ee])

    def _calc_regressor(self, context, value):
        q, v, q_d, qd_d, qdd_d, _, _ = self._inputs(context)
        err = tracking_errors(
            self.gains.armour.Kr, q, v, q_d=q_d, qd_d=qd_d, qdd_d=qdd_d, continuous=self.robot.joint_params.continuous
        )
        wp, _ = self.dyn.regressors(q, v, err.qd_a, aa=err.qdd_a, x=np.zeros(self.n))
        value.set_value((err, wp))

    def estimate(self, context: Context, theta0: np.ndarray, box: Interval) -> np.ndarray:
        """theta_hat (14 n): theta0 with the adapted end effector, projected on the box."""
        ee = self.ee
        theta = theta0.copy()
        delta = context.get_discrete_state(self._delta).get_value()
        theta[ee] = np.clip(theta0[ee] + delta, box.lo[ee], box.hi[ee])
        return theta

    def _terms(self, context, q, v, q_d, qd_d, qdd_d, theta0, box):
        err, wp = self._regressor.Eval(context)
        return err, wp, self.estimate(context, theta0, box)

    def _torque(self, context, *inputs):
        err, wp, theta_hat = self._terms(context, *inputs)
        u = wp @ theta_hat + self.gains.adaptive_kd * err.r
        if self.robust:
            box = inputs[-1]
            spread = np.maximum(box.hi - theta_hat, theta_hat - box.lo)
            w_bar = np.abs(wp) @ np.maximum(spread, 0.0)
            u = u + w_bar * np.clip(err.r / self.gains.robust_boundary, -1.0, 1.0)
        return u

    def _update(self, context, state):
        ee = self.ee
        inputs = self._inputs(context)
        err, wp, theta_hat = self._terms(context, *inputs)
        theta0, box = inputs[-2], inputs[-1]
        step = self.time_step * self.gains.adaptive_gamma * (wp[:, ee].T @ err.r)
        new = np.clip(theta_hat[ee] + step, box.lo[ee], box.hi[ee])
        state.get_mutable_discrete_state(self._delta).SetFromVector(new - theta0[ee])


# kind -> factory (robot, gains, time_step); the kinds of systems/methods.py CONTROLLER_KINDS.
CONTROLLERS = {
    "armour": lambda robot, gains, time_step: ArmourController(robot, gains),
    "pid": GravityPidController,
    "adaptive": lambda robot, gains, time_step: AdaptiveController(robot, gains, time_step, robust=False),
    "adaptive_robust": lambda robot, gains, time_step: AdaptiveController(robot, gains, time_step, robust=True),
}


def make_controller(kind: str, robot: RobotModel, gains: ControllerGains, *, time_step: float) -> ControllerBase:
    """kind: a key of CONTROLLERS (a method's MethodSpec.controller, or scenario.controller.kind)."""
    try:
        factory = CONTROLLERS[kind]
    except KeyError:
        raise ValueError(f"controller.kind: unknown controller {kind!r}") from None
    return factory(robot, gains, time_step)


class PhaseSwitch(LeafSystem):
    """Output torque = input "identification" while input phase is 0, input "task" once it is 1
    (TaskPhaseSource's phase): one method, two controllers (grav-pid-ours)."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.phase = self.DeclareVectorInputPort("phase", 1)
        self.inputs = [self.DeclareVectorInputPort(name, n) for name in ("identification", "task")]
        self.DeclareVectorOutputPort("torque", n, self._calc)

    def _calc(self, context: Context, output: BasicVector) -> None:
        selected = self.inputs[int(self.phase.Eval(context)[0] > 0.5)]
        output.SetFromVector(selected.Eval(context))
