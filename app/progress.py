"""What a person sees while something runs: a progress bar for batches of runs (compare, sweep),
and for one `safesysid run` the live options (wait for a browser, real-time rate, keep serving
the recording), a progress line (phase, plan k/N, sim time vs wall time) and a clean Ctrl-C."""

from __future__ import annotations

import signal
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from pydrake.geometry import Meshcat
    from pydrake.systems.analysis import Simulator
    from safesysid.systems.config import Scenario


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 60}m{seconds % 60:02d}s" if seconds >= 60 else f"{seconds}s"


class Progress:
    """A progress bar on stderr: redrawn in place on a terminal, one line per step otherwise
    (logs and CI keep every line). No dependency (neither tqdm nor rich is installed)."""

    def __init__(self, total: int, label: str, stream: TextIO | None = None, *, width: int = 24) -> None:
        self.total, self.label, self.width = total, label, width
        self.stream = stream or sys.stderr
        self.done = 0
        self.start = time.perf_counter()
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def line(self, note: str = "") -> str:
        frac = self.done / self.total if self.total else 1.0
        filled = int(round(frac * self.width))
        elapsed = time.perf_counter() - self.start
        eta = f", ~{_clock(elapsed / self.done * (self.total - self.done))} left" if 0 < self.done < self.total else ""
        bar = "#" * filled + "-" * (self.width - filled)
        return f"{self.label} [{bar}] {self.done}/{self.total} {_clock(elapsed)}{eta}" + (f"  {note}" if note else "")

    def step(self, note: str = "") -> None:
        self.done += 1
        text = self.line(note)
        self.stream.write(f"\r\x1b[K{text}" if self.tty else text + "\n")
        if self.tty and self.done == self.total:
            self.stream.write("\n")
        self.stream.flush()


@dataclass
class RunDisplay:
    """Options of one interactive run. Truthy when Meshcat is shown live, so it stands where the
    `live_meshcat` flag of run_online stood."""

    meshcat: bool = False
    wait_for_viewer: bool = False
    realtime_rate: float = 0.0  # 0: as fast as possible
    keep_serving: bool = True  # after the run, serve the recording until Ctrl-C
    progress: bool = True
    after_s: float = 3.0  # the progress line starts once a run has taken this long (wall)
    every_s: float = 2.0
    interrupted: bool = False
    viewer: Meshcat | None = field(default=None, repr=False)  # the Meshcat instance (viz.start_meshcat)

    def __bool__(self) -> bool:
        return self.meshcat


@contextmanager
def interruptible(display: RunDisplay) -> Iterator[RunDisplay]:
    """The first Ctrl-C asks the running simulation to stop (display.interrupted; the run then
    writes what it has), a second one raises KeyboardInterrupt as usual."""

    def on_sigint(signum, frame):
        if display.interrupted:
            raise KeyboardInterrupt
        display.interrupted = True
        print("\nCtrl-C: stopping the simulation, writing what was done (again to abort)", file=sys.stderr)

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield display
    finally:
        signal.signal(signal.SIGINT, previous)


def phase_at(t: float, scenario: Scenario, switch_time_s: float | None) -> str:
    """`identification, plan k/N` before the task switch (or the horizon), `task` after it."""
    p = scenario.planner
    horizon = (p.num_plans - 1) * p.replan_period_s + p.duration_s
    if switch_time_s is not None and t >= switch_time_s:
        return "task"
    if t > horizon:
        return "after identification"
    k = min(int(t // p.replan_period_s) + 1, p.num_plans)
    return f"identification, plan {k}/{p.num_plans}"


def wait_for_viewer(display: RunDisplay, poll_s: float = 0.2) -> None:
    """Block until a browser has the Meshcat page open (or Ctrl-C)."""
    meshcat = display.viewer
    if meshcat is None or meshcat.GetNumActiveConnections() > 0:
        return
    print(f"waiting for a browser at {meshcat.web_url()} (Ctrl-C to skip) ...", file=sys.stderr, flush=True)
    while meshcat.GetNumActiveConnections() == 0 and not display.interrupted:
        time.sleep(poll_s)
    display.interrupted = False  # a Ctrl-C here skips the wait, it does not stop the run


def watch(
    simulator: Simulator,
    scenario: Scenario,
    display: RunDisplay | bool,
    *,
    switch_time_s: float | None = None,
    stream: TextIO | None = None,
) -> None:
    """Before a run's first AdvanceTo: apply the live options and install a monitor that prints
    the progress line and stops the simulation on Ctrl-C (display.interrupted). No-op unless
    `display` is a RunDisplay (compare and sweep workers pass nothing)."""
    from pydrake.systems.framework import EventStatus

    if not isinstance(display, RunDisplay):
        return
    if display.meshcat and display.viewer is not None:  # the live view framed on the arm at its start
        from safesysid import viz
        from safesysid.systems.model.loading import robot_from_scenario

        viz.frame_camera(
            display.viewer, viz.frame_points(robot_from_scenario(scenario), scenario.q0_rad, scenario.obstacles)
        )
    if display.meshcat and display.wait_for_viewer:
        wait_for_viewer(display)
    if display.realtime_rate > 0:
        simulator.set_target_realtime_rate(display.realtime_rate)
    stream = stream or sys.stderr
    wall0 = time.perf_counter()
    next_print = [wall0 + display.after_s]

    warned = [False]

    def monitor(context):
        if display.interrupted:
            return EventStatus.ReachedTermination(None, "interrupted (Ctrl-C)")
        now = time.perf_counter()
        if display.progress and now >= next_print[0]:
            t = context.get_time()
            wall = now - wall0
            phase = phase_at(t, scenario, switch_time_s)
            stream.write(f"run: {phase}; sim {t:.2f} s in {wall:.1f} s wall ({t / wall:.2f}x real time)\n")
            warning = realtime_shortfall(t, wall, display.realtime_rate)
            if warning and not warned[0]:
                stream.write(warning + "\n")
                warned[0] = True
            stream.flush()
            next_print[0] = now + display.every_s
        return EventStatus.Succeeded()

    simulator.set_monitor(monitor)


def realtime_shortfall(sim_s: float, wall_s: float, target_rate: float, *, tolerance: float = 0.9) -> str | None:
    """The warning a live run prints when it does not reach its --realtime-rate (None when it does,
    or when no rate was asked)."""
    if target_rate <= 0 or wall_s <= 0 or sim_s / wall_s >= tolerance * target_rate:
        return None
    return (
        f"run: warning: --realtime-rate {target_rate:g} not reached ({sim_s / wall_s:.2f}x): "
        "this machine simulates slower than that; the motion in the viewer is slowed down"
    )


def _stop_on_signals() -> None:
    """Ctrl-C and SIGTERM end the serve phase even where the shell started the process with SIGINT
    ignored (a script's `cmd &`), which Python otherwise inherits."""

    def stop(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)


def serve_until_interrupt(display: RunDisplay) -> None:
    """Keep the Meshcat server (recording loaded) up until Ctrl-C, as Drake's examples do."""
    if not (display.meshcat and display.keep_serving and display.viewer is not None):
        return
    _stop_on_signals()
    try:
        print(
            f"Meshcat: the recording is loaded at {display.viewer.web_url()} (Open Controls > Animations > play); "
            "Ctrl-C to quit",
            file=sys.stderr,
            flush=True,
        )
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
