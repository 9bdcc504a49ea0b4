"""Payloads held by the end effector: dumbbell shape, its exact inertia, and the combined
end-effector parameters theta_e (end effector + payload about the end-effector frame)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.model import inertial


@dataclass(frozen=True)
class Dumbbell:
    name: str
    mass_kg: float
    handle_radius_m: float
    handle_length_m: float
    head_radius_m: float
    head_length_m: float

    def parts(self) -> list[tuple[float, float, float, float]]:
        """(mass, x-offset of centre, radius, length) of the handle and the two heads."""
        vol = lambda r, l: np.pi * r * r * l  # noqa: E731
        v_handle = vol(self.handle_radius_m, self.handle_length_m)
        v_head = vol(self.head_radius_m, self.head_length_m)
        density = self.mass_kg / (v_handle + 2 * v_head)
        x_head = (self.handle_length_m + self.head_length_m) / 2
        return [
            (density * v_handle, 0.0, self.handle_radius_m, self.handle_length_m),
            (density * v_head, x_head, self.head_radius_m, self.head_length_m),
            (density * v_head, -x_head, self.head_radius_m, self.head_length_m),
        ]

    @property
    def length_m(self) -> float:
        return self.handle_length_m + 2 * self.head_length_m

    def theta_about_centre(self) -> np.ndarray:
        """theta in a frame at the dumbbell centre, x along the handle (exact for the shape)."""
        total = np.zeros(10)
        for m, x, r, l in self.parts():
            # Solid cylinder along x about its own centre.
            i_c = np.diag([m * r * r / 2, m * (3 * r * r + l * l) / 12, m * (3 * r * r + l * l) / 12])
            total += inertial.from_mass_com_inertia(m, [x, 0, 0], i_c)
        return total

    def covering_spheres(self) -> list[tuple[tuple[float, float, float], float]]:
        """Spheres (centre in the dumbbell frame, radius) that contain the shape."""
        out = []
        for _, x, r, l in self.parts()[1:]:  # heads: a sphere around each
            out.append(((x, 0.0, 0.0), float(np.hypot(r, l / 2))))
        out.append(((0.0, 0.0, 0.0), float(np.hypot(self.handle_radius_m, self.handle_length_m / 2))))
        return out


def load_dumbbells(path: str | Path) -> dict[str, Dumbbell]:
    import yaml

    path = Path(path)
    doc = yaml.safe_load(path.read_text())
    out = {}
    for name, fields in doc.items():
        try:
            out[str(name)] = Dumbbell(name=str(name), **{k: float(v) for k, v in fields.items()})
        except TypeError as err:
            raise ValueError(f"{path}: dumbbell {name}: {err}") from err
    return out


def payload_theta_in_end_effector(dumbbell: Dumbbell | None, grasp_point: ArrayLike) -> np.ndarray:
    """theta of the payload alone, about the end-effector frame origin (zeros without one)."""
    if dumbbell is None:
        return np.zeros(10)
    return inertial.shift_to(dumbbell.theta_about_centre(), grasp_point)
