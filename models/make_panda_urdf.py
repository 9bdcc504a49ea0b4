"""Writes panda.urdf and panda_spheres.yaml: the Franka Emika Panda (FER) 7-DoF arm with its hand.

Source of every figure below: github.com/frankaemika/franka_description, commit
b299b39d9692bfae795184df32a98ce7778d56af (2025-03-21): robots/fer/kinematics.yaml (joint
origins), robots/fer/inertials.yaml (link masses, centres of mass, inertias), robots/fer/
joint_limits.yaml (position, velocity and torque limits: 87 N m on joints 1-4, 12 N m on 5-7),
robots/fer/dynamics.yaml (Coulomb friction 0.2 N m, damping 0.003 N m s/rad),
end_effectors/franka_hand/inertials.yaml and end_effectors/common/franka_hand.xacro (hand and
finger inertials, the hand's mount at the flange rotated -pi/4, fingers at z 0.0584, the TCP at
z 0.1034). The link shapes are Franka's published coarse capsules (robots/common/franka_arm.xacro
and franka_hand.xacro `collision_capsule`), link 1's trimmed at its foot so that it stands clear
of the floor (the base covers that part); the fingers are boxes, held open on a 32 mm handle.
The motors' reflected inertia is not published there: ARMATURE_KGM2 = 0.1 kg m^2 per joint is
the figure of MuJoCo Menagerie's Panda (franka_emika_panda/panda.xml, joint armature).
The files in the repository are not copied: this script writes the URDF from the figures.

The hand is its own link welded to panda_link7 (Drake merges it into the end-effector body);
the fingers are fixed and lumped into the hand. Shapes are both visual and collision geometry.
The planner's spheres come from the collision shapes by the generic generator
(models/cover_spheres.py). Run `python models/make_panda_urdf.py` after editing the figures.
"""

from pathlib import Path

import numpy as np
import yaml
from safesysid.models.urdf_parts import inertial_xml, shape_xml

HERE = Path(__file__).parent
PARAMS = yaml.safe_load((HERE / "panda_params.yaml").read_text())["joints"]
HALF_PI = np.pi / 2

# kinematics.yaml: (xyz, rpy) of joints 1..7 in the parent link; joint 8 (flange) z = 0.107.
JOINTS = [
    ((0, 0, 0.333), (0, 0, 0)),
    ((0, 0, 0), (-HALF_PI, 0, 0)),
    ((0, -0.316, 0), (HALF_PI, 0, 0)),
    ((0.0825, 0, 0), (HALF_PI, 0, 0)),
    ((-0.0825, 0.384, 0), (-HALF_PI, 0, 0)),
    ((0, 0, 0), (HALF_PI, 0, 0)),
    ((0.088, 0, 0), (HALF_PI, 0, 0)),
]
FLANGE_Z, HAND_YAW, FINGER_Z, TCP_Z = 0.107, -np.pi / 4, 0.0584, 0.1034
# inertials.yaml: (mass, com, [ixx, iyy, izz, ixy, ixz, iyz]) of link0..link7.
LINKS = [
    (2.3966, (-0.0172, 0.0004, 0.0745), (0.0090, 0.0115, 0.0085, 0.0, 0.0020, 0.0)),
    (
        2.7907,
        (0.00033, -0.02204, -0.04762),
        (0.01564782655, 0.01439883526, 0.00500443991, 5.31236e-6, -3.676721e-5, -0.00248480843),
    ),
    (
        2.5420,
        (0.00038, -0.09211, 0.01908),
        (0.01662427728, 0.00462501261, 0.01545124526, 3.086077e-5, 8.3594e-6, 0.0035589983),
    ),
    (
        2.2513,
        (0.05152, 0.01696, -0.02971),
        (0.00631741992, 0.00866285493, 0.00657804051, 0.00097309955, 0.00292525834, 0.00093469224),
    ),
    (
        2.2037,
        (-0.05113, 0.05825, 0.01698),
        (0.00784585566, 0.00649543136, 0.01003079917, -0.00339591957, 0.00158704074, -0.00181477884),
    ),
    (
        2.2855,
        (-0.00005, 0.03730, -0.09280),
        (0.02297014781, 0.02095060919, 0.00430606551, -9.49345e-6, -2.063156e-5, 0.00382345782),
    ),
    (
        1.353,
        (0.06572, -0.00371, 0.00153),
        (0.00087964522, 0.00277796968, 0.00286701969, -0.00021487814, -0.00011911662, 1.274322e-5),
    ),
    (
        0.35973,
        (0.00089, -0.00044, 0.05491),
        (0.00019541063, 0.00019210361, 0.00017936256, 1.65231e-6, 1.48826e-6, -1.31132e-6),
    ),
]
HAND = (0.6544, (-0.0000376, 0.0119128, 0.0207260), (0.00186, 0.00030, 0.00174, 0.0, 0.0, -0.00002))
FINGER = (0.0291, (0, 0.0152850, 0.0219675), (0.00000849, 0.00000853, 0.00000177, 0.0, 0.0, -0.00000106))
FINGER_OPENING_M = 0.016  # each finger's travel (0..0.04): open on a 32 mm dumbbell handle
# Capsules (centre, axis, radius, length between the cap centres) per link, link frame (link 7's
# rotated by +pi/4 about z, as Franka's self-collision link is).
CAPSULES = {
    "panda_link0": [((-0.075, 0, 0.06), "x", 0.06, 0.03)],
    "panda_link1": [((0, 0, -0.1565), "z", 0.06, 0.213)],  # Franka's: z -0.1915, length 0.283
    "panda_link2": [((0, 0, 0), "z", 0.06, 0.12)],
    "panda_link3": [((0, 0, -0.145), "z", 0.06, 0.15)],
    "panda_link4": [((0, 0, 0), "z", 0.06, 0.12)],
    "panda_link5": [((0, 0, -0.26), "z", 0.06, 0.10), ((0, 0.08, -0.13), "z", 0.025, 0.14)],
    "panda_link6": [((0, 0, -0.03), "z", 0.05, 0.08)],
    "panda_link7": [((0, 0, 0.01), "z", 0.04, 0.14), ((0.06, 0, 0.082), "x", 0.03, 0.01)],
    "panda_hand": [((0, 0, 0.04), "y", 0.04, 0.1), ((0, 0, 0.10), "y", 0.02, 0.1)],
}
LINK7_SC_YAW = np.pi / 4
# Finger boxes (franka_hand.xacro: the tip 17.5 x 15.2 x 18.5 mm at finger z 45.25 mm, the
# diagonal part and mount above it), one box per finger enclosing those, in the finger frame.
FINGER_BOX = ((0, 0.0125, 0.0285), (0.022, 0.025, 0.057))
COLORS = ["0.92 0.92 0.92 1", "0.25 0.25 0.28 1"]
SPHERE_MARGIN_M = 0.015


def _inertia_matrix(i):
    ixx, iyy, izz, ixy, ixz, iyz = i
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])


def _rot_z(yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _finger_frames():
    """(rotation, origin) of the two fingers in the hand frame (the right one turned pi about z)."""
    return [(_rot_z(yaw), _rot_z(yaw) @ [0, FINGER_OPENING_M, 0] + [0, 0, FINGER_Z]) for yaw in (0.0, np.pi)]


def hand_inertia():
    """Hand + both fingers (fixed) lumped: (mass, com, inertia about com) in the hand frame."""
    parts = [(HAND[0], np.array(HAND[1]), _inertia_matrix(HAND[2]))]
    for rot, origin in _finger_frames():
        parts.append((FINGER[0], rot @ FINGER[1] + origin, rot @ _inertia_matrix(FINGER[2]) @ rot.T))
    mass = sum(m for m, _, _ in parts)
    com = sum(m * c for m, c, _ in parts) / mass
    inertia = sum(i + m * ((c - com) @ (c - com) * np.eye(3) - np.outer(c - com, c - com)) for m, c, i in parts)
    return mass, com, inertia


def physically_valid(inertia):
    """The inertia itself if its principal moments satisfy the triangle inequality; otherwise the
    two smaller moments raised by one factor until they sum to 1.01 x the largest (Franka's link 4
    figures fail it: 0.00368 + 0.00796 < 0.01274 kg m^2). Principal axes are kept."""
    moments, axes = np.linalg.eigh(inertia)
    if moments[0] + moments[1] >= moments[2]:
        return inertia
    moments[:2] *= 1.01 * moments[2] / (moments[0] + moments[1])
    return axes @ np.diag(moments) @ axes.T


def _inertial(mass, com, inertia):
    return inertial_xml(
        mass, com, physically_valid(inertia if isinstance(inertia, np.ndarray) else _inertia_matrix(inertia))
    )


def _shape(name, xyz, rpy, geometry, color):
    return shape_xml(name, (xyz, rpy), geometry, material=f"c{color}", rgba=COLORS[color])


def _capsules(link, color):
    yaw = LINK7_SC_YAW if link == "panda_link7" else 0.0
    axis_rpy = {"x": (0, HALF_PI, 0), "y": (HALF_PI, 0, 0), "z": (0, 0, 0)}
    out = []
    for k, (centre, axis, radius, length) in enumerate(CAPSULES[link]):
        xyz = _rot_z(yaw) @ centre
        roll, pitch, _ = axis_rpy[axis]
        geometry = f'<capsule radius="{radius}" length="{length}"/>'
        out.append(_shape(f"{link}_capsule_{k}", xyz, (roll, pitch, yaw), geometry, color))
    return "".join(out)


def _fingers():
    (centre, size), out = FINGER_BOX, []
    for k, (rot, origin) in enumerate(_finger_frames()):
        yaw = 0.0 if k == 0 else np.pi
        geometry = f'<box size="{size[0]} {size[1]} {size[2]}"/>'
        out.append(_shape(f"panda_hand_finger_{k}", rot @ centre + origin, (0, 0, yaw), geometry, 1))
    return "".join(out)


def _joint(k):
    (xyz, rpy), j = JOINTS[k], PARAMS
    limit = (
        f'<limit lower="{j["position_lower_rad"][k]}" upper="{j["position_upper_rad"][k]}" '
        f'effort="{j["torque_limit_Nm"][k]}" velocity="{j["velocity_limit_rad_s"][k]}"/>'
    )
    return (
        f'  <joint name="panda_joint{k + 1}" type="revolute"><parent link="panda_link{k}"/>'
        f'<child link="panda_link{k + 1}"/><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" '
        f'rpy="{rpy[0]:.17g} {rpy[1]} {rpy[2]}"/><axis xyz="0 0 1"/>{limit}</joint>\n'
    )


def urdf():
    out = ['<?xml version="1.0"?>\n<!-- Generated by make_panda_urdf.py; edit that file. -->\n<robot name="panda">\n']
    for k, (mass, com, inertia) in enumerate(LINKS):
        name = f"panda_link{k}"
        out.append(f'  <link name="{name}">\n' + _inertial(mass, com, inertia) + _capsules(name, k % 2) + "  </link>\n")
    out.append('  <link name="panda_hand">\n' + _inertial(*hand_inertia()) + _capsules("panda_hand", 0))
    out.append(_fingers() + "  </link>\n")
    out += [_joint(k) for k in range(7)]
    out.append(
        '  <joint name="panda_hand_joint" type="fixed"><parent link="panda_link7"/><child link="panda_hand"/>'
        f'<origin xyz="0 0 {FLANGE_Z}" rpy="0 0 {HAND_YAW:.17g}"/></joint>\n</robot>\n'
    )
    return "".join(out)


if __name__ == "__main__":
    from safesysid.models.cover_spheres import model_spheres, spheres_yaml

    path = HERE / "panda.urdf"
    path.write_text(urdf())
    spheres = HERE / "panda_spheres.yaml"
    spheres.write_text(spheres_yaml(model_spheres(path, SPHERE_MARGIN_M), "make_panda_urdf.py"))
    print("wrote", path, "and", spheres, "hand mass", hand_inertia()[0])
