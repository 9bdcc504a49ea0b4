"""Writes kinova_gen3.urdf: the Kinova Gen3 7-DoF arm for this project.

Kinematic and inertial figures are the public Gen3 (V12) values; visuals are primitive
capsules; collision geometry is the ARMOUR sphere set (offsets from joint frames, radii).
The last link is the end effector: bracelet + Robotiq 2F-85 (fingers fixed) lumped into one
rigid body of 1.28 kg, its frame the joint-7 child frame (tool along -z).
Run `python models/make_gen3_urdf.py` after editing the figures below.
"""
from pathlib import Path

import numpy as np
import yaml

PARAMS = yaml.safe_load(Path(__file__).with_name("kinova_gen3_params.yaml").read_text())["joints"]

# (name, origin xyz in the parent link, rpy, continuous?, unused) for joints 1..7; limits come
# from kinova_gen3_params.yaml.
JOINTS = [
    ("joint_1", (0, 0, 0.15643), (np.pi, 0, 0), True, None),
    ("joint_2", (0, 0.005375, -0.12838), (np.pi / 2, 0, 0), False, None),
    ("joint_3", (0, -0.21038, -0.006375), (-np.pi / 2, 0, 0), True, None),
    ("joint_4", (0, 0.006375, -0.21038), (np.pi / 2, 0, 0), False, None),
    ("joint_5", (0, -0.20843, -0.006375), (-np.pi / 2, 0, 0), True, None),
    ("joint_6", (0, 0.00017505, -0.10593), (np.pi / 2, 0, 0), False, None),
    ("joint_7", (0, -0.10593, -0.00017505), (-np.pi / 2, 0, 0), True, None),
]
# (link, mass, com, [ixx, iyy, izz, ixy, ixz, iyz] about com)
LINKS = [
    ("base_link", 1.697, (-0.000648, -0.000166, 0.084487), (0.004622, 0.004495, 0.002079, 9e-6, 6e-5, 9e-6)),
    ("shoulder_link", 1.3773, (-2.3e-5, -0.010364, -0.07336), (0.00457, 0.004831, 0.001409, 1e-6, 2e-6, 0.000448)),
    ("half_arm_1_link", 1.1636, (-4.4e-5, -0.09958, -0.013278), (0.011088, 0.001072, 0.011255, 5e-6, 0, -0.000691)),
    ("half_arm_2_link", 1.1636, (-4.4e-5, -0.006641, -0.117892), (0.010932, 0.011127, 0.001043, 0, -7e-6, 0.000606)),
    ("forearm_link", 0.9302, (-1.8e-5, -0.075478, -0.015006), (0.008147, 0.000631, 0.008316, -1e-6, 0, -0.0005)),
    ("spherical_wrist_1_link", 0.6781, (1e-6, -0.009432, -0.063883), (0.001596, 0.001607, 0.000399, 0, 0, 0.000256)),
    ("spherical_wrist_2_link", 0.6781, (1e-6, -0.045483, -0.00965), (0.001641, 0.00041, 0.001641, 0, 0, -0.000278)),
]
BRACELET = (0.5006, (-0.000281, -0.011402, -0.029798), (0.000587, 0.000369, 0.000609, 3e-6, 3e-6, 0.000118))
# Robotiq 2F-85 + coupling, fingers fixed: solid cylinder below the flange (z = -0.0615).
GRIPPER_MASS, GRIPPER_RADIUS, GRIPPER_LENGTH, FLANGE_Z = 0.7794, 0.042, 0.13, -0.0615
# ARMOUR collision spheres (offset in the joint's child frame, radius).
SPHERES = {
    "half_arm_1_link": [((0, -y, -0.01), 0.06) for y in (0.05, 0.11, 0.17, 0.24, 0.30, 0.36)] + [((0, -0.43, -0.01), 0.07)],
    "forearm_link": [((0, -0.07, 0), 0.07)] + [((0, -y, 0), 0.06) for y in (0.14, 0.21, 0.28, 0.32)],
    "spherical_wrist_2_link": [((0, -0.07, 0), 0.05), ((0, -0.14, 0), 0.05)],
    "end_effector_link": [((x, -0.06, -0.055), 0.02) for x in (-0.03, 0.0, 0.03)]
    + [((0, 0, -z), 0.05) for z in (0.10, 0.15, 0.20)],
}
COLORS = ["0.55 0.55 0.6 1", "0.8 0.8 0.82 1"]


def _inertia_matrix(i):
    ixx, iyy, izz, ixy, ixz, iyz = i
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])


def end_effector_inertia():
    """Bracelet + gripper lumped: (mass, com, inertia about com)."""
    m1, c1, i1 = BRACELET[0], np.array(BRACELET[1]), _inertia_matrix(BRACELET[2])
    m2, c2 = GRIPPER_MASS, np.array([0, 0, FLANGE_Z - GRIPPER_LENGTH / 2])
    r, h = GRIPPER_RADIUS, GRIPPER_LENGTH
    i2 = np.diag([m2 * (3 * r**2 + h**2) / 12] * 2 + [m2 * r**2 / 2])
    m = m1 + m2
    c = (m1 * c1 + m2 * c2) / m

    def shift(i, mass, d):
        return i + mass * (d @ d * np.eye(3) - np.outer(d, d))

    return m, c, shift(i1, m1, c1 - c) + shift(i2, m2, c2 - c)


def _capsule_to(vec, radius, color):
    """Visual capsule from the link origin to `vec` (the next joint origin)."""
    vec = np.asarray(vec, float)
    length = np.linalg.norm(vec)
    z = vec / length
    # rpy that rotates +z onto the direction (roll about x, then pitch about y).
    roll = np.arctan2(-z[1], z[2])
    pitch = np.arcsin(np.clip(z[0], -1, 1))
    mid = vec / 2
    return (f'    <visual><origin xyz="{mid[0]:.6g} {mid[1]:.6g} {mid[2]:.6g}" rpy="{roll:.6g} {pitch:.6g} 0"/>'
            f'<geometry><capsule radius="{radius}" length="{max(length - 2 * radius, 1e-3):.6g}"/></geometry>'
            f'<material name="c{color}"><color rgba="{COLORS[color]}"/></material></visual>\n')


def _inertial(mass, com, inertia):
    i = inertia if isinstance(inertia, np.ndarray) else _inertia_matrix(inertia)
    return (f'    <inertial><origin xyz="{com[0]:.9g} {com[1]:.9g} {com[2]:.9g}" rpy="0 0 0"/><mass value="{mass:.9g}"/>'
            f'<inertia ixx="{i[0, 0]:.9g}" iyy="{i[1, 1]:.9g}" izz="{i[2, 2]:.9g}" ixy="{i[0, 1]:.9g}" ixz="{i[0, 2]:.9g}" iyz="{i[1, 2]:.9g}"/></inertial>\n')


def _spheres(link):
    return "".join(f'    <collision name="{link}_sphere_{k}"><origin xyz="{o[0]} {o[1]} {o[2]}"/><geometry><sphere radius="{r}"/></geometry></collision>\n'
                   for k, (o, r) in enumerate(SPHERES.get(link, [])))


def urdf():
    out = ['<?xml version="1.0"?>\n<!-- Generated by make_gen3_urdf.py; edit that file. -->\n<robot name="kinova_gen3">\n']
    names = [l[0] for l in LINKS] + ["end_effector_link"]
    for k, (name, mass, com, inertia) in enumerate(LINKS):
        nxt = JOINTS[k][1]
        out.append(f'  <link name="{name}">\n' + _inertial(mass, com, inertia)
                   + _capsule_to(nxt, 0.045 if k < 5 else 0.04, k % 2) + _spheres(name) + "  </link>\n")
    m, c, i = end_effector_inertia()
    flange = (0, 0, FLANGE_Z)
    grip = (0, 0, FLANGE_Z - GRIPPER_LENGTH)
    out.append('  <link name="end_effector_link">\n' + _inertial(m, c, i) + _capsule_to(flange, 0.04, 1)
               + f'    <visual><origin xyz="0 0 {(FLANGE_Z + grip[2]) / 2:.6g}"/><geometry><box size="0.085 0.06 {GRIPPER_LENGTH}"/></geometry>'
               + '<material name="grip"><color rgba="0.15 0.15 0.15 1"/></material></visual>\n'
               + _spheres("end_effector_link") + "  </link>\n")
    for k, (jname, xyz, rpy, continuous, lim) in enumerate(JOINTS):
        kind = "continuous" if continuous else "revolute"
        effort, speed = PARAMS["torque_limit_Nm"][k], PARAMS["velocity_limit_rad_s"][k]
        bounds = "" if continuous else f'lower="{PARAMS["position_lower_rad"][k]}" upper="{PARAMS["position_upper_rad"][k]}" '
        limit = f'<limit {bounds}effort="{effort}" velocity="{speed}"/>'
        out.append(f'  <joint name="{jname}" type="{kind}"><parent link="{names[k]}"/><child link="{names[k + 1]}"/>'
                   f'<origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="{rpy[0]:.17g} {rpy[1]} {rpy[2]}"/><axis xyz="0 0 1"/>{limit}</joint>\n')
    out.append("</robot>\n")
    return "".join(out)


if __name__ == "__main__":
    path = Path(__file__).with_name("kinova_gen3.urdf")
    path.write_text(urdf())
    print("wrote", path, "end effector mass", end_effector_inertia()[0])
