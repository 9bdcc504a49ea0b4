"""LeafSystems of the arm boundary (thin: the rules are in freshness.py and messages.py).

Arm side (`safesysid arm-sim`, or what a driver must do): ArmDriver turns commands into the
motor torque u and holds the arm when they stop; StatusPublisherInput encodes the arm's status.
Run side: StatusReceiver decodes the status into the station's outputs; CommandEncoder encodes u.
"""

from __future__ import annotations

import collections
from dataclasses import replace

import numpy as np
from drake import lcmt_panda_command, lcmt_panda_status
from pydrake.common.value import AbstractValue
from pydrake.lcm import DrakeLcm
from pydrake.systems.framework import Context, EventStatus, LeafSystem
from safesysid.systems.estimation.packets import PACKET_ROWS, pack, packet_size

from .freshness import Freshness
from .messages import Status, command_message, parse_command, parse_status, status_message


class LatestMessage:
    """The newest message on an LCM channel, kept outside the Context (a DrakeLcm's are pumped by
    the LcmInterfaceSystem; a QueuedLcm's by `receive`, at the reader's step). A subscriber
    system's abstract state, a Python lcmtype, is deep-copied at every step's unrestricted update
    (measured: most of the 1 kHz loop's time)."""

    def __init__(self, lcm: DrakeLcm, channel: str, lcm_type: type, *, backlog: int = 0) -> None:
        """backlog: also keep up to this many of the latest messages for `drain` (0: none)."""
        self.lcm_type, self._latest, self._decoded = lcm_type, (0, None), (0, lcm_type())
        self._backlog: collections.deque = collections.deque(maxlen=backlog)
        self._lcm = lcm
        lcm.Subscribe(channel, self._on_message)

    def receive(self, timeout_ms: int = 0) -> None:
        """Take in what arrived (waiting up to timeout_ms for a first message)."""
        self._lcm.HandleSubscriptions(timeout_ms)

    @property
    def count(self) -> int:
        return self._latest[0]

    def _on_message(self, data: bytes) -> None:
        self._latest = (self._latest[0] + 1, data)
        self._backlog.append(data)

    def drain(self) -> list:
        """The messages received since the last drain (at most `backlog`, the newest), decoded."""
        out = []
        while self._backlog:
            out.append(self.lcm_type.decode(self._backlog.popleft()))
        return out

    def message(self) -> object:
        count, data = self._latest
        if self._decoded[0] != count:  # decode once per new message
            self._decoded = (count, self.lcm_type.decode(data))
        return self._decoded[1]


HOLD_KP_NM_RAD = 50.0  # the driver's hold: gravity + a PD to the pose at the trip
HOLD_KD_NMS_RAD = 5.0


class ArmDriver(LeafSystem):
    """Commands (lcmt_panda_command) -> motor torque u [N m], before the actuators' saturation.

    Holds q at the trip pose (gravity(q) + PD; gravity: the driver's own model, q -> N m) before
    the first command, after a hold request, when no new command arrived for watchdog_s (the
    driver's watchdog), or when the commands' clock jumps by more than that; latched, as a real
    driver stays in its error state."""

    def __init__(
        self, n: int, gravity, commands: LatestMessage, *, time_step_s: float, watchdog_s: float, q_start: np.ndarray
    ):
        super().__init__()
        self.gravity, self.n, self.commands = gravity, n, commands
        self.state = self.DeclareVectorInputPort("state", 2 * self.n)
        initial = (Freshness(watchdog_s), np.asarray(q_start, float))
        self._memo = self.DeclareAbstractState(AbstractValue.Make(initial))
        self.DeclarePeriodicUnrestrictedUpdateEvent(time_step_s, 0.0, self._tick)
        self.DeclareVectorOutputPort("torque", self.n, self._torque)

    def guard(self, context: Context) -> Freshness:
        return context.get_abstract_state(int(self._memo)).get_value()[0]

    def release_refusal(self, context: Context) -> str | None:
        """Why the gripper must not open now (None: the run's commands drive the arm)."""
        guard = self.guard(context)
        return "the arm holds" if guard.tripped is not None or not guard.armed else None

    def payload_released(self, context: Context) -> None:
        """Nothing here: the run switches its controller on the gripper's status (app/task_lcm.py)."""

    def _tick(self, context, state):
        guard, q_hold = context.get_abstract_state(int(self._memo)).get_value()
        t = context.get_time()
        self.commands.receive()
        parsed = parse_command(self.commands.message(), self.n)
        before = guard.tripped
        if parsed is None:
            guard = guard.step(t, name="command")
        else:
            sent, torque, hold = parsed
            guard = guard.step(t, sent, torque, name="command")
            if hold and guard.last_sent_s == sent:
                guard = guard.trip(t, "hold_requested", "the run asked the driver to brake and hold")
        if guard.tripped is not None and before is None:
            q_hold = self.state.Eval(context)[: self.n].copy()
        state.get_mutable_abstract_state(int(self._memo)).set_value((guard, q_hold))
        return EventStatus.Succeeded()

    def _torque(self, context, output):
        guard, q_hold = context.get_abstract_state(int(self._memo)).get_value()
        if guard.armed and guard.tripped is None:
            output.SetFromVector(guard.payload)
            return
        x = self.state.Eval(context)
        q, v = x[: self.n], x[self.n :]
        output.SetFromVector(self.gravity(q) + HOLD_KP_NM_RAD * (q_hold - q) - HOLD_KD_NMS_RAD * v)


class StatusEncoder(LeafSystem):
    """The arm's status (lcmt_panda_status), time-stamped with the arm's own clock."""

    def __init__(self, n: int):
        super().__init__()
        self.n = n
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.measured_torque = self.DeclareVectorInputPort("measured_torque", n)
        self.commanded_torque = self.DeclareVectorInputPort("commanded_torque", n)
        self.DeclareAbstractOutputPort("status", lambda: AbstractValue.Make(lcmt_panda_status()), self._calc)

    def _calc(self, context, output):
        x = self.state.Eval(context)
        status = Status(
            context.get_time(),
            x[: self.n],
            x[self.n :],
            self.measured_torque.Eval(context),
            self.commanded_torque.Eval(context),
        )
        output.set_value(status_message(status))


class StatusReceiver(LeafSystem):
    """lcmt_panda_status -> state [q, v], measured_torque (the newest status), the estimator's
    arm-timestamped samples (estimation/packets.py: every status received since the last step and
    newer than the last delivered one, in the arm's time order; `statuses` must keep a backlog),
    and hold (1.0 once the status stream stopped, jumped or stalled beyond status_timeout_s: the
    run must brake). `statuses` must queue (queued_lcm.py): a DrakeLcm pumped once per step loses
    the second of two statuses that reached one step (docs/hardware.md, Time)."""

    def __init__(
        self,
        n: int,
        statuses: LatestMessage,
        time_step_s: float,
        *,
        status_timeout_s: float,
        q_start: np.ndarray,
        resume: bool = False,
    ):
        """resume: after a trip (an event, as always) take the next status as a new start instead
        of latching (the controller beside the arm: an outage is only a gap in the samples)."""
        super().__init__()
        self.n, self.statuses, self.resume = n, statuses, resume
        rest = Status(0.0, np.asarray(q_start, float), np.zeros(n), np.zeros(n), np.zeros(n))
        self._memo = self.DeclareAbstractState(AbstractValue.Make((Freshness(status_timeout_s, payload=rest), ())))
        self.DeclarePeriodicUnrestrictedUpdateEvent(time_step_s, 0.0, self._tick)
        deps = {self.abstract_state_ticket(self._memo)}
        self.DeclareVectorOutputPort("state", 2 * n, self._state, prerequisites_of_calc=deps)
        self.DeclareVectorOutputPort("measured_torque", n, self._torque, prerequisites_of_calc=deps)
        self.DeclareVectorOutputPort("samples", packet_size(n), self._samples, prerequisites_of_calc=deps)
        self.DeclareVectorOutputPort("hold", 1, self._hold, prerequisites_of_calc=deps)

    def guard(self, context: Context) -> Freshness:
        return context.get_abstract_state(int(self._memo)).get_value()[0]

    def rearm(self, root_context: Context, grace_s: float = 0.1) -> None:
        """Forget the stream's timing (keeping the last status): the run's clock starts now, after
        its set-up (the first plan, the controller's compilation) held this loop; for grace_s the
        newest status is taken without timing checks (the backlog of the set-up drains)."""
        context = self.GetMyMutableContextFromRoot(root_context)
        guard = self.guard(context)
        fresh = Freshness(guard.limit_s, payload=guard.payload, grace_until_s=context.get_time() + grace_s)
        self.statuses.receive()
        self.statuses.drain()  # the set-up's statuses: the estimator starts with the clock
        context.get_mutable_abstract_state(int(self._memo)).set_value((fresh, ()))

    def _tick(self, context, state):
        guard = self.guard(context)
        self.statuses.receive()
        received = self.statuses.drain()
        status = parse_status(self.statuses.message(), self.n)
        t = context.get_time()
        new = guard.step(t, name="status") if status is None else guard.step(t, status.t_s, status, name="status")
        rows = ()
        if new.tripped is None and new.last_sent_s != guard.last_sent_s:  # a newer status was accepted
            after = -np.inf if guard.last_sent_s is None else guard.last_sent_s
            rows = _sample_rows(received, self.n, after=after, upto=new.last_sent_s)
        if new.tripped is not None and self.resume:
            new, rows = self._resumed(new, guard, status, received, now_s=t)
        state.get_mutable_abstract_state(int(self._memo)).set_value((new, rows))
        return EventStatus.Succeeded()

    def _resumed(self, tripped: Freshness, before: Freshness, status: Status | None, received: list, *, now_s: float):
        """(guard, rows) after a trip when resuming: this step's newest status accepted as a new start
        (the trip stays an event; the statuses are the arm's samples all the same: none is lost)."""
        fresh = Freshness(tripped.limit_s, payload=tripped.payload, ignored=tripped.ignored, events=tripped.events)
        if status is None:
            return fresh, ()
        after = -np.inf if before.last_sent_s is None else before.last_sent_s
        rows = _sample_rows(received, self.n, after=after, upto=status.t_s)
        return replace(
            fresh, last_sent_s=status.t_s, last_seen_s=status.t_s, last_arrival_s=now_s, payload=status
        ), rows

    def _status(self, context) -> Status:
        return self.guard(context).payload

    def _state(self, context, output):
        status = self._status(context)
        output.SetFromVector(np.concatenate([status.q, status.v]))

    def _torque(self, context, output):
        output.SetFromVector(self._status(context).measured_torque)

    def _samples(self, context, output):
        output.SetFromVector(pack(list(context.get_abstract_state(int(self._memo)).get_value()[1]), self.n))

    def _hold(self, context, output):
        output.SetFromVector([0.0 if self.guard(context).tripped is None else 1.0])


def _sample_rows(received: list, n: int, *, after: float, upto: float) -> tuple:
    """The estimator's rows [t, q, v, τ] of the statuses with after < t <= upto, once each, in
    time order, the newest PACKET_ROWS of them."""
    statuses = {s.t_s: s for s in (parse_status(m, n) for m in received) if s is not None and after < s.t_s <= upto}
    ordered = [statuses[t] for t in sorted(statuses)][-PACKET_ROWS:]
    return tuple(np.concatenate([[s.t_s], s.q, s.v, s.measured_torque]) for s in ordered)


class CommandEncoder(LeafSystem):
    """u [N m] -> lcmt_panda_command stamped with the run's clock; input hold > 0.5 asks the
    driver to brake and hold (control_mode_expected = kNone)."""

    def __init__(self, n: int):
        super().__init__()
        self.torque = self.DeclareVectorInputPort("torque", n)
        self.hold = self.DeclareVectorInputPort("hold", 1)
        self.DeclareAbstractOutputPort("command", lambda: AbstractValue.Make(lcmt_panda_command()), self._calc)

    def _calc(self, context, output):
        hold = self.hold.HasValue(context) and self.hold.Eval(context)[0] > 0.5
        output.set_value(command_message(context.get_time(), self.torque.Eval(context), hold))


def with_events(guard: Freshness, **extra: object) -> dict:
    """A receiver's record for summary files."""
    return dict(tripped=guard.tripped, ignored_messages=guard.ignored, events=list(guard.events), **extra)
