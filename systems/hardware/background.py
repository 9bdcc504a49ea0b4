"""Planning and estimation that do not stop the clock (Algorithm 2's timing in wall-clock time).

A call started at t_k runs in a worker process while the 1 kHz loop goes on; its result is used
at t_k + t_p. The planner plans at t_k the plan that starts at t_k + t_p, from the state the
executing plan reaches then (known exactly: it is the desired trajectory), with the estimate
published at t_k. A result not back at t_k + t_p is a missed deadline: status deadline_missed,
the robot brakes on the verified plan (as for any failed call). A worker that dies is that
call's planner_error. The estimator hands the samples of [t_(k-1), t_k] to a worker at t_k and
publishes the result at t_(k+1) (the estimator itself advances in the worker: only the Estimate
comes back); a late result is an event (estimator_late) and the samples of the next period join
the next call. The pending call lives in the system, not in the context:
these systems serve one wall-clock run (the simulated clock keeps the synchronous systems).
"""

from __future__ import annotations

import copy
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import replace

import numpy as np
from safesysid.systems.estimation.system import SysIdEstimator, SysIdState, estimate_update
from safesysid.systems.planner.safe_planner import PlanResult
from safesysid.systems.planner.system import ExcitingPlanner
from safesysid.systems.planner.trajectory_source import Piece

from ..estimation import EstimatorError
from .realtime import lower_realtime

# Test hook (docs/hardware.md, faults): SAFESYSID_WORKER_FAULT="die:K" or "hang:K" makes the
# worker's K-th job (0-based, planner and estimator jobs counted together) exit or hang.
WORKER_FAULT_ENV = "SAFESYSID_WORKER_FAULT"
MAX_DETAIL_SIZE = 1000


class BackgroundWorker:
    """Two forked worker processes, one per lane, each running its jobs in order: the planner's
    calls and the estimator's updates (in one process a planning call waited behind an update of
    up to 1 s and missed t_p). The planner's lane runs ahead of the estimator's (LANE_NICE)."""

    def __init__(self, *, realtime: bool = True) -> None:
        """realtime: the loops run SCHED_FIFO (or will): the workers go below them (LANE_NICE)."""
        self._pools = {
            lane: ProcessPoolExecutor(
                max_workers=1,
                mp_context=multiprocessing.get_context("fork"),
                initializer=_worker_init,
                initargs=(nice if realtime else None,),
            )
            for lane, nice in LANE_NICE.items()
        }
        self._jobs = 0
        self._clock_zero = 0.0
        self.fault = os.environ.get(WORKER_FAULT_ENV, "")
        # Per lane, each collected job's (CPU [s], wall [s]) in its worker: a share well below 1 is a
        # worker starved of CPU by the loops (docs/hardware.md).
        self.job_times: dict[str, list[tuple[float, float]]] = {lane: [] for lane in LANE_NICE}

    def start(self) -> None:
        """Fork the workers now, before the clock starts (a fork stalls the loop for tens of ms).
        They inherit every system registered so far (register): jobs name them instead of shipping them."""
        for pool in self._pools.values():
            if not getattr(pool, "_processes", None):  # not forked yet (a job forks its lane)
                pool.submit(int).result()

    def submit(self, fn: Callable, *args: object, lane: str) -> Future:
        job, self._jobs = self._jobs, self._jobs + 1
        submitted = time.time()
        future = self._pools[lane].submit(_timed, fn, _fault_of(self.fault, job), *args)
        future.submitted, future.lane = submitted, lane
        return future

    def clock_started(self) -> None:
        """The run's clock starts now: a call submitted during the set-up is timed from here."""
        self._clock_zero = time.time()

    def latency(self, future: Future) -> tuple[object, float]:
        """(the job's result, its latency [s] from its submission or the clock's start, whichever
        is later: the time it took of the run's clock)."""
        result, finished, cpu_s, wall_s = future.result()
        self.job_times[future.lane].append((cpu_s, wall_s))
        return result, max(0.0, finished - max(future.submitted, self._clock_zero))

    def shutdown(self) -> None:
        for pool in self._pools.values():
            processes = list((getattr(pool, "_processes", None) or {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            for process in processes:
                process.kill()  # a hung job must not outlive the run


# Each lane's niceness (where the loops run SCHED_FIFO and may set it: realtime.lower_realtime).
LANE_NICE = {"planner": -10, "estimator": -5}


def _worker_init(nice: int | None) -> None:
    """Below the loops' priority (realtime.lower_realtime; None: the loops are not real-time) and
    one BLAS thread (2 cores)."""
    from threadpoolctl import threadpool_limits

    if nice is not None:
        lower_realtime(nice)
    threadpool_limits(1)


def _fault_of(text: str, job: int) -> str:
    kind, _, index = text.partition(":")
    return kind if kind in ("die", "hang") and index.isdigit() and int(index) == job else ""


def _timed(fn, fault: str, *args):
    """(fn(*args), the wall time it finished [s], its CPU time [s], its duration [s])."""
    if fault == "die":
        os._exit(3)
    if fault == "hang":
        time.sleep(3600.0)
    cpu, wall = time.process_time(), time.perf_counter()
    result = fn(*args)
    return result, time.time(), time.process_time() - cpu, time.perf_counter() - wall


# Systems a forked worker inherits: a job names one by its key (pickling a planner's precomputed
# tables on every call would hold this process's interpreter for tens of ms).
_REGISTRY: dict[int, object] = {}
_CAPS: dict[int, float] = {}  # in the worker: each planner's configured wall-time cap [s]
_OVERRUN: dict[int, float] = {}  # in the worker: each planner's longest call past its cap [s]


def register(system: object) -> int:
    _REGISTRY[id(system)] = system
    return id(system)


def _plan_job(key, submitted, t_start, q, v, a, thetas, k_init, rng, mode, past):
    planner = ExcitingPlanner._planner_at(_REGISTRY[key], t_start)
    configured = _CAPS.setdefault(key, planner.config.max_solve_time_s)
    # The wall-time cap counts from the submission at t_k, not from when the worker got to it, and
    # leaves room for the work after the solver stops (the certification of the point found), as
    # long as the longest such overrun so far: with less than a core it took 0.2-0.4 s.
    cap = configured - (time.time() - submitted) - _OVERRUN.get(key, 0.0)
    planner.config = replace(planner.config, max_solve_time_s=max(0.05, cap))
    started = time.perf_counter()
    res = planner.plan(q, v, a, *thetas, k_init=k_init, rng=rng, mode=mode, past=past)
    overrun = time.perf_counter() - started - planner.config.max_solve_time_s
    _OVERRUN[key] = max(_OVERRUN.get(key, 0.0), overrun)
    # Large details (the certified swept spheres, for drawing) stay here: unpickling them in the
    # run's process would hold its interpreter, and so the 1 kHz loop, for tens of ms.
    small = {k: v for k, v in res.details.items() if np.size(v) <= MAX_DETAIL_SIZE}
    return replace(res, details=small), rng


class WallClockPlanner(ExcitingPlanner):
    """ExcitingPlanner whose calls run one period ahead in `worker` (module docstring)."""

    def __init__(self, *args, worker: BackgroundWorker, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.worker = worker
        self.key = register(self)
        self.pending = None  # (future, start time of the plan it computes, its start state, its thetas)
        self.latencies_s: list[float] = []  # each call's submission-to-result time (vs t_p)
        self._invocations = 0

    def _planner_at(self, t):
        return _PlanAhead(self, t)


class _PlanAhead:
    """What ExcitingPlanner._plan_into calls at t: the result of the call started one period ago."""

    def __init__(self, system: WallClockPlanner, t: float) -> None:
        self.system, self.t = system, t

    def plan(self, q, v, a, *thetas, k_init, rng, mode, past):
        system, t = self.system, self.t
        system._invocations += 1
        if system.pending is None:  # from rest at q0, before the arm moves: in this process
            res = ExcitingPlanner._planner_at(system, t).plan(
                q, v, a, *thetas, k_init=k_init, rng=rng, mode=mode, past=past
            )
        else:
            res = self._collect(q, v, a, rng)
        system.pending = None
        if res.ok and system._invocations < system._num_plans:
            self._submit(res, thetas, rng, mode, past)
        return res

    def _collect(self, q, v, a, rng) -> PlanResult:
        future, t_start, start, thetas = self.system.pending
        if not future.done():
            future.cancel()
            reason = f"the call for the plan starting at {t_start:.3f} s had not returned by then"
            return PlanResult(ok=False, status="deadline_missed", reason=reason)
        (res, rng_after), latency = self.system.worker.latency(future)  # a dead worker raises: planner_error
        self.system.latencies_s.append(latency)
        if not all(np.allclose(x, y, atol=1e-9) for x, y in zip(start, (q, v, a))):
            return PlanResult(ok=False, status="start_mismatch", reason="the plan was computed from another state")
        rng.bit_generator.state = rng_after.bit_generator.state
        return replace(res, thetas=thetas)  # certified with the estimate of its submission

    def _submit(self, res: PlanResult, thetas, rng, mode, past) -> None:
        system, t_next = self.system, self.t + self.system._period
        start = Piece(self.t, res.trajectory, res.q_end).evaluate(t_next)
        thetas = tuple(np.array(x, float) for x in thetas)
        args = (
            system.key,
            time.time(),
            t_next,
            *start,
            thetas,
            res.k,
            copy.deepcopy(rng),
            mode,
            past,
        )
        system.pending = (system.worker.submit(_plan_job, *args, lane="planner"), t_next, start, thetas)


class WallClockEstimator(SysIdEstimator):
    """SysIdEstimator whose updates run in `worker`, published one period later."""

    def __init__(self, *args, worker: BackgroundWorker, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.worker = worker
        self.pending = None  # (future, the time its samples end)
        self.latencies_s: list[float] = []
        self.events_late: list[dict] = []

    def _update(self, t, run: SysIdState, state) -> SysIdState:
        if self.pending is not None:
            future, t_data = self.pending
            if not future.done():
                detail = f"the update on the samples up to {t_data:.3f} s has not returned: the box is kept"
                self.events_late.append(dict(t=t, kind="estimator_late", detail=detail))
                return run  # its samples and the new ones go to the next call
            self.pending = None
            try:
                outcome, latency = self.worker.latency(future)
                self.latencies_s.append(latency)
            except Exception as err:  # noqa: BLE001 -- a dead worker: the update is lost, the box kept
                outcome = EstimatorError(f"worker failed: {type(err).__name__}: {err}")
            run = self._apply(t, run, run.estimator, outcome, state)
        if not run.samples:
            return replace(run, history=run.history + ({"t": t, "skipped": "no valid samples"},))
        try:
            future = self.worker.submit(_estimate_job, id(self), run.estimator, data_of(run), self.n, lane="estimator")
        except Exception as err:  # noqa: BLE001 -- the worker is gone: no more updates, the box kept
            detail = f"no estimator update: {type(err).__name__}: {err}"
            self.events_late.append(dict(t=t, kind="estimator_worker_failed", detail=detail))
            return run
        run, data = self._take(run)
        self.pending = (future, float(data[-1, 0]))
        return run


# In the worker: each wall-clock estimator's IncrementalEstimator, advanced by its jobs. Only the
# Estimate comes back: unpickling the whole estimator (its segments grow with the data) would hold
# the run's interpreter, and so the 1 kHz loop, for tens of ms. The run's context keeps the initial one.
_ADVANCED: dict[int, object] = {}


def _estimate_job(key: int, initial: object, data: np.ndarray, n: int) -> object:
    estimator, outcome = estimate_update(_ADVANCED.get(key, initial), data, n)
    _ADVANCED[key] = estimator
    return outcome


def data_of(run: SysIdState) -> np.ndarray:
    return np.array(run.samples)
