"""`safesysid` command line (the verbs of README.md, "Commands").

Exit status: 0 success, 1 the run failed, 2 bad input (one line naming file and field);
compare and sweep exit 0 when they completed (their runs' failures are data).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence


class BadInput(ValueError):
    """Raised for user-input problems; printed as one line, exit code 2."""


def require_positive(**counts: int) -> None:
    """BadInput naming the first option (--trials, --workers, ...) below 1."""
    for name, value in counts.items():
        if value < 1:
            raise BadInput(f"--{name}: must be >= 1")


def _bad_input_types():
    from safesysid.joint_log import LogError
    from safesysid.systems.config import ScenarioError
    from safesysid.systems.model.robot_model import ModelError

    return (BadInput, LogError, ScenarioError, ModelError)


def _bag_options(p):
    p.add_argument("--topic", default="/joint_states", help="ROS bag logs: the sensor_msgs/JointState topic")
    p.add_argument(
        "--joints",
        type=lambda text: [x.strip() for x in text.split(",") if x.strip()],
        help="ROS bag logs: joint names in model order, comma separated (default: the model's)",
    )


def _add_scenario_text(p):
    p.add_argument(
        "--scenario-text",
        action="append",
        default=[],
        metavar="YAML",
        help="YAML layered over the scenario, changing only the keys it names "
        "(repeatable; e.g. --scenario-text 'noise: {torque_floor_Nm: 0.1}')",
    )


COMPLETED_EXIT = (
    "Exit status 0 when it completed: a run's failure is data in the table, not an error "
    "(1: interrupted or could not complete; 2: bad input)."
)
LOG_COLUMNS = (
    "Input joint log (CSV): header row, columns t [s, increasing], q1..qn [rad], v1..vn [rad/s], "
    "optional a1..an [rad/s^2], tau1..taun [N m]; other columns are ignored; n = the model's joints. "
    "Or a ROS bag of sensor_msgs/JointState (--topic)."
)


def _installed_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("safesysid")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown"


def _run_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run Algorithm 2 (plan, track, identify) on a scenario")
    p.add_argument("scenario", nargs="?", help="scenario YAML (default: scenarios/quickstart.yaml)")
    p.add_argument("--out", default="out/run", help="output folder")
    p.add_argument("--method", help="a method of the paper's table of comparisons (systems/methods.py)")
    p.add_argument("--seed", type=int)
    p.add_argument("--meshcat", action="store_true", help="show live in Meshcat (prints the URL)")
    p.add_argument(
        "--wait-for-viewer", action="store_true", help="with Meshcat: wait until a browser is connected, then simulate"
    )
    p.add_argument("--realtime-rate", type=float, default=0.0, help="target sim/wall rate (1 = real time; 0 = fast)")
    p.add_argument(
        "--arm",
        choices=("simulated", "lcm"),
        help="the arm: simulated in this process, or over LCM in wall-clock time (default: the scenario's arm.driver)",
    )
    p.add_argument("--no-fifo", action="store_true", help="--arm lcm: do not ask for SCHED_FIFO real-time scheduling")
    p.add_argument(
        "--no-serve", action="store_true", help="with Meshcat: exit after the run (default: serve until Ctrl-C)"
    )
    _add_scenario_text(p)


def _compare_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compare",
        help="methods x dumbbells x trials on a process pool; the paper's Table III row",
        description=f"Methods x dumbbells x trials; the paper's Table III row format. {COMPLETED_EXIT}",
    )
    p.add_argument("scenario")
    p.add_argument("--methods", default="ours,random", help="all, or comma-separated method names")
    p.add_argument("--dumbbells", help="4lb,6lb or 4lb..8lb (default: the scenario's dumbbell)")
    p.add_argument(
        "--trials", type=int, default=1, help="trials per method and dumbbell (seed = scenario seed + trial)"
    )
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    p.add_argument(
        "--stack",
        action="store_true",
        help="place each dumbbell on the lighter ones of --dumbbells (the paper's stacking; task.stack_on)",
    )
    p.add_argument("--out", default="out/compare")
    _add_scenario_text(p)


def _sweep_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sweep",
        help="randomized adversarial closed-loop trials; aggregate safety evidence",
        description=f"Randomized adversarial closed-loop trials; aggregate.json. {COMPLETED_EXIT}",
    )
    p.add_argument("scenario")
    p.add_argument("--trials", type=int, default=20)
    p.add_argument("--methods", help="comma-separated methods, or all (default: the scenario's)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="parallel trials (local pool or Ray CPUs)")
    p.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run the trials as Ray tasks: a local Ray instance, or the cluster at ADDRESS (auto: `ray start`'s)",
    )
    p.add_argument("--seed", type=int, default=0, help="trial k uses seed SEED + k")
    p.add_argument(
        "--nominal",
        action="store_true",
        help="plain random scenes (default: noise at the declared bound, robot parameters drawn in their box)",
    )
    p.add_argument("--out", default="out/sweep")
    _add_scenario_text(p)


def _sysid_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sysid",
        help="Algorithm 1 offline on a joint log",
        description="Algorithm 1 offline on a joint log; writes estimate.json and the interval plots. "
        f"{LOG_COLUMNS} Exit status: 0 identified (consistent, truth inside where known), "
        "1 the data contradict the declared bounds or the truth is outside, 2 bad input.",
    )
    p.add_argument(
        "log", help="joint log: CSV (t, q1..qn, v1..vn, optional a1..an, tau1..taun) or a ROS bag (see --topic)"
    )
    p.add_argument("--scenario", help="scenario YAML (robot, noise, estimator settings)")
    p.add_argument("--model", help="corrected_model.yaml from `safesysid diagnose`: the robot model to identify with")
    p.add_argument("--out", default="out/sysid")
    _bag_options(p)
    _add_scenario_text(p)


def _diagnose_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "diagnose",
        help="where and why a model and logs disagree",
        description=f"Where and why a model and logs disagree; diagnosis.json, report.md, corrected_model.yaml. "
        f"{LOG_COLUMNS} Exit status 0 when the diagnosis completed, 2 on bad input.",
    )
    p.add_argument("--model", help="URDF/SDF of a fixed-base arm, or a scenario YAML")
    p.add_argument("--fit", nargs="+", default=[], help="logs to fit effects on")
    p.add_argument("--check", nargs="+", default=[], help="held-out logs to score on")
    p.add_argument("--out", default="out/diagnose")
    p.add_argument(
        "--leave-one-out",
        action="store_true",
        help="hold each log (--fit and --check) out once, fit on the others; pooled held-out report",
    )
    p.add_argument("--self-check", action="store_true", help="blind test on simulated logs with withheld effects")
    p.add_argument("--cases", type=int, default=40, help="self-check: number of blind cases")
    p.add_argument("--workers", type=int, default=1, help="self-check: parallel processes")
    p.add_argument(
        "--hard", action="store_true", help="self-check: two effects per non-null case, 3%% noise, no accelerations"
    )
    p.add_argument("--seed", type=int, default=0)
    _bag_options(p)


def _arm_sim_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("arm-sim", help="the simulated arm behind LCM, in wall-clock time (docs/hardware.md)")
    p.add_argument("scenario", nargs="?", help="scenario YAML (default: scenarios/quickstart.yaml)")
    p.add_argument("--out", default="out/arm-sim", help="output folder (arm_summary.json, arm_log.csv)")
    p.add_argument("--duration", type=float, default=30.0, help="seconds of the arm's clock to serve")
    p.add_argument("--seed", type=int)
    p.add_argument("--no-fifo", action="store_true", help="do not ask for SCHED_FIFO real-time scheduling")
    _add_scenario_text(p)


def _bench_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="timing benchmarks")
    p.add_argument("--out", default="out/bench")
    p.add_argument("--quick", action="store_true", help="smaller sizes")


SUB_COMMANDS = (
    _run_parser,
    _compare_parser,
    _sweep_parser,
    _sysid_parser,
    _diagnose_parser,
    _arm_sim_parser,
    _bench_parser,
)  # each adds its verb's parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="safesysid", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {_installed_version()}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True
    for add in SUB_COMMANDS:
        add(sub)
    return parser


def _dispatch(args):
    # Each verb lives in its own module of app/ (safesysid.<module>.<function>(args)).
    handlers = {
        "run": ("safesysid.run_cli", "cmd_run"),
        "compare": ("safesysid.compare_cli", "cmd_compare"),
        "sweep": ("safesysid.sweep_cli", "cmd_sweep"),
        "sysid": ("safesysid.sysid_cli", "cmd_sysid"),
        "diagnose": ("safesysid.diagnose_cli", "cmd_diagnose"),
        "bench": ("safesysid.bench_cli", "cmd_bench"),
        "arm-sim": ("safesysid.arm_sim", "cmd_arm_sim"),
    }
    module_name, fn_name = handlers[args.verb]
    return getattr(importlib.import_module(module_name), fn_name)(args)


def _check_out(out: str | None) -> None:
    if out is not None and os.path.exists(out) and not os.path.isdir(out):
        raise BadInput(f"--out: {out} exists and is not a folder")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        _check_out(getattr(args, "out", None))
        return int(_dispatch(args) or 0)
    except _bad_input_types() as err:
        print(f"safesysid {args.verb}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
