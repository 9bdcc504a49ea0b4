"""The simulated real arm (systems/plant/station.py, Drake) tracking a desired trajectory with a fixed
controller: computed torque on a controller model plus PD, sampled every plant step and held.
The plant comes from a scenario and a RobotModel (which may differ from the controller's, e.g.
a corrected model), so two plants can be driven by the same commanded trajectory and their
logs compared. The feed-forward is evaluated once for the whole trajectory (vectorized), so a
second of 1 kHz simulation costs about a third of a second.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Context, DiagramBuilder, DiscreteValues, LeafSystem
from pydrake.systems.primitives import LogVectorOutput
from safesysid.systems.config import Scenario
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import RobotModel


class ComputedTorque(LeafSystem):
    """u_k = feed_forward[k] + kp (q_d[k] - q) + kd (v_d[k] - v) at step k = t / h, held every
    plant step (no direct feedthrough: the loop through motor-side encoders stays causal). The
    discrete update runs after the plant's own step (an unrestricted update in Drake 1.51), so
    at t_k it reads the state of t_k + h: track_trajectory's grid is shifted by h to match, and
    the command held over the next step uses that step's state and desired values."""

    def __init__(
        self, h: float, feed_forward: np.ndarray, q_d: np.ndarray, *, v_d: np.ndarray, kp: float, kd: float
    ) -> None:
        super().__init__()
        n = feed_forward.shape[1]
        self._h, self._feed_forward, self._q_d, self._v_d, self._kp, self._kd = h, feed_forward, q_d, v_d, kp, kd
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        u_index = self.DeclareDiscreteState(n)
        self.DeclarePeriodicDiscreteUpdateEvent(h, 0.0, self._update)
        self.DeclareStateOutputPort("u", u_index)

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        k = int(round(context.get_time() / self._h))
        x = self.state.Eval(context)
        n = len(x) // 2
        u = self._feed_forward[k] + self._kp * (self._q_d[k] - x[:n]) + self._kd * (self._v_d[k] - x[n:])
        discrete_state.get_mutable_vector().SetFromVector(u)


def track_trajectory(
    scenario: Scenario,
    plant_robot: RobotModel,
    controller_robot: RobotModel,
    traj: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]],
    seed: int,
    duration_s: float,
    *,
    rate_hz: float = 100.0,
    kp_Nm_rad: float = 400.0,
    kd_Nms_rad: float = 40.0,
    skip_s: float = 0.2,
) -> JointLog:
    """JointLog (t, q, v, measured torque; no accelerations: the arm has no such sensor) of the
    real arm built from (scenario, plant_robot), no payload, tracking traj(t) -> (q, v, a) with
    u = ID_controller(q_d, v_d, a_d) + kp (q_d - q) + kd (v_d - v); the first skip_s seconds
    (start-up transient) are dropped."""
    from safesysid.systems.plant.station import add_real_arm

    n = controller_robot.n
    h = scenario.plant.time_step_s
    grid = np.arange(0.0, duration_s + 2 * h, h) + h  # the command of step k is for t_k + h
    q_d, v_d, a_d = traj(grid)
    feed_forward = controller_robot.inverse_dynamics(q_d, v_d, a_d)
    builder = DiagramBuilder()
    arm = add_real_arm(builder, scenario, plant_robot, dumbbell=None, seed=seed)

    ctrl = builder.AddSystem(ComputedTorque(h, feed_forward, q_d, v_d=v_d, kp=kp_Nm_rad, kd=kd_Nms_rad))
    builder.Connect(arm.state_output, ctrl.state)
    builder.Connect(ctrl.get_output_port(), arm.commanded_torque_input)
    log_x = LogVectorOutput(arm.state_output, builder, 1.0 / rate_hz)
    log_u = LogVectorOutput(arm.measured_torque_output, builder, 1.0 / rate_hz)
    sim = Simulator(builder.Build())
    ctx = sim.get_mutable_context()
    q0, v0, _ = traj(np.array([0.0]))
    arm.set_state(ctx, q0[0], v0[0])
    arm.seed_noise(ctx)  # the log depends on `seed`, not on how many sources were built before
    sim.AdvanceTo(duration_s)
    lx, lu = log_x.FindLog(ctx), log_u.FindLog(ctx)
    t, x, tau = lx.sample_times(), lx.data().T, lu.data().T
    keep = t > skip_s
    return JointLog(t[keep], x[keep, :n], x[keep, n:], tau[keep], None, {}, "real_arm")
