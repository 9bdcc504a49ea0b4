"""The planner's world after an obstacle appears (faults.appearing_obstacles): a planner that
knows it, and how far the running plan's certified swept spheres stay from it."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from safesysid.systems.config import Obstacle
    from safesysid.systems.planner.safe_planner import PlanResult, SafePlanner


def with_obstacle(planner: SafePlanner, obstacle: Obstacle) -> SafePlanner:
    """A copy of a SafePlanner whose world also holds `obstacle` (a scenario Obstacle record)."""
    import copy

    from safesysid.systems.planner.reachability import Boxes

    new = Boxes.from_obstacles([obstacle])
    out = copy.copy(planner)
    old = planner.boxes
    out.boxes = Boxes(
        *(
            np.concatenate([a, b])
            for a, b in zip((old.centre, old.rotation, old.half_size), (new.centre, new.rotation, new.half_size))
        ),
        list(old.names) + new.names,
    )
    return out


def remaining_plan_clearance(
    result: PlanResult, elapsed_s: float, obstacles: Iterable[Obstacle]
) -> tuple[float, float]:
    """(smallest margin, first time since the plan's start where it is < 0) of a plan's certified
    swept spheres (PlanResult.details: every point of sphere s during interval i lies in the ball
    (centres[i, s], radii[i, s])) against `obstacles` (scenario Obstacle records), over the
    intervals that end after elapsed_s. A margin >= 0 keeps the plan's collision certificate for
    these obstacles too."""
    from safesysid.systems.planner.reachability import Boxes, box_signed_distance

    boxes = Boxes.from_obstacles(list(obstacles))

    edges = np.asarray(result.details["interval_edges_s"])
    keep = edges[1:] > elapsed_s
    centres = result.details["sphere_centres"][keep]  # (i, s, 3)
    radii = result.details["sphere_radii"][keep]
    first_t, margin = float("inf"), float("inf")
    for o in range(len(boxes.centre)):
        pts = centres.reshape(-1, 3)
        sd, _ = box_signed_distance(
            pts,
            np.broadcast_to(boxes.centre[o], pts.shape),
            np.broadcast_to(boxes.rotation[o], (len(pts), 3, 3)),
            np.broadcast_to(boxes.half_size[o], pts.shape),
        )
        slack = sd.reshape(radii.shape) - radii
        margin = min(margin, float(slack.min()) if slack.size else margin)
        bad = np.flatnonzero(np.any(slack < 0, axis=1))
        if len(bad):
            first_t = min(first_t, float(edges[:-1][keep][bad[0]]))
    return margin, first_t
