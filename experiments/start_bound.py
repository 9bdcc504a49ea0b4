"""Can the planner certify holding still at q0? Prints its answer for a scenario and layers.

    python experiments/start_bound.py SCENARIO.yaml [--scenario-text YAML ...]

Builds the planner exactly as a run does (prior box, tracking tube from the controller's V_max,
Kr and alpha, obstacles, payload spheres) and asks for the plan at rest at q0 (k = 0): prints
"certified" or the planner's reason (e.g. the torque bound of the joint that fails). The tuning
table of docs/own-robot.md is this command's output.
"""

from __future__ import annotations

import argparse

import numpy as np


def start_reason(scenario) -> str:
    from safesysid.systems.controller.armour import ArmourGains, tracking_bounds_for
    from safesysid.systems.model.loading import robot_from_scenario
    from safesysid.systems.model.uncertainty import prior_box
    from safesysid.systems.planner.safe_planner import SafePlanner
    from safesysid.systems.plant.arm_plant import scenario_dumbbell

    robot = robot_from_scenario(scenario)
    theta0, box = prior_box(robot, scenario.initial_interval, scenario.noise)
    c = scenario.controller
    tracking = tracking_bounds_for(robot, ArmourGains(np.asarray(c.Kr, float), c.alpha, c.V_max), box.lo)
    planner = SafePlanner(
        robot, scenario.planner, obstacles=scenario.obstacles, payload=scenario_dumbbell(scenario), tracking=tracking
    )
    rest = np.zeros(robot.n)
    return planner.problem(np.asarray(scenario.q0_rad, float), rest, rest, theta0, box.lo, box.hi).reason


def main(argv=None):
    from safesysid.scenario import load_scenario

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("--scenario-text", action="append", default=[])
    args = parser.parse_args(argv)
    print(start_reason(load_scenario(args.scenario, overrides=args.scenario_text)) or "certified")


if __name__ == "__main__":
    main()
