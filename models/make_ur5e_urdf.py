"""Writes ur5e.urdf and ur5e_spheres.yaml: the Universal Robots UR5e (6 joints), a third arm
brought in by the steps of docs/own-robot.md only (no code of systems/ or app/ edited for it).

Source: github.com/UniversalRobots/Universal_Robots_ROS2_Description, commit
2221ec0f720fb1af99339eb891639b499b62f1da (2024-10-14): config/ur5e/default_kinematics.yaml
(joint origins), config/ur5e/physical_parameters.yaml (link masses, centres of mass, inertia
tensors and their rotations, link radii, shoulder and elbow offsets), config/ur5e/joint_limits.yaml
(+-2 pi, elbow +-pi; 180 deg/s; 150 N m on joints 1-3, 28 N m on 4-6). The reflected inertia is
not published there: ARMATURE 0.1 kg m^2 per joint is MuJoCo Menagerie's UR5e figure.
Link shapes are capsules of the published radii along each link (the upper arm and forearm tubes
at the shoulder and elbow offsets); the tool is the user's own: a 0.5 kg box gripper on the
flange (welded to wrist_3_link), the payload held 0.15 m out along the tool axis.
Run `python models/make_ur5e_urdf.py` after editing the figures.
"""

from pathlib import Path

import numpy as np
from safesysid.models.urdf_parts import inertial_xml, shape_xml

HERE = Path(__file__).parent
HALF_PI = np.pi / 2
NAMES = ["shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3"]
LINKS = ["base_link", "shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link"]
JOINTS = [  # (xyz, rpy) in the parent link: default_kinematics.yaml
    ((0, 0, 0.1625), (0, 0, 0)),
    ((0, 0, 0), (HALF_PI, 0, 0)),
    ((-0.425, 0, 0), (0, 0, 0)),
    ((-0.3922, 0, 0.1333), (0, 0, 0)),
    ((0, -0.0997, 0), (HALF_PI, 0, 0)),
    ((0, 0.0996, 0), (HALF_PI, np.pi, np.pi)),
]
LOWER = [-2 * np.pi, -2 * np.pi, -np.pi, -2 * np.pi, -2 * np.pi, -2 * np.pi]
VELOCITY = [np.pi] * 6
EFFORT = [150.0, 150.0, 150.0, 28.0, 28.0, 28.0]
ARMATURE = 0.1
# (mass, com, pitch of the tensor's frame, [ixx, iyy, izz]) per moving link: physical_parameters.yaml
INERTIALS = [
    (3.761, (0.0, -0.00193, -0.02561), 0.0, (0.0102675, 0.0102675, 0.00666)),
    (8.058, (-0.2125, 0.0, 0.11336), HALF_PI, (0.13388583541666665, 0.13388583541666665, 0.0151074)),
    (2.846, (-0.2422, 0.0, 0.0265), HALF_PI, (0.03120936758333333, 0.03120936758333333, 0.004095)),
    (1.37, (0.0, -0.01634, -0.0018), 0.0, (0.0025599, 0.0025599, 0.0021942)),
    (1.3, (0.0, 0.01634, -0.0018), 0.0, (0.0025599, 0.0025599, 0.0021942)),
    (0.365, (0.0, 0.0, -0.001159), 0.0, (9.890414008333333e-05, 9.890414008333333e-05, 0.0001321171875)),
]
BASE = (4.0, (0.0, 0.0, 0.025), (0.0061063, 0.0061063, 0.01125))  # base_mass; a 6 cm x 5 cm cylinder
SHOULDER_OFFSET, ELBOW_OFFSET = 0.138, 0.007
# Capsules (start, end, radius) per link, link frame.
CAPSULES = {
    "base_link": [((0, 0, 0.06), (0, 0, 0.1), 0.06)],
    "shoulder_link": [((0, 0, -0.04), (0, 0, 0.02), 0.06)],
    "upper_arm_link": [
        ((0, 0, 0.0), (0, 0, SHOULDER_OFFSET), 0.06),
        ((0, 0, SHOULDER_OFFSET), (-0.425, 0, SHOULDER_OFFSET), 0.054),
    ],
    "forearm_link": [((0, 0, 0.0), (0, 0, 0.12), 0.06), ((0, 0, ELBOW_OFFSET), (-0.3922, 0, ELBOW_OFFSET), 0.04)],
    "wrist_1_link": [((0, 0, -0.02), (0, 0, 0.02), 0.045), ((0, 0, 0), (0, -0.0997, 0), 0.045)],
    "wrist_2_link": [((0, 0, -0.02), (0, 0, 0.02), 0.045), ((0, 0, 0), (0, 0.0996, 0), 0.045)],
    "wrist_3_link": [((0, 0, -0.03), (0, 0, -0.01), 0.045)],
}
TOOL_MASS, TOOL_BOX = 0.5, (0.06, 0.08, 0.1)  # the user's gripper, centred 0.05 m out on the flange
GRASP_Z = 0.15
SPHERE_MARGIN_M = 0.015
COLORS = ["0.3 0.45 0.65 1", "0.8 0.8 0.82 1"]


def _rot_y(pitch):
    c, s = np.cos(pitch), np.sin(pitch)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _shape(name, xyz, rpy, geometry, color):
    return shape_xml(name, (xyz, rpy), geometry, material=f"u{color}", rgba=COLORS[color])


def _capsule(name, start, end, radius, color):
    start, end = np.asarray(start, float), np.asarray(end, float)
    vec = end - start
    axis = vec / np.linalg.norm(vec)
    roll, pitch = np.arctan2(-axis[1], axis[2]), np.arcsin(np.clip(axis[0], -1, 1))
    geometry = f'<capsule radius="{radius}" length="{np.linalg.norm(vec):.9g}"/>'
    return _shape(name, (start + end) / 2, (roll, pitch, 0.0), geometry, color)


def _link(k, name):
    if k == 0:
        inertial = inertial_xml(BASE[0], BASE[1], np.diag(BASE[2]))
    else:
        mass, com, pitch, moments = INERTIALS[k - 1]
        rot = _rot_y(pitch)
        inertial = inertial_xml(mass, com, rot @ np.diag(moments) @ rot.T)
    shapes = "".join(_capsule(f"{name}_capsule_{j}", *c, k % 2) for j, c in enumerate(CAPSULES[name]))
    return f'  <link name="{name}">\n{inertial}{shapes}  </link>\n'


def _tool():
    a, b, h = TOOL_BOX
    inertia = np.diag([b * b + h * h, a * a + h * h, a * a + b * b]) * TOOL_MASS / 12
    box = _shape("tool_box", (0, 0, h / 2), (0, 0, 0), f'<box size="{a} {b} {h}"/>', 1)
    return f'  <link name="tool">\n{inertial_xml(TOOL_MASS, (0, 0, h / 2), inertia)}{box}  </link>\n'


def urdf():
    out = ['<?xml version="1.0"?>\n<!-- Generated by make_ur5e_urdf.py; edit that file. -->\n<robot name="ur5e">\n']
    out += [_link(k, name) for k, name in enumerate(LINKS)] + [_tool()]
    for k, ((xyz, rpy), name) in enumerate(zip(JOINTS, NAMES)):
        limit = (
            f'<limit lower="{LOWER[k]:.9g}" upper="{-LOWER[k]:.9g}" effort="{EFFORT[k]}" velocity="{VELOCITY[k]:.9g}"/>'
        )
        out.append(
            f'  <joint name="{name}_joint" type="revolute"><parent link="{LINKS[k]}"/><child link="{LINKS[k + 1]}"/>'
            f'<origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="{rpy[0]:.17g} {rpy[1]:.17g} {rpy[2]:.17g}"/>'
            f'<axis xyz="0 0 1"/>{limit}</joint>\n'
        )
    out.append('  <joint name="tool_joint" type="fixed"><parent link="wrist_3_link"/><child link="tool"/></joint>\n')
    return "".join(out) + "</robot>\n"


def params_yaml():
    joints = [f"{n}_joint" for n in NAMES]
    fmt = lambda values: "[" + ", ".join(f"{v:.6g}" for v in values) + "]"  # noqa: E731
    return (
        "# Generated by make_ur5e_urdf.py; edit that file. Joint parameters of the UR5e (docs/own-robot.md).\n"
        "urdf: ur5e.urdf\nplanner_spheres: ur5e_spheres.yaml\nend_effector_link: tool\n"
        f"grasp_point_m: [0.0, 0.0, {GRASP_Z}]\njoints:\n"
        f"  names: [{', '.join(joints)}]\n"
        f"  position_lower_rad: {fmt(LOWER)}\n  position_upper_rad: {fmt(-np.asarray(LOWER))}\n"
        f"  velocity_limit_rad_s: {fmt(VELOCITY)}\n  torque_limit_Nm: {fmt(EFFORT)}\n"
        f"  armature_kgm2: {fmt([ARMATURE] * 6)}\n"
        "uncertainty:\n  link_inertial_ratio: 0.05\n  friction_ratio: 0.05\n"
    )


if __name__ == "__main__":
    from safesysid.models.cover_spheres import model_spheres, spheres_yaml

    (HERE / "ur5e.urdf").write_text(urdf())
    (HERE / "ur5e_params.yaml").write_text(params_yaml())
    spheres = model_spheres(HERE / "ur5e.urdf", SPHERE_MARGIN_M)
    (HERE / "ur5e_spheres.yaml").write_text(spheres_yaml(spheres, "make_ur5e_urdf.py"))
    print("wrote ur5e.urdf, ur5e_params.yaml, ur5e_spheres.yaml")
