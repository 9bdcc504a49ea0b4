"""Real-time factor (simulated s per s) of the closed loop, measured in one run next to the plant
alone: real arm (1 kHz discrete MultibodyPlant, friction, sensor) + ARMOUR controller (interval
bounds over all 14 n parameters) + Bezier source, loggers included.

Target (issue 16): the closed loop of ours >= 4x real time on one core. The machine is shared,
so each factor is given on the wall clock AND on this process's CPU time (what the loop costs
with a core to itself), with the load average. Also in the same run: the law alone per step
(fast path systems/controller/armour_fast.py and the reference armour.armour_control, i.e. after/before),
the closed loop with the reference law, the baseline controllers' loops, and the whole online
diagram (planner, estimator, safety monitor) per method of safesysid.systems.config.METHODS.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import numpy as np
from safesysid.benchmarks.scaling import load_average, png
from safesysid.closed_loop import build_closed_loop
from safesysid.scenario import load_scenario
from safesysid.systems.config import METHODS
from safesysid.systems.controller import armour as C
from safesysid.systems.controller import systems as controller_systems
from safesysid.systems.controller.armour_fast import FastArmourLaw, FastControllerDynamics
from safesysid.systems.math.bezier import QuinticBezier
from safesysid.systems.math.intervals import Interval
from safesysid.systems.model import uncertainty
from safesysid.systems.model.loading import robot_from_scenario

TARGET_RTF = 4.0


class ReferenceArmourController(controller_systems.ArmourController):
    """The ARMOUR LeafSystem on the reference path (armour.armour_control with ControllerDynamics,
    inputs read twice per step): the 'before' of the fast path, timed in the same run."""

    def __init__(self, robot, gains):
        super().__init__(robot, gains)
        self.dyn = C.ControllerDynamics(robot)

    def _calc_law(self, context, value):
        *args, theta0, lo, hi = self._raw_inputs(context)
        value.set_value(C.armour_control(self.dyn, self.gains.armour, *args, theta0, Interval(lo, hi)))

    def _calc_torque(self, context, output):
        controller_systems.ControllerBase._calc_torque(self, context, output)


@contextlib.contextmanager
def _reference_armour():
    """closed_loop.add_controller builds ReferenceArmourController for kind 'armour' inside."""
    make = controller_systems.make_controller

    def reference(kind, robot, gains, time_step):
        return (
            ReferenceArmourController(robot, gains)
            if kind == "armour"
            else make(kind, robot, gains, time_step=time_step)
        )

    controller_systems.make_controller = reference
    try:
        yield
    finally:
        controller_systems.make_controller = make


@contextlib.contextmanager
def _replayed_law():
    """The loop around the law, for the per-step breakdown: the first loop run inside records the
    ARMOUR system's law outputs by (time, state); the later runs return the recorded output
    instead of computing it, so the plant gets the same torques (the same steps) while the law
    costs its input reads and a lookup. Freezing the law's first output instead changed what the
    plant did, and so its cost: the breakdown then gave the law ~0 us."""
    calc = controller_systems.ArmourController._calc_law
    recorded = {}

    def replay(self, context, value):
        q, v, *_ = self._raw_inputs(context)  # the law's inputs are read as the live law reads them
        key = (context.get_time(), q.tobytes(), v.tobytes())
        if key not in recorded:
            calc(self, context, value)
            recorded[key] = value.get_value()
        else:
            value.set_value(recorded[key])

    controller_systems.ArmourController._calc_law = replay
    try:
        yield
    finally:
        controller_systems.ArmourController._calc_law = calc


def _best_rtf(prepare, sim_s, repeat):
    """(wall factor, CPU factor), each the best of `repeat` runs; prepare() builds and
    initializes a Simulator (not timed), the timed part is AdvanceTo(sim_s)."""
    best, best_cpu = np.inf, np.inf
    for _ in range(repeat):
        sim = prepare()
        t0, c0 = time.perf_counter(), time.process_time()
        sim.AdvanceTo(sim_s)
        best, best_cpu = min(best, time.perf_counter() - t0), min(best_cpu, time.process_time() - c0)
    return sim_s / best, sim_s / best_cpu


def _simulator(diagram, arm, q0):
    from pydrake.systems.analysis import Simulator

    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    arm.seed_noise(ctx)
    arm.set_state(ctx, np.asarray(q0, float))
    sim.Initialize()
    return sim


def _trajectory(s, robot):
    q0 = np.array(s.q0_rad)
    q_end = q0 + np.array(s.planner.k_range_rad) * np.linspace(-1, 1, robot.n)
    return q0, (QuinticBezier(q0, np.zeros(robot.n), np.zeros(robot.n), s.planner.duration_s), q_end)


def loop_rtf(s, robot, theta0, box, kind, sim_s, repeat):
    """(wall, CPU) real-time factor of the closed loop with controller `kind` (loggers on)."""
    q0, trajectory = _trajectory(s, robot)

    def prepare():
        loop = build_closed_loop(s, trajectory, theta0, theta_box=box, kind=kind, robot=robot)
        return _simulator(loop.diagram, loop.arm, q0)

    return _best_rtf(prepare, sim_s, repeat)


def loop_command(s, robot, theta0, box, sim_s):
    """(t, u): the torque the ARMOUR loop commands over sim_s (what the plant alone replays)."""
    from safesysid.closed_loop import simulate_closed_loop

    q0, trajectory = _trajectory(s, robot)
    logs = simulate_closed_loop(
        build_closed_loop(s, trajectory, theta0, theta_box=box, kind="armour", robot=robot), q0, sim_s
    )
    return logs["torque"]


def plant_rtf(s, robot, sim_s, repeat, command=None):
    """(wall, CPU) real-time factor of the real arm station alone: the loop's command (t, u)
    replayed as a zero-order hold from C++ (zero torque if None: the arm then falls and its
    contacts change the cost), the same state and measured-torque loggers as the closed loop."""
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput, TrajectorySource
    from pydrake.trajectories import PiecewisePolynomial
    from safesysid.systems.plant.station import add_real_arm

    def prepare():
        builder = DiagramBuilder()
        arm = add_real_arm(builder, s, robot=robot)
        if command is None:
            source = ConstantVectorSource(np.zeros(robot.n))
        else:
            t, u = command
            source = TrajectorySource(PiecewisePolynomial.ZeroOrderHold(t, u.T))
        builder.Connect(builder.AddSystem(source).get_output_port(), arm.commanded_torque_input)
        for port in (arm.state_output, arm.measured_torque_output):
            LogVectorOutput(port, builder, s.plant.time_step_s)
        return _simulator(builder.Build(), arm, s.q0_rad)

    return _best_rtf(prepare, sim_s, repeat)


def method_rtf(s, method, sim_s):
    """(wall, CPU) real-time factor of the whole online diagram of `method` (app/online.py:
    planner, estimator when identifying, controller, safety monitor, loggers) over sim_s."""
    from safesysid.online import build_online

    def prepare():
        built = build_online(s, method)
        return _simulator(built.diagram, built.arm, s.q0_rad)

    return _best_rtf(prepare, sim_s, 1)


def law_cpu_us(s, robot, theta0, box, count):
    """CPU µs per evaluation of the law at random states: reference and fast path, interleaved
    (the same load for both); also the largest difference of their outputs (relative to 1 + |x|)."""
    gains = C.ArmourGains(np.asarray(s.controller.Kr, float), s.controller.alpha, s.controller.V_max)
    dyn, fast = C.ControllerDynamics(robot), FastArmourLaw(FastControllerDynamics(robot), gains)
    rng = np.random.default_rng(0)
    states = rng.normal(size=(count, 5, robot.n))
    ref_s = fast_s = 0.0
    worst = 0.0
    for q, v, q_d, qd_d, qdd_d in states:
        c0 = time.process_time()
        a = C.armour_control(dyn, gains, q, v, q_d, qd_d, qdd_d, theta0, box)
        c1 = time.process_time()
        b = fast(q, v, q_d, qd_d, qdd_d, theta0, box.lo, box.hi)
        c2 = time.process_time()
        ref_s, fast_s = ref_s + c1 - c0, fast_s + c2 - c1
        worst = max(worst, float(np.max(np.abs(a.u - b.u) / (1 + np.abs(a.u)))))
    return 1e6 * ref_s / count, 1e6 * fast_s / count, worst


def run(quick: bool = False, out: Path | None = None) -> dict:
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    robot = robot_from_scenario(s)
    ii = s.initial_interval
    theta0, box = uncertainty.parameter_box(robot, ii.nominal, ii.lower, ii.upper)
    sim_s = 1.0 if quick else 3.0
    repeat = 1 if quick else 3
    result = {"sim_time_s": sim_s, "time_step_s": s.plant.time_step_s, "target_real_time_factor": TARGET_RTF}
    result["load_average_at_start"] = load_average()
    command = loop_command(s, robot, theta0, box, sim_s)
    result["plant_alone_real_time_factor"], result["plant_alone_cpu_real_time_factor"] = plant_rtf(
        s, robot, sim_s, repeat, command
    )
    rtf, rtf_cpu = loop_rtf(s, robot, theta0, box, "armour", sim_s, repeat)
    result["armour_real_time_factor"], result["armour_cpu_real_time_factor"] = rtf, rtf_cpu
    with _reference_armour():
        ref = loop_rtf(s, robot, theta0, box, "armour", sim_s, repeat)
    result["armour_reference_real_time_factor"], result["armour_reference_cpu_real_time_factor"] = ref
    # Per-step CPU cost of everything but the controller path = 1 / plant factor.
    result["plant_cpu_us_per_step"] = 1e6 * s.plant.time_step_s / result["plant_alone_cpu_real_time_factor"]
    result["armour_loop_cpu_us_per_step"] = 1e6 * s.plant.time_step_s / rtf_cpu
    result["armour_reference_loop_cpu_us_per_step"] = 1e6 * s.plant.time_step_s / ref[1]
    with _replayed_law():
        loop_rtf(s, robot, theta0, box, "armour", sim_s, 1)  # records the law's outputs
        replayed = loop_rtf(s, robot, theta0, box, "armour", sim_s, repeat)
    # Breakdown of the loop's step: plant | law (in the loop, caches cold) | the rest around it.
    result["armour_loop_law_replayed_cpu_us_per_step"] = 1e6 * s.plant.time_step_s / replayed[1]
    result["armour_law_in_loop_cpu_us_per_step"] = (
        result["armour_loop_cpu_us_per_step"] - result["armour_loop_law_replayed_cpu_us_per_step"]
    )
    result["meets_target_wall"] = bool(rtf >= TARGET_RTF)
    result["meets_target_cpu"] = bool(rtf_cpu >= TARGET_RTF)
    ref_us, fast_us, worst = law_cpu_us(s, robot, theta0, box, 300 if quick else 2000)
    result["armour_law_reference_cpu_us_per_step"] = ref_us
    result["armour_law_cpu_us_per_step"] = fast_us
    result["armour_law_fast_vs_reference_max_rel_diff"] = worst
    kinds = () if quick else ("pid", "adaptive", "adaptive_robust")
    for kind in kinds:
        result[f"{kind}_real_time_factor"], result[f"{kind}_cpu_real_time_factor"] = loop_rtf(
            s, robot, theta0, box, kind, sim_s, 1
        )
    methods = {}
    for method in () if quick else METHODS:
        wall, cpu = method_rtf(load_scenario(), method, sim_s)
        methods[method] = {"real_time_factor": wall, "cpu_real_time_factor": cpu}
    result["online_by_method"] = methods
    result["load_average_at_end"] = load_average()
    labels = ["plant alone", "armour (fast)", "armour (reference)", *kinds, *(f"online {m}" for m in methods)]
    cpu = [
        result["plant_alone_cpu_real_time_factor"],
        rtf_cpu,
        ref[1],
        *(result[f"{k}_cpu_real_time_factor"] for k in kinds),
        *(m["cpu_real_time_factor"] for m in methods.values()),
    ]
    result["plot"] = _bar_plot(png(out, "sim_real_time_factor"), labels, cpu)
    return result


def _bar_plot(path, labels, cpu_factors):
    if path is None:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    ax.barh(labels, cpu_factors)
    ax.axvline(TARGET_RTF, color="k", ls="--", lw=1, label=f"target {TARGET_RTF:g}x")
    ax.axvline(1.0, color="r", ls=":", lw=1, label="real time")
    ax.set(xlabel="CPU-time real-time factor (sim s / CPU s)", title="Closed-loop simulation speed")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def profile_online(method="ours", sim_s=3.0, top=25):
    """cProfile of the online diagram over sim_s (the top items by cumulative time, printed)."""
    import cProfile
    import pstats

    from safesysid.online import build_online

    s = load_scenario()
    built = build_online(s, method)
    sim = _simulator(built.diagram, built.arm, s.q0_rad)
    profiler = cProfile.Profile()
    profiler.runcall(sim.AdvanceTo, sim_s)
    pstats.Stats(profiler).sort_stats("cumulative").print_stats(top)


def advance_loop(sim_s: float) -> None:
    """Only the ARMOUR closed loop of `run` (8 lb, Table II prior) advanced over sim_s: the target
    of an instruction count, e.g. `valgrind --tool=callgrind --collect-atstart=no
    '--toggle-collect=*AdvanceTo*' python -m safesysid.benchmarks.bench_sim --loop 0.3` (instructions
    per step = the collected count / 300)."""
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    robot = robot_from_scenario(s)
    ii = s.initial_interval
    theta0, box = uncertainty.parameter_box(robot, ii.nominal, ii.lower, ii.upper)
    q0, trajectory = _trajectory(s, robot)
    loop = build_closed_loop(s, trajectory, theta0, theta_box=box, kind="armour", robot=robot)
    _simulator(loop.diagram, loop.arm, q0).AdvanceTo(sim_s)


if __name__ == "__main__":
    import json
    import sys

    if "--profile-online" in sys.argv:
        profile_online()
    elif "--loop" in sys.argv:
        advance_loop(float(sys.argv[sys.argv.index("--loop") + 1]))
    else:
        print(json.dumps(run(quick="--quick" in sys.argv, out=Path("out/bench")), indent=2))
