"""Meshcat: the arm, payload and obstacles (from SceneGraph), the planned trajectory of the end
effector, and (toggle "planner/swept" in the Meshcat controls) the over-approximated spheres
the planner certified. Every run is recorded and saved as a self-contained replay.html."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # Drake's visualizer is imported when a run shows or records
    from pydrake.geometry import Meshcat, MeshcatVisualizer
    from pydrake.systems.framework import DiagramBuilder, OutputPort

PLAN_PATH = "planner/plan"
SWEPT_PATH = "planner/swept"


def start_meshcat(live: bool) -> Meshcat:
    """Drake's Meshcat (a local server; works offline). Prints the URL when shown live."""
    import logging

    from pydrake.geometry import Meshcat

    drake_log = logging.getLogger("drake")
    level = drake_log.level
    if not live:  # recording only: no "listening at" banner
        drake_log.setLevel(logging.WARNING)
    try:
        meshcat = Meshcat()
    finally:
        drake_log.setLevel(level)
    if live:
        print(f"Meshcat: {meshcat.web_url()}", flush=True)
    return meshcat


def add_visualizer(builder: DiagramBuilder, query_object_port: OutputPort, meshcat: Meshcat) -> MeshcatVisualizer:
    """Meshcat on a station's exported SceneGraph query port (the SceneGraph is inside it)."""
    from pydrake.geometry import MeshcatVisualizer, MeshcatVisualizerParams, Role

    params = MeshcatVisualizerParams()
    params.role = Role.kIllustration
    return MeshcatVisualizer.AddToBuilder(builder, query_object_port, meshcat, params)


def draw_plan(
    meshcat: Meshcat,
    points_world: np.ndarray,
    index: int,
    rgba: tuple[float, float, float, float] = (0.1, 0.4, 1.0, 1.0),
) -> None:
    """Polyline of the planned end-effector path (3 x N points in world)."""
    from pydrake.geometry import Rgba

    meshcat.SetLine(f"{PLAN_PATH}/{index}", np.asarray(points_world, float).T, 3.0, Rgba(*rgba))


def draw_swept_spheres(meshcat: Meshcat, centres: np.ndarray, radii: np.ndarray, index: int, every: int = 4) -> None:
    """The planner's certified spheres (a subset of time intervals), hidden by default."""
    from pydrake.geometry import Rgba, Sphere
    from pydrake.math import RigidTransform

    centres = np.asarray(centres, float)
    radii = np.asarray(radii, float)
    for k in range(0, len(centres), every):
        for s, (c, r) in enumerate(zip(centres[k], radii[k])):
            path = f"{SWEPT_PATH}/{index}/{k}/{s}"
            meshcat.SetObject(path, Sphere(float(r)), Rgba(1.0, 0.55, 0.1, 0.08))
            meshcat.SetTransform(path, RigidTransform(c))
    meshcat.SetProperty(SWEPT_PATH, "visible", False)


def save_replay(meshcat: Meshcat, visualizer: MeshcatVisualizer, path: str | Path) -> Path:
    """Publish the recorded animation and write Meshcat's self-contained HTML."""
    visualizer.PublishRecording()
    path = Path(path)
    path.write_text(meshcat.StaticHtml())
    return path
