"""The task phase's torque certificate against the time scale (app/task_run.certify_task) for the
paper's experiments (scenarios/experiment_{a,b,c}.yaml) and the methods whose box is fixed
before the task (conservative: Table II; wrong: no payload, zero width): the certificate at
every scale of the grid 1 .. task.max_time_scale, the scale the task is played at, or refused.
ours and random latch the estimator's box at the switch, so theirs is per run (summary.json
task.time_scales_tried; `safesysid compare`'s table).

    python experiments/task_time_scales.py     # prints a markdown table (docs/task-phase.md)
"""

from __future__ import annotations

METHODS = ("conservative", "wrong")


def certificates(name: str, method: str, scales=None) -> tuple[float, list[tuple[float, float]]]:
    """(the task trajectory's duration at 1x, [(scale, certificate)] over `scales`, by default the
    scenario's whole grid) of experiment `name` with `method`'s task box."""
    from safesysid.scenario import SCENARIOS_DIR, load_scenario
    from safesysid.systems import methods
    from safesysid.systems.model import parameter_sources
    from safesysid.systems.model.loading import robot_from_scenario
    from safesysid.systems.task.check import phase_certificate, time_scale_grid
    from safesysid.systems.task.phase import task_plan

    scenario = load_scenario(SCENARIOS_DIR / f"{name}.yaml")
    problem, plan = task_plan(scenario)
    theta0, box = parameter_sources.task_parameters(
        methods.method_spec(method), robot_from_scenario(scenario), scenario
    )
    grid = scales or time_scale_grid(scenario.task.max_time_scale, scenario.task.time_scale_step)
    thetas = (theta0, box.lo, box.hi)
    return plan.trajectory.duration, [(s, phase_certificate(problem, [plan.trajectory], thetas, scale=s)) for s in grid]


def main() -> None:
    rows = []
    for name in ("experiment_a", "experiment_b", "experiment_c"):
        for method in METHODS:
            duration, tried = certificates(name, method)
            played = next((f"{s:g}x ({duration * s:.2f} s)" for s, r in tried if r <= 1.0), "refused")
            rows.append((name, method, played, tried))
    scales = [s for s, _ in rows[0][3]]
    print("| experiment | method | played at | " + " | ".join(f"{s:g}x" for s in scales) + " |")
    print("|" + "---|" * (3 + len(scales)))
    for name, method, played, tried in rows:
        print(f"| {name} | {method} | {played} | " + " | ".join(f"{r:.3f}" for _, r in tried) + " |")
    _, beyond = certificates("experiment_a", "conservative", [5.0, 10.0, 100.0, 1000.0])
    print("\nexperiment_a conservative beyond the cap: " + ", ".join(f"{s:g}x {r:.4f}" for s, r in beyond))


if __name__ == "__main__":
    main()
