"""Our Kinova Gen3 model: loads offline, one parameter file, end effector, link shapes and the
planner's separate spheres, payloads."""

import numpy as np
import pytest
from helpers import params_with_spheres
from safesysid.systems.model import inertial
from safesysid.systems.model.payload import load_dumbbells, payload_theta_in_end_effector
from safesysid.systems.model.robot_model import MODELS_DIR, ModelError, load_joint_parameters, load_robot, make_plant


def test_gen3_loads_with_one_parameter_set():
    robot = load_robot()
    jp = robot.joint_params
    assert robot.n == 7 and robot.body_names[robot.end_effector] == "end_effector_link"
    assert np.isclose(robot.theta_e[0], 1.28, atol=1e-3)
    assert jp.continuous.tolist() == [True, False, True, False, True, False, True]
    assert np.allclose(robot.theta[70:].reshape(7, 4)[:, 1], jp.viscous)
    assert all(inertial.is_physically_consistent(robot.theta[10 * i : 10 * i + 10]) for i in range(7))


def test_urdf_limits_come_from_the_parameter_file():
    """The generated URDF carries the YAML's limits: Drake sees the same figures."""
    _, jp = load_joint_parameters(MODELS_DIR / "kinova_gen3_params.yaml")
    plant, _, _ = make_plant(MODELS_DIR / "kinova_gen3.urdf")
    plant.Finalize()
    for k, name in enumerate(jp.names):
        joint = plant.GetJointByName(name)
        assert np.isclose(joint.velocity_upper_limits()[0], jp.velocity_limit[k])
        if np.isfinite(jp.position_upper[k]):
            assert np.isclose(joint.position_upper_limits()[0], jp.position_upper[k])
        actuator = plant.GetJointActuatorByName(f"{name}_actuator")
        assert actuator.effort_limit() == jp.torque_limit[k]


def test_collision_geometry_is_the_link_shapes_and_the_planner_spheres_are_separate():
    """The URDF collides with what it shows (capsules, gripper box); no sphere of the planner's
    set is in it. The planner's spheres come from the sphere file, some on every link."""
    from pydrake.geometry import Role
    from safesysid.systems.planner.reachability import arm_spheres

    plant, sg, _ = make_plant(MODELS_DIR / "kinova_gen3.urdf", scene_graph=True)
    plant.Finalize()
    inspector = sg.model_inspector()

    def shapes(role):
        return sorted(
            (inspector.GetName(inspector.GetFrameId(g)), repr(inspector.GetShape(g)), str(inspector.GetPoseInFrame(g)))
            for g in inspector.GetAllGeometryIds(role)
        )

    collision = shapes(Role.kProximity)
    assert collision == shapes(Role.kIllustration) and len(collision) == 9
    assert not any("Sphere" in shape for _, shape, _ in collision)
    robot = load_robot()
    spheres = arm_spheres(robot)
    links = {name.rsplit("_sphere_", 1)[0] for name in spheres.names}
    assert links == {"base_link", *robot.body_names}
    assert np.all(spheres.body[[n.startswith("base_link") for n in spheres.names]] == -1)  # fixed to the world


def test_a_bad_sphere_file_names_the_file_and_the_field(tmp_path):
    from safesysid.systems.planner.reachability import arm_spheres

    spheres = tmp_path / "spheres.yaml"
    robot = load_robot(params_path=params_with_spheres(tmp_path, spheres))
    spheres.write_text("links:\n  elbow_link:\n    - {centre_m: [0, 0, 0], radius_m: 0.05}\n")
    with pytest.raises(ModelError, match=r"spheres.yaml: links.elbow_link: no such link"):
        arm_spheres(robot)
    spheres.write_text("links:\n  forearm_link:\n    - {centre_m: [0, 0], radius_m: 0.05}\n")
    with pytest.raises(ModelError, match=r"spheres.yaml: links.forearm_link\[0\]: needs centre_m"):
        arm_spheres(robot)


def test_dumbbells_are_consistent_and_inside_the_table_ii_box():
    robot = load_robot()
    lower = np.array([1.2, -0.4, -0.4, -1.0] + [-0.2] * 6)
    upper = np.array([5.2, 0.4, 0.4, -0.1] + [0.2] * 6)
    bells = load_dumbbells(MODELS_DIR / "dumbbells.yaml")
    assert list(bells) == ["4lb", "5lb", "6lb", "7lb", "8lb"]
    for bell in bells.values():
        theta = robot.theta_e + payload_theta_in_end_effector(bell, robot.extra["grasp_point"])
        assert inertial.is_physically_consistent(theta)
        assert np.all(theta >= lower) and np.all(theta <= upper)
    assert np.isclose(bells["8lb"].mass_kg, 3.629)


def test_bad_model_files_name_the_file(tmp_path):
    with pytest.raises(ModelError, match="not found"):
        load_robot(model_path=tmp_path / "missing.urdf")
    broken = tmp_path / "broken.urdf"
    broken.write_text(
        "<robot name='x'><link name='a'/><joint name='j' type='revolute'><parent link='a'/></joint></robot>"
    )
    with pytest.raises(ModelError, match="broken.urdf"):
        load_robot(model_path=broken)
    params = tmp_path / "p.yaml"
    params.write_text(
        "urdf: kinova_gen3.urdf\njoints: {names: [a, b], velocity_limit_rad_s: [1, 2, 3], torque_limit_Nm: [1, 2]}\n"
    )
    with pytest.raises(ModelError, match="velocity_limit_rad_s"):
        load_joint_parameters(params)
