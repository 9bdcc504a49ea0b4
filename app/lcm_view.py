"""`safesysid run --arm lcm --meshcat`: the live arm in Meshcat from the received status (the joint
positions the arm reports), the obstacles and the payload it is believed to hold.

A diagram of its own (a plant with the robot's URDF, the scenario's obstacles and the dumbbell
welded at the grasp point, a SceneGraph, Drake's MeshcatVisualizer) that StatusView, a system of
the run's diagram, poses and publishes at VIEW_RATE_HZ: the 1 kHz loop pays for one small
publish every 1 / VIEW_RATE_HZ s, never for a second plant stepping beside it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from pydrake.systems.framework import EventStatus, LeafSystem

if TYPE_CHECKING:
    from pydrake.geometry import Meshcat
    from pydrake.systems.framework import DiagramBuilder, OutputPort
    from safesysid.systems.config import Scenario
    from safesysid.systems.model.robot_model import RobotModel

VIEW_RATE_HZ = 30.0


def _view_diagram(robot: RobotModel, scenario: Scenario, meshcat: Meshcat):
    """(diagram, plant, visualizer): the scene as the run believes it, drawn on meshcat."""
    from pydrake.math import RigidTransform
    from pydrake.systems.framework import DiagramBuilder
    from safesysid.systems.model.robot_model import make_plant
    from safesysid.systems.plant.arm_plant import register_dumbbell_geometry, register_obstacles, scenario_dumbbell
    from safesysid.viz import add_visualizer

    builder = DiagramBuilder()
    plant, scene_graph, instance = make_plant(robot.source, builder=builder)
    register_obstacles(plant, scenario)
    dumbbell = scenario_dumbbell(scenario)
    if dumbbell is not None:
        from safesysid.systems.plant.arm_plant import dumbbell_spatial_inertia

        body = plant.AddRigidBody("payload", plant.AddModelInstance("payload"), dumbbell_spatial_inertia(dumbbell))
        ee = plant.GetBodyByName(robot.body_names[robot.end_effector], instance)
        plant.WeldFrames(ee.body_frame(), body.body_frame(), RigidTransform(robot.extra["grasp_point"]))
        register_dumbbell_geometry(plant, body, dumbbell)
    plant.Finalize()
    visualizer = add_visualizer(builder, scene_graph.get_query_output_port(), meshcat)
    return builder.Build(), plant, visualizer


class StatusView(LeafSystem):
    """Input state [q, v] (the received status); publishes the arm at q to Meshcat at VIEW_RATE_HZ."""

    def __init__(self, robot: RobotModel, scenario: Scenario, meshcat: Meshcat) -> None:
        super().__init__()
        self.n = robot.n
        self.diagram, self.plant, self.visualizer = _view_diagram(robot, scenario, meshcat)
        self.view_context = self.diagram.CreateDefaultContext()
        self.state = self.DeclareVectorInputPort("state", 2 * robot.n)
        self.DeclarePeriodicPublishEvent(1.0 / VIEW_RATE_HZ, 0.0, self._publish)
        self.DeclareForcedPublishEvent(self._publish)

    def _publish(self, context) -> EventStatus:
        q = np.asarray(self.state.Eval(context)[: self.n], float)
        plant_context = self.plant.GetMyMutableContextFromRoot(self.view_context)
        self.plant.SetPositions(plant_context, q)
        self.view_context.SetTime(context.get_time())
        self.visualizer.ForcedPublish(self.visualizer.GetMyContextFromRoot(self.view_context))
        return EventStatus.Succeeded()


def add_status_view(
    builder: DiagramBuilder, state_output: OutputPort, robot: RobotModel, scenario: Scenario, meshcat: Meshcat
) -> StatusView:
    view = builder.AddNamedSystem("status_view", StatusView(robot, scenario, meshcat))
    builder.Connect(state_output, view.state)
    return view
