"""Fault injection (scenario `faults`, systems/config.py Faults): small Drake stages between the
real arm and the systems that read it, and the pure helpers the planner and the payload use.

Each stage keeps what it injected as events {t, kind, detail} in its own Context (abstract
state), so summary.json can list them (app/online.py). Random faults draw from a Drake
RandomSource (one U(0, 1) per fault and step), seeded per context with the run's seed like the
torque sensor's noise (real_arm.py, RealArm.seed_noise): a rate r [1/s] fires at a step with
probability r h. Decisions are pure functions of (inputs, the stage's state before the update,
the draws) so the output at t_k and the update at t_k (both read the pre-update context, as the
loggers and the estimator do) agree.

Stages:
- TorqueSensorFaults: spikes of +-magnitude N m on one joint at a rate; a dropout (reads 0 N m).
- VelocityClip: the encoders' velocities clipped to +-limit (what controller and estimator read).
- SampleFaults: what reaches the estimator, as a packet of 0-2 timestamped samples per step:
  lost (0), duplicated (the same sample twice), reordered (held back one step, then delivered
  after the next sample), or with a NaN in one field.

add_fault_stages wires the scenario's stages into the real arm's station (systems/plant/station.py).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, Context, DiagramBuilder, EventStatus, LeafSystem, OutputPort
from pydrake.systems.primitives import RandomSource
from safesysid.systems.estimation.packets import pack, packet_size

if TYPE_CHECKING:
    from safesysid.systems.config import Faults, Scenario
    from safesysid.systems.model.payload import Dumbbell


class _EventStage(LeafSystem):
    """A stage that records what it injected: abstract state `memo` (stage-specific, immutable)
    and a tuple of events, appended by a per-step unrestricted update when `per_step`."""

    def __init__(self, time_step_s: float, memo=None, per_step: bool = True):
        super().__init__()
        self.time_step_s = float(time_step_s)
        self._log = self.DeclareAbstractState(AbstractValue.Make((memo, ())))
        if per_step:
            self.DeclarePeriodicUnrestrictedUpdateEvent(self.time_step_s, 0.0, self._on_step)

    def _memo(self, context):
        return context.get_abstract_state(int(self._log)).get_value()[0]

    def events(self, context: Context) -> list[dict]:
        return list(context.get_abstract_state(int(self._log)).get_value()[1]) + self.scheduled_events()

    def scheduled_events(self) -> list[dict]:
        """Events known from the scenario alone (not drawn)."""
        return []

    def _on_step(self, context, state):
        memo, events = context.get_abstract_state(int(self._log)).get_value()
        new_memo, new_events = self._step(context, memo)
        if new_events or new_memo is not memo:
            state.get_mutable_abstract_state(int(self._log)).set_value((new_memo, events + tuple(new_events)))
        return EventStatus.Succeeded()

    def _step(self, context, memo):
        """(memo after this step, events of this step)."""
        return memo, []


class TorqueSensorFaults(_EventStage):
    """The measured torque plus spikes (on a draw u0 < rate h: ±magnitude on a joint picked by
    u1 among `joints`, 0-based) and a dropout (0 N m) over [dropout_start_s, + duration)."""

    def __init__(self, n, time_step_s, magnitude_Nm, *, rate_per_s, joints, dropout_start_s, dropout_duration_s):
        self.n = n
        self.magnitude = float(magnitude_Nm)
        self.p_spike = float(rate_per_s) * time_step_s if magnitude_Nm > 0 else 0.0
        self.joints = list(joints) or list(range(n))
        self.dropout = (float(dropout_start_s), float(dropout_start_s) + float(dropout_duration_s))
        super().__init__(time_step_s, per_step=self.p_spike > 0)
        self.torque = self.DeclareVectorInputPort("torque", n)
        self.unit_noise = self.DeclareVectorInputPort("unit_noise", 2) if self.p_spike > 0 else None
        self.DeclareVectorOutputPort("measured_torque", BasicVector(n), self._calc)

    def _spike(self, context):
        """(joint, signed magnitude) of this step's spike, or None."""
        if self.unit_noise is None:
            return None
        u = self.unit_noise.Eval(context)
        if u[0] >= self.p_spike:
            return None
        pick = min(int(u[1] * 2 * len(self.joints)), 2 * len(self.joints) - 1)
        return self.joints[pick // 2], self.magnitude * (1.0 if pick % 2 else -1.0)

    def _in_dropout(self, t):
        return self.dropout[0] <= t < self.dropout[1]

    def _calc(self, context, output):
        if self._in_dropout(context.get_time()):
            output.SetFromVector(np.zeros(self.n))
            return
        tau = self.torque.Eval(context).copy()
        spike = self._spike(context)
        if spike is not None:
            tau[spike[0]] += spike[1]
        output.SetFromVector(tau)

    def _step(self, context, memo):
        spike = self._spike(context)
        if spike is None or self._in_dropout(context.get_time()):
            return memo, []
        detail = f"torque sensor spike {spike[1]:+.3g} N m on joint {spike[0] + 1}"
        return memo, [dict(t=context.get_time(), kind="fault_torque_spike", detail=detail)]

    def scheduled_events(self) -> list[dict]:
        start, end = self.dropout
        if end <= start:
            return []
        return [dict(t=start, kind="fault_torque_dropout", detail=f"torque sensor reads 0 N m until {end:.3f} s")]


class VelocityClip(_EventStage):
    """The state (q, v) with v clipped to ±limit; logs the first clipped step of each joint."""

    def __init__(self, n, time_step_s, limit_rad_s):
        self.n, self.limit = n, float(limit_rad_s)
        super().__init__(time_step_s, memo=frozenset())
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.DeclareVectorOutputPort("measured_state", BasicVector(2 * n), self._calc)

    def _calc(self, context, output):
        x = self.state.Eval(context).copy()
        x[self.n :] = np.clip(x[self.n :], -self.limit, self.limit)
        output.SetFromVector(x)

    def _step(self, context, memo):
        v = self.state.Eval(context)[self.n :]
        new = [j for j in np.flatnonzero(np.abs(v) > self.limit) if j not in memo]
        if not new:
            return memo, []
        events = [
            dict(
                t=context.get_time(),
                kind="fault_velocity_clipped",
                detail=f"joint {j + 1} velocity {v[j]:+.4g} rad/s read as {np.sign(v[j]) * self.limit:+.4g} rad/s",
            )
            for j in new
        ]
        return memo | frozenset(int(j) for j in new), events


@dataclasses.dataclass(frozen=True)
class SampleRates:
    """Probabilities per step (rate * h) of each sample fault."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    nan: float = 0.0

    @classmethod
    def from_faults(cls, faults: Faults, time_step_s: float) -> SampleRates:
        f = faults
        return cls(
            *(
                r * time_step_s
                for r in (
                    f.sample_drop_rate_per_s,
                    f.sample_duplicate_rate_per_s,
                    f.sample_reorder_rate_per_s,
                    f.sample_nan_rate_per_s,
                )
            )
        )


def deliver(
    row: np.ndarray, held: np.ndarray | None, u: np.ndarray, *, rates: SampleRates, n: int
) -> tuple[list[np.ndarray], np.ndarray | None, list[dict]]:
    """What reaches the estimator at one step: (rows delivered, the row held back for the next
    step or None, events). row: this step's true sample [t, q, v, τ]; held: a row held back at
    the previous step; u: 5 draws U(0, 1) (drop, duplicate, reorder, nan, which field)."""
    t = float(row[0])
    if held is not None:  # the late sample arrives after this one
        return [row, held], None, [dict(t=t, kind="fault_sample_reordered", detail=f"sample of {held[0]:.3f} s late")]
    if u[2] < rates.reorder:
        return [], row, []
    if u[0] < rates.drop:
        return [], None, [dict(t=t, kind="fault_sample_dropped", detail="sample lost")]
    if u[3] < rates.nan:
        field = 1 + min(int(u[4] * 3 * n), 3 * n - 1)
        row = row.copy()
        row[field] = np.nan
        name = ("q", "v", "tau")[(field - 1) // n] + str((field - 1) % n + 1)
        return [row], None, [dict(t=t, kind="fault_sample_nan", detail=f"NaN in {name}")]
    if u[1] < rates.duplicate:
        return [row, row], None, [dict(t=t, kind="fault_sample_duplicated", detail="sample delivered twice")]
    return [row], None, []


class SampleFaults(_EventStage):
    """Between the arm and the estimator: output `samples`, a packet (pack/unpack) of what the
    estimator receives this step (deliver); the held-back row is the stage's state."""

    def __init__(self, n, time_step_s, rates: SampleRates):
        self.n, self.rates = n, rates
        super().__init__(time_step_s, memo=None)
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.torque = self.DeclareVectorInputPort("measured_torque", n)
        self.unit_noise = self.DeclareVectorInputPort("unit_noise", 5)
        self.DeclareVectorOutputPort("samples", BasicVector(packet_size(n)), self._calc)

    def _deliver(self, context, held):
        row = np.concatenate([[context.get_time()], self.state.Eval(context), self.torque.Eval(context)])
        return deliver(row, held, self.unit_noise.Eval(context), rates=self.rates, n=self.n)

    def _calc(self, context, output):
        rows, _, _ = self._deliver(context, self._memo(context))
        output.SetFromVector(pack(rows, self.n))

    def _step(self, context, memo):
        _, held, events = self._deliver(context, memo)
        return held, events


def scenario_events(scenario: Scenario) -> list[dict]:
    """Events of faults fixed by the scenario alone (the others are logged where they happen)."""
    extra = scenario.faults.payload_extra_mass_kg
    if extra > 0 and scenario.payload.dumbbell.lower() != "none":
        detail = f"the real payload is {extra:.3g} kg heavier than the {scenario.payload.dumbbell} dumbbell"
        return [dict(t=0.0, kind="fault_payload_heavier", detail=detail)]
    return []


def heavier_payload(dumbbell: Dumbbell | None, extra_mass_kg: float) -> Dumbbell | None:
    """The same dumbbell shape, extra_mass_kg heavier (denser): a payload outside the prior."""
    if dumbbell is None or extra_mass_kg <= 0:
        return dumbbell
    return dataclasses.replace(dumbbell, mass_kg=dumbbell.mass_kg + float(extra_mass_kg))


@dataclasses.dataclass
class InjectedFaults:
    """What add_fault_stages added to a station."""

    stages: tuple[_EventStage, ...] = ()
    sources: tuple[RandomSource, ...] = ()  # their draws (seeded with the sensor noise)
    samples: OutputPort | None = None  # the estimator's packet port (SampleFaults), or None


def add_fault_stages(
    station: DiagramBuilder, scenario: Scenario, n: int, *, h: float, measured: OutputPort, state_out: OutputPort
) -> tuple[OutputPort, OutputPort, InjectedFaults]:
    """The scenario's fault stages (above) on the measured torque and the encoders,
    and the faulty link to the estimator: (measured torque, state, InjectedFaults)."""

    f, injected = scenario.faults, InjectedFaults()

    def add(system, name, draws=0):
        system.set_name(name)
        injected.stages += (station.AddSystem(system),)
        if draws:
            source = station.AddSystem(RandomSource(RandomDistribution.kUniform, draws, h))
            source.set_name(f"{name}_draws")
            station.Connect(source.get_output_port(), system.unit_noise)
            injected.sources += (source,)
        return system

    if f.torque_spike_magnitude_Nm * f.torque_spike_rate_per_s > 0 or f.torque_dropout_duration_s > 0:
        joints = [j - 1 for j in f.torque_spike_joints]
        spikes = f.torque_spike_magnitude_Nm * f.torque_spike_rate_per_s > 0
        stage = TorqueSensorFaults(
            n,
            h,
            f.torque_spike_magnitude_Nm,
            rate_per_s=f.torque_spike_rate_per_s,
            joints=joints,
            dropout_start_s=f.torque_dropout_start_s,
            dropout_duration_s=f.torque_dropout_duration_s,
        )
        add(stage, "fault_torque_sensor", 2 if spikes else 0)
        station.Connect(measured, stage.torque)
        measured = stage.get_output_port()
    if f.velocity_clip_rad_s > 0:
        stage = add(VelocityClip(n, h, f.velocity_clip_rad_s), "fault_velocity_clip")
        station.Connect(state_out, stage.state)
        state_out = stage.get_output_port()
    if f.samples_faulty():
        stage = add(SampleFaults(n, h, SampleRates.from_faults(f, h)), "fault_samples", 5)
        station.Connect(state_out, stage.state)
        station.Connect(measured, stage.torque)
        injected.samples = stage.get_output_port()
    return measured, state_out, injected
