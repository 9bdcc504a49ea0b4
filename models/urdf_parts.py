"""URDF text shared by the arm generators (make_panda_urdf.py, make_ur5e_urdf.py)."""

from __future__ import annotations

import numpy as np


def inertial_xml(mass: float, com, inertia: np.ndarray) -> str:
    """<inertial> of a body: mass, centre of mass and the 3x3 inertia about it (link frame)."""
    i = inertia
    return (
        f'    <inertial><origin xyz="{com[0]:.9g} {com[1]:.9g} {com[2]:.9g}"/><mass value="{mass:.9g}"/>'
        f'<inertia ixx="{i[0, 0]:.9g}" iyy="{i[1, 1]:.9g}" izz="{i[2, 2]:.9g}" '
        f'ixy="{i[0, 1]:.9g}" ixz="{i[0, 2]:.9g}" iyz="{i[1, 2]:.9g}"/></inertial>\n'
    )


def shape_xml(name: str, pose: tuple, geometry: str, *, material: str, rgba: str) -> str:
    """The same shape as visual and collision geometry (the referee measures what is shown);
    pose = (xyz, rpy)."""
    xyz, rpy = pose
    origin = f'<origin xyz="{xyz[0]:.9g} {xyz[1]:.9g} {xyz[2]:.9g}" rpy="{rpy[0]:.17g} {rpy[1]:.17g} {rpy[2]:.17g}"/>'
    colour = f'<material name="{material}"><color rgba="{rgba}"/></material>'
    visual = f"    <visual>{origin}<geometry>{geometry}</geometry>{colour}</visual>\n"
    return visual + f'    <collision name="{name}">{origin}<geometry>{geometry}</geometry></collision>\n'
