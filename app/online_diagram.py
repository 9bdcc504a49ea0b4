"""The parts of a built online diagram (app/online.py build_online), in a module of its own so
the task phase, the summary and the outputs that read it import no run."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pydrake.geometry import Meshcat, MeshcatVisualizer
    from pydrake.systems.framework import Diagram
    from pydrake.systems.primitives import VectorLogSink
    from safesysid.systems.controller.armour import TrackingBounds
    from safesysid.systems.controller.systems import ControllerBase
    from safesysid.systems.estimation.system import SysIdEstimator
    from safesysid.systems.math.intervals import Interval
    from safesysid.systems.planner.system import ExcitingPlanner
    from safesysid.systems.planner.trajectory_source import TaskPhaseSource
    from safesysid.systems.plant.safety_monitor import SafetyMonitor
    from safesysid.systems.plant.station import RealArm

# The parameter ports of the planner, the task phase source and the controllers.
THETA_NAMES = ("theta0", "theta_lower", "theta_upper")


@dataclass(kw_only=True)
class OnlineDiagram:
    """The online diagram and its parts (build_online fills it in as it adds them)."""

    arm: RealArm
    controller: ControllerBase
    theta_prior: tuple[np.ndarray, Interval]
    tracking: TrackingBounds
    meshcat: Meshcat | None
    diagram: Diagram | None = None  # None until built
    planner: ExcitingPlanner | None = None  # None: no planner (Fourier excitation, or none)
    estimator: SysIdEstimator | None = None
    monitor: SafetyMonitor | None = None  # None: the arm is reached over LCM (its referee is the arm side's)
    loggers: dict[str, VectorLogSink] = field(default_factory=dict)
    visualizer: MeshcatVisualizer | None = None
    source: TaskPhaseSource | None = None  # None: no task phase
    task: tuple = ()  # (TaskProblem, TaskResult) of the scenario's task
