"""The parameters (theta0, [theta]) each method's controller and planner take, by source
(systems/methods.py: no payload, the Table II prior, the identified box)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.methods import IDENTIFIED, NO_PAYLOAD, PRIOR, MethodSpec

if TYPE_CHECKING:
    from safesysid.systems.config import Scenario
    from safesysid.systems.math.intervals import Interval
    from safesysid.systems.model.robot_model import RobotModel


def parameters_from(
    source: str, robot: RobotModel, scenario: Scenario, *, identified: Sequence[ArrayLike] | None = None
) -> tuple[np.ndarray, Interval]:
    """(theta0 (14 n), Interval) of a parameter source; IDENTIFIED needs `identified` =
    (theta0, lower, upper) of the estimator."""
    from safesysid.systems.math.intervals import Interval
    from safesysid.systems.model.uncertainty import prior_box

    if source == IDENTIFIED:
        if identified is None:
            raise ValueError("the identified parameters are needed (the estimator's theta0, lower, upper)")
        theta0, lo, hi = (np.asarray(x, float) for x in identified)
        return theta0, Interval(lo, hi)
    return prior_box(robot, scenario.initial_interval, scenario.noise, exact=source == NO_PAYLOAD)


def initial_parameters(spec: MethodSpec, robot: RobotModel, scenario: Scenario) -> tuple[np.ndarray, Interval]:
    """(theta0, [theta]) the run starts with: Table II when there is an identification phase
    (paper: "assigned to the planner and the controller at the beginning of the identification
    phase"), else the task's own (which then never identifies from data)."""
    source = PRIOR if spec.excitation is not None else spec.theta0_source
    return parameters_from(source, robot, scenario)


def task_parameters(
    spec: MethodSpec, robot: RobotModel, scenario: Scenario, *, identified: Sequence[ArrayLike] | None = None
) -> tuple[np.ndarray, Interval]:
    """(theta0, [theta]) the task-phase controller takes (identified: the estimator's final
    (theta0, lower, upper), for the IDENTIFIED methods). Where the model and box sources differ
    (none today) the box's source wins only for the box."""
    theta0, _ = parameters_from(spec.theta0_source, robot, scenario, identified=identified)
    _, box = parameters_from(spec.box_source, robot, scenario, identified=identified)
    return theta0, box
