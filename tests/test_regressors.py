"""Every regressor reproduces Drake on random states and random physically valid parameters."""

import numpy as np
import pytest
from pydrake.multibody.tree import MultibodyForces
from safesysid.systems.model import inertial, regressors
from safesysid.systems.model.robot_model import load_robot, make_plant

RTOL = 1e-9


@pytest.fixture(scope="module")
def gen3():
    robot = load_robot()
    plant, _, _ = make_plant(robot.source)
    plant.Finalize()
    return robot, plant, plant.CreateDefaultContext()


def random_theta(rng, n):
    """Random physically consistent body parameters (through the log-Cholesky map)."""
    return np.concatenate(
        [
            inertial.log_cholesky_to_theta(rng.normal(scale=0.4, size=10) + [-0.3, -1.5, -1.5, -1.5, 0, 0, 0, 0, 0, 0])
            for _ in range(n)
        ]
    )


def set_bodies(plant, context, robot, theta):
    for i, name in enumerate(robot.body_names):
        body = plant.GetBodyByName(name)
        body.SetSpatialInertiaInBodyFrame(context, inertial.to_spatial_inertia(theta[10 * i : 10 * i + 10]))


def rel_err(a, b):
    return np.abs(a - b).max() / max(np.abs(b).max(), 1e-12)


def set_state(plant, ctx, robot, theta, q, v):
    set_bodies(plant, ctx, robot, theta)
    plant.SetPositions(ctx, q)
    plant.SetVelocities(ctx, v)


def mass_rate(plant, ctx, q, v, h=1e-6):
    """Mdot along v by central differences; leaves the context at (q, v)."""

    def mass(qq):
        plant.SetPositions(ctx, qq)
        return plant.CalcMassMatrix(ctx)

    m_dot = (mass(q + h * v) - mass(q - h * v)) / (2 * h)
    plant.SetPositions(ctx, q)
    plant.SetVelocities(ctx, v)
    return m_dot


def states(rng, n, count=5):
    for _ in range(count):
        yield rng.uniform(-2, 2, n), rng.normal(size=n), rng.normal(size=n)


def test_standard_regressor_matches_inverse_dynamics(gen3):
    robot, plant, ctx = gen3
    rng = np.random.default_rng(0)
    for q, v, a in states(rng, robot.n):
        theta = random_theta(rng, robot.n)
        set_state(plant, ctx, robot, theta, q, v)
        forces = MultibodyForces(plant)
        plant.CalcForceElementsContribution(ctx, forces)
        tau = plant.CalcInverseDynamics(ctx, a, forces)
        w = regressors.standard_regressor(robot.tree, q, v, a)[0]
        assert rel_err(w @ theta, tau) < RTOL


def test_momentum_and_mass_matrix(gen3):
    robot, plant, ctx = gen3
    rng = np.random.default_rng(1)
    for q, v, _ in states(rng, robot.n):
        theta = random_theta(rng, robot.n)
        set_state(plant, ctx, robot, theta, q, v)
        m = plant.CalcMassMatrix(ctx)
        assert rel_err(regressors.momentum_regressor(robot.tree, q, v)[0] @ theta, m @ v) < RTOL
        full = robot.with_theta(np.concatenate([theta, robot.theta[70:]]))
        assert rel_err(full.mass_matrix(q)[0], m + np.diag(robot.joint_params.armature)) < RTOL


def test_momentum_rate_is_coriolis_transpose_minus_gravity(gen3):
    """Wc theta = C^T v - g, with C^T v = Mdot v - C v and Mdot from central differences."""
    robot, plant, ctx = gen3
    rng = np.random.default_rng(2)
    for q, v, _ in states(rng, robot.n):
        theta = random_theta(rng, robot.n)
        set_bodies(plant, ctx, robot, theta)
        m_dot = mass_rate(plant, ctx, q, v)
        expected = m_dot @ v - plant.CalcBiasTerm(ctx) + plant.CalcGravityGeneralizedForces(ctx)
        got = regressors.momentum_rate_regressor(robot.tree, q, v)[0] @ theta
        assert rel_err(got, expected) < 1e-7  # limited by the finite difference of M


def test_passivity_regressor_is_christoffel_consistent(gen3):
    """Wp(q, v, va, 0) - g = C(q, v) va with Mdot = C + C^T and C(q, v) v = Drake's bias term."""
    robot, plant, ctx = gen3
    rng = np.random.default_rng(3)
    q, v, _ = next(states(rng, robot.n))
    theta = random_theta(rng, robot.n)
    set_bodies(plant, ctx, robot, theta)
    zero = np.zeros(robot.n)
    g = regressors.passivity_regressor(robot.tree, q, zero, zero, zero)[0] @ theta
    c = np.stack([regressors.passivity_regressor(robot.tree, q, v, e, zero)[0] @ theta - g for e in np.eye(robot.n)], 1)
    m_dot = mass_rate(plant, ctx, q, v)
    assert rel_err(c @ v, plant.CalcBiasTerm(ctx)) < RTOL
    assert np.abs(m_dot - c - c.T).max() < 1e-7 * np.abs(m_dot).max() + 1e-9


def test_momentum_integral_identity_along_a_motion():
    """d/dt (Wm theta) = Wc theta + tau, with tau from the standard regressor (friction included)."""
    robot = load_robot(coulomb_smoothing=0.05)
    t = np.linspace(0, 1, 4001)
    w = np.array([1.0, 1.3, 0.7, 1.9, 2.3, 0.5, 1.1])
    q = 0.6 * np.sin(np.outer(t, w))
    v = 0.6 * w * np.cos(np.outer(t, w))
    a = -0.6 * w * w * np.sin(np.outer(t, w))
    tau = robot.standard_regressor(q, v, a) @ robot.theta
    p = robot.momentum_regressor(q, v) @ robot.theta
    rate = robot.momentum_rate_regressor(q, v) @ robot.theta + tau
    dp = np.gradient(p, t, axis=0)
    assert np.abs(dp - rate)[5:-5].max() < 1e-4 * np.abs(rate).max()


def test_regressor_is_generic_over_joint_count(tmp_path):
    """A 2-link arm written here: the regressors reproduce Drake too (nothing assumes 7 joints)."""
    urdf = tmp_path / "two_link.urdf"
    urdf.write_text("""<robot name="two"><link name="base"/>
      <link name="l1"><inertial>
    <origin xyz="0.1 0.02 0"/><mass value="1.5"/>
    <inertia ixx="0.01" iyy="0.02" izz="0.03" ixy="0.001" ixz="0" iyz="0"/></inertial></link>
      <link name="l2"><inertial>
    <origin xyz="0.2 0 0.01"/><mass value="0.8"/>
    <inertia ixx="0.004" iyy="0.01" izz="0.012" ixy="0" ixz="0.0005" iyz="0"/></inertial></link>
      <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="50" velocity="3"/></joint>
      <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.3 0 0" rpy="0.2 0 0"/>
    <axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="50" velocity="3"/></joint>
    </robot>""")
    robot = load_robot(model_path=urdf)
    assert robot.n == 2 and robot.joint_params.torque_limit.tolist() == [50, 50]
    plant, _, _ = make_plant(urdf)
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    rng = np.random.default_rng(4)
    q, v, a = rng.normal(size=(3, 2))
    plant.SetPositions(ctx, q)
    plant.SetVelocities(ctx, v)
    forces = MultibodyForces(plant)
    plant.CalcForceElementsContribution(ctx, forces)
    assert rel_err(robot.inverse_dynamics(q, v, a)[0], plant.CalcInverseDynamics(ctx, a, forces)) < RTOL


def test_friction_columns_follow_the_law():
    robot = load_robot(coulomb_smoothing=0.0)
    n = robot.n
    rng = np.random.default_rng(5)
    v, a = rng.normal(size=(2, 3, n))
    jp = robot.joint_params
    cols = robot.standard_regressor(np.zeros((3, n)), v, a)[..., 10 * n :]
    expected = jp.coulomb * np.sign(v) + jp.viscous * v + jp.armature * a + jp.offset
    assert np.allclose(cols @ jp.friction_theta(), expected)
