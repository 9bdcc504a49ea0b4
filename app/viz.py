"""Meshcat: the arm, payload and obstacles (from SceneGraph), the planned trajectory of the end
effector, and (toggle "planner/swept" in the Meshcat controls) the over-approximated spheres
the planner certified; with a task phase, the task path. Every run is recorded and saved as a
self-contained replay.html: the camera framed on the arm's workspace, the phases named in a
banner that follows the animation time."""

from __future__ import annotations

import html
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # Drake's visualizer is imported when a run shows or records
    from pydrake.geometry import Meshcat, MeshcatVisualizer
    from pydrake.systems.framework import DiagramBuilder, OutputPort

PLAN_PATH = "planner/plan"
SWEPT_PATH = "planner/swept"
TASK_PATH = "task/path"
VISUALIZER_PREFIX = "visualizer"  # Drake's default, named so body_path can address a body
PHASE_COLOURS = {"identification": "#1f66ff", "task": "#1a9e3a", "settle": "#8a8a8a"}


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
    if hasattr(live, "viewer"):  # progress.RunDisplay: the CLI keeps serving it after the run
        live.viewer = meshcat
    return meshcat


def add_visualizer(builder: DiagramBuilder, query_object_port: OutputPort, meshcat: Meshcat) -> MeshcatVisualizer:
    """Meshcat on a station's exported SceneGraph query port (the SceneGraph is inside it)."""
    from pydrake.geometry import MeshcatVisualizer, MeshcatVisualizerParams, Role

    params = MeshcatVisualizerParams()
    params.role = Role.kIllustration
    params.prefix = VISUALIZER_PREFIX
    return MeshcatVisualizer.AddToBuilder(builder, query_object_port, meshcat, params)


def draw_plan(
    meshcat: Meshcat,
    points_world: np.ndarray,
    index: int,
    *,
    rgba: tuple[float, float, float, float] = (0.1, 0.4, 1.0, 1.0),
) -> None:
    """Polyline of the planned end-effector path (3 x N points in world)."""
    from pydrake.geometry import Rgba

    meshcat.SetLine(f"{PLAN_PATH}/{index}", np.asarray(points_world, float).T, 3.0, Rgba(*rgba))


def draw_swept_spheres(meshcat: Meshcat, centres: np.ndarray, radii: np.ndarray, *, index: int, every: int = 4) -> None:
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


if TYPE_CHECKING:  # what a replay is framed on
    from collections.abc import Sequence

    from safesysid.systems.config import Obstacle
    from safesysid.systems.model.robot_model import RobotModel


@dataclass
class ReplayScene:
    """What replay.html frames and names: the logged joint positions q and desired positions qd
    (N x n) at times t, and the phases [(name, t0, t1)] (figures.phases_of)."""

    robot: RobotModel
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    phases: list
    obstacles: Sequence[Obstacle] = ()  # scenario Obstacles: those within REACH_M of the base are framed too
    hidden_from: Sequence[tuple[str, float]] = ()  # (Meshcat path, t): hidden in the recording from t on


REACH_M = 1.2  # Gen3 reach (0.9 m) plus a held dumbbell and margin: obstacles beyond are not framed


def _box_corners(box: Obstacle) -> np.ndarray:
    from pydrake.math import RollPitchYaw

    rot = RollPitchYaw(box.rpy_rad).ToRotationMatrix().matrix()
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    return np.asarray(box.xyz_m, float) + (signs * np.asarray(box.size_m, float) / 2) @ rot.T


def frame_camera(
    meshcat: Meshcat,
    points: np.ndarray,
    direction: tuple[float, float, float] = (1.0, -1.1, 0.75),
    *,
    fov_deg: float = 75.0,
    margin: float = 1.0,
) -> tuple[np.ndarray, float]:
    """Aim Meshcat's default camera at the bounding box of `points` (N x 3, world) from
    `direction`, close enough that the box's enclosing sphere fills the (vertical) field of view."""
    points = np.asarray(points, float).reshape(-1, 3)
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 0.4)
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    distance = margin * radius / np.sin(np.radians(fov_deg) / 2)
    meshcat.SetCameraPose(centre + distance * d, centre)
    return centre, distance


def frame_points(robot: RobotModel, q: np.ndarray, obstacles: Sequence[Obstacle] = ()) -> np.ndarray:
    """What the camera frames: the base, the link origins and the grasp point at the
    configurations q (N x n), and the corners of the obstacles within REACH_M of the base."""
    q = np.atleast_2d(np.asarray(q, float))
    points = [np.zeros((1, 3)), robot.forward_kinematics(q).p.reshape(-1, 3), _grasp_path(robot, q)]
    points += [_box_corners(b) for b in obstacles if np.linalg.norm(b.xyz_m) < REACH_M]
    return np.vstack(points)


def _grasp_path(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    kin = robot.forward_kinematics(np.asarray(q, float))
    ee = robot.end_effector
    return kin.p[:, ee] + kin.R[:, ee] @ robot.extra["grasp_point"]


def decorate(
    meshcat: Meshcat | None, visualizer: MeshcatVisualizer | None, scene: ReplayScene, *, samples: int = 200
) -> None:
    """Camera on the arm's swept workspace, the task path (desired gripper centre over the task
    phase, shown from the task's start in the recording). No-op without a visualizer."""
    if visualizer is None:
        return
    from pydrake.geometry import Rgba

    every = max(1, len(scene.t) // samples)
    frame_camera(meshcat, frame_points(scene.robot, scene.q[::every], scene.obstacles))
    for name, t0, t1 in scene.phases:
        if name != "task":
            continue
        inside = (scene.t >= t0) & (scene.t <= t1)
        if inside.sum() < 2:
            continue
        path = _grasp_path(scene.robot, scene.qd[inside][:: max(1, inside.sum() // samples)])
        meshcat.SetLine(TASK_PATH, path.T, 3.0, Rgba(0.1, 0.62, 0.23, 1.0))
        recording = visualizer.get_mutable_recording()
        full = f"/drake/{TASK_PATH}"
        recording.SetProperty(0, full, "visible", False)
        recording.SetProperty(recording.frame(t0), full, "visible", True)
    recording = visualizer.get_mutable_recording()
    for path, t in scene.hidden_from:
        recording.SetProperty(0, path, "visible", True)
        recording.SetProperty(recording.frame(t), path, "visible", False)


def body_path(frame_name: str) -> str:
    """Meshcat path of a body's geometry under the run's visualizer (frame_name: SceneGraph's scoped
    frame name, 'model_instance::body', as MeshcatVisualizer lays the tree out)."""
    return f"/drake/{VISUALIZER_PREFIX}/" + frame_name.replace("::", "/")


def phase_banner(phases: list[tuple[str, float, float]]) -> str:
    """HTML + script appended to replay.html: the phases with their times, the current one (from
    the Meshcat animation time) highlighted."""
    items = "".join(
        f'<span data-t0="{t0:.3f}" data-t1="{t1:.3f}" style="padding:1px 6px;margin-right:4px;border-radius:3px;'
        f'border:2px solid {PHASE_COLOURS.get(name, "#555")}">{html.escape(name)} {t0:.1f}-{t1:.1f} s</span>'
        for name, t0, t1 in phases
    )
    script = (
        "setInterval(function(){var a=window.viewer&&viewer.animator;if(!a)return;var t=a.time||0;"
        "document.querySelectorAll('#safesysid-phases span').forEach(function(s){var on=t>=+s.dataset.t0&&"
        "t<=+s.dataset.t1;s.style.fontWeight=on?'bold':'normal';s.style.background=on?'#ffffcc':'';});"
        "document.getElementById('safesysid-time').textContent='t = '+t.toFixed(2)+' s';},200);"
    )
    return (
        '<div id="safesysid-phases" style="position:fixed;left:8px;bottom:8px;font:13px sans-serif;'
        'background:rgba(255,255,255,0.85);padding:4px 8px;border-radius:4px;z-index:10" '
        f"data-phases='{html.escape(json.dumps(phases))}'>{items}"
        '<span id="safesysid-time" style="border:none"></span></div>'
        f"<script>{script}</script>"
    )


def add_phase_banner(path: Path, phases: list[tuple[str, float, float]]) -> None:
    """Name the phases in a written replay.html (no-op when there is none)."""
    path = Path(path)
    if phases and path.exists():
        page = path.read_text()
        path.write_text(page.replace("</body>", phase_banner(phases) + "\n</body>", 1))
