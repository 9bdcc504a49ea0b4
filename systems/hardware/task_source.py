"""The task phase's switch in wall-clock time: make_task (the return move's solve and ARMOUR's
certificate of the task, seconds of CPU) runs in the worker process while the 1 kHz loop holds
the arm at the switch pose; the curves start when the result is back (docs/hardware.md).

In the simulated clock the switch computes the curves at once (the clock stops); here a loop
stalled for seconds would trip the driver's watchdog. A worker that dies, or a result not back
within TASK_TIMEOUT_S, is a refused task (`task_error`): no curves, the arm holds, as for an
uncertified task.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.systems.framework import EventStatus
from safesysid.systems.planner.trajectory_source import PhaseState, TaskPhaseSource, TimedCurve

from .background import BackgroundWorker, register

POLL_PERIOD_S = 0.01  # how often the loop looks for the worker's result
TASK_TIMEOUT_S = 30.0  # make_task measured ~3 s on an idle core (experiment_a)


class WallClockTaskSource(TaskPhaseSource):
    """TaskPhaseSource whose make_task call runs in `worker` (module docstring)."""

    def __init__(self, *args, worker: BackgroundWorker, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.worker, self.key = worker, register(self)
        self.pending = None  # (future, time of the switch) while the task is being made
        self.latency_s: float | None = None
        self.DeclarePeriodicUnrestrictedUpdateEvent(POLL_PERIOD_S, 0.0, self._poll)

    def _switch(self, context, state):
        t = context.get_time()
        desired = self._plan_desired.Eval(context) if self._plan_desired.HasValue(context) else None
        q_now = self._q0 if desired is None else np.array(desired[: self._n])
        thetas = tuple(np.array(port.Eval(context), float) for port in self._task_thetas)
        events = ()
        try:
            self.pending = (self.worker.submit(_task_job, self.key, q_now, thetas, lane="planner"), t)
        except Exception as err:  # noqa: BLE001 (the worker is gone: no task, the arm holds)
            events = (dict(t=t, kind="task_error", detail=f"no worker to make the task ({err!r}): the arm holds"),)
        waiting = PhaseState("task", t, q_now, (), False, thetas, events, {})
        state.get_mutable_abstract_state(int(self._state)).set_value(waiting)

    def _poll(self, context, state):
        if self.pending is None:
            return EventStatus.DidNothing()
        future, t_switch = self.pending
        t = context.get_time()
        if not future.done() and t - t_switch <= TASK_TIMEOUT_S:
            return EventStatus.DidNothing()
        self.pending = None
        st = self.phase_state(context)
        made, events, report = _result(future, t - t_switch)
        if made:
            self.latency_s = t - t_switch
        curves, start = [], t  # the arm held at q_switch until now: the curves start here
        for curve in made:
            curves.append(TimedCurve(start, curve))
            start += curve.duration
        found = tuple(dict(t=t, **e) for e in events)
        new = dataclasses.replace(st, curves=tuple(curves), ready=bool(curves), events=found, report=dict(report))
        state.get_mutable_abstract_state(int(self._state)).set_value(new)
        return EventStatus.Succeeded()


def _result(future, waited_s: float) -> tuple[list, list, dict]:
    if not future.done():
        future.cancel()
        detail = f"the task was not made within {TASK_TIMEOUT_S:g} s of the switch: the arm holds"
        return [], [dict(kind="task_error", detail=detail)], {}
    try:
        (made, events, report), *_ = future.result()  # (result, the wall time it finished, CPU, duration)
    except Exception as err:  # noqa: BLE001 (a dead worker: the task is refused, the arm holds)
        return [], [dict(kind="task_error", detail=f"the worker failed making the task ({err!r}): the arm holds")], {}
    detail = f"made in the worker in {waited_s:.2f} s (the arm held at the switch pose)"
    return made, [*events, dict(kind="task_made", detail=detail)], report


def _task_job(key: int, q_now: np.ndarray, thetas: tuple) -> tuple:
    from .background import _REGISTRY

    return _REGISTRY[key]._make_task(q_now, thetas)
