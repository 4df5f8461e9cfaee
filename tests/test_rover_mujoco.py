"""MujocoRover: frames, kinematics, time stepping and drive modes against analytic answers."""

from __future__ import annotations

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from cosim.contract import RoverSide, WheelWrench  # noqa: E402
from rover_models import asset_path  # noqa: E402
from rover_models.mjcf import MMX_WHEELS, mmx_rover_xml, single_wheel_rig_xml  # noqa: E402
from rover_models.mujoco_rover import MujocoRover  # noqa: E402
from soil.control import quaternion_multiply, quaternion_to_matrix  # noqa: E402


def _axis_quat(axis, angle):
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


FREE_BODY = """
<mujoco>
  <option gravity="0 0 0" timestep="1e-4"/>
  <worldbody>
    <body name="hub" pos="0.3 -0.2 0.5" quat="{body_quat}">
      <freejoint/>
      <inertial pos="{com}" quat="{inertial_quat}" mass="{mass}" diaginertia="{inertia}"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_wrench_at_offset_hub_gives_analytic_accelerations():
    """A world-frame force + torque at the hub (body origin), CoM offset and rotated
    principal axes: a_com = F/m and alpha = I_world^-1 ((p_hub - p_com) x F + tau)."""
    body_q = _axis_quat([1, 2, 3], 0.7)
    inertial_q = _axis_quat([-1, 0.5, 2], 1.1)
    com_local = np.array([0.08, -0.05, 0.03])
    mass, inertia = 2.5, np.array([0.011, 0.023, 0.031])
    xml = FREE_BODY.format(
        body_quat=" ".join(map(str, body_q)),
        com=" ".join(map(str, com_local)),
        inertial_quat=" ".join(map(str, inertial_q)),
        mass=mass,
        inertia=" ".join(map(str, inertia)),
    )
    rover = MujocoRover(xml, ["hub"])
    force = np.array([3.0, -1.0, 2.0])
    torque = np.array([0.2, 0.5, -0.3])
    rover.apply_wheel_wrenches([WheelWrench(force=force, torque=torque)])
    mujoco.mj_forward(rover.model, rover.data)

    # Theory, from the MJCF numbers only.
    R_body = quaternion_to_matrix(body_q)
    R_inertia = R_body @ quaternion_to_matrix(inertial_q)
    p_hub = np.array([0.3, -0.2, 0.5])
    p_com = p_hub + R_body @ com_local
    I_world = R_inertia @ np.diag(inertia) @ R_inertia.T
    a_com = force / mass
    alpha = np.linalg.solve(I_world, np.cross(p_hub - p_com, force) + torque)
    # Free joint: qacc = [acceleration of the body origin (world), alpha (body frame)];
    # at rest the origin's acceleration is a_com + alpha x (p_hub - p_com).
    a_origin = a_com + np.cross(alpha, p_hub - p_com)
    np.testing.assert_allclose(rover.data.qacc[:3], a_origin, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(R_body @ rover.data.qacc[3:], alpha, rtol=1e-9, atol=1e-12)
    # The adapter wrote the shifted torque at the CoM, not the hub torque.
    assert not np.allclose(rover.data.xfrc_applied[1, 3:], torque)


ARM_AND_WHEEL = """
<mujoco>
  <option gravity="0 0 0"/>
  <worldbody>
    <body name="arm" pos="0.1 0.2 0.3">
      <joint name="yaw" type="hinge" axis="0 0 1"/>
      <inertial pos="0.2 0 0" mass="3" diaginertia="0.1 0.1 0.1"/>
      <body name="wheel" pos="{L} 0 0">
        <joint name="spin" type="hinge" axis="0 1 0"/>
        <inertial pos="0 0 0.01" mass="1" diaginertia="0.01 0.02 0.01"/>
      </body>
    </body>
  </worldbody>
  <actuator><velocity name="spin_motor" joint="spin" kv="1"/></actuator>
</mujoco>
"""


def test_wheel_kinematics_match_prescribed_motion():
    """Wheel on an arm yawing at Omega about z, spinning at omega about its axis:
    hub velocity = Omega z x (p_hub - p_pivot), angular velocity = Omega z + omega y_arm."""
    L, psi, theta, Omega, omega = 0.4, 0.6, -1.3, 2.0, 7.5
    rover = MujocoRover(ARM_AND_WHEEL.format(L=L), ["wheel"])
    assert isinstance(rover, RoverSide)
    rover.data.qpos[:] = [psi, theta]
    rover.data.qvel[:] = [Omega, omega]
    mujoco.mj_forward(rover.model, rover.data)
    (k,) = rover.wheel_kinematics()

    pivot = np.array([0.1, 0.2, 0.3])
    Rz = quaternion_to_matrix(_axis_quat([0, 0, 1], psi))
    p_hub = pivot + Rz @ [L, 0, 0]
    np.testing.assert_allclose(k.position, p_hub, atol=1e-12)
    np.testing.assert_allclose(k.linear_velocity, np.cross([0, 0, Omega], p_hub - pivot), atol=1e-12)
    np.testing.assert_allclose(k.angular_velocity, [0, 0, Omega] + omega * (Rz @ [0, 1, 0]), atol=1e-12)
    q = quaternion_multiply(_axis_quat([0, 0, 1], psi), _axis_quat([0, 1, 0], theta))
    assert min(np.linalg.norm(k.orientation - q), np.linalg.norm(k.orientation + q)) < 1e-12
    # cvel's linear part is taken at the subtree CoM, so it is not the hub velocity:
    # this test would catch an adapter that read cvel directly.
    assert not np.allclose(rover.data.cvel[2, 3:], k.linear_velocity, atol=1e-3)


def test_advance_lands_exactly_on_t_end_and_restores_timestep():
    rover = MujocoRover(single_wheel_rig_xml(timestep=1e-3, hub_height=1.0), ["wheel"], gravity=(0, 0, -9.81))
    z0 = rover.wheel_kinematics()[0].position[2]
    for t_end in (0.0105, 0.02, 0.0333333):  # not multiples of the timestep
        rover.advance(t_end)
        assert rover.time == t_end
        assert rover.model.opt.timestep == 1e-3
    # Free fall of the ballast + wheel (the terrain is absent): z = z0 - g t^2 / 2 up to
    # the integrator's O(h) error, and kinematics are those at t_end (not one step stale).
    t = rover.time
    k = rover.wheel_kinematics()[0]
    assert abs(k.position[2] - (z0 - 9.81 * t**2 / 2)) < 9.81 * 1e-3 * t
    assert abs(k.linear_velocity[2] + 9.81 * t) < 1e-9
    with pytest.raises(ValueError):
        rover.advance(0.01)


def test_gravity_is_pushed_to_the_model():
    rover = MujocoRover(single_wheel_rig_xml(), ["wheel"])
    rover.set_gravity([0, 0, -5.7e-3])
    np.testing.assert_array_equal(rover.model.opt.gravity, [0, 0, -5.7e-3])


def test_speed_and_torque_modes():
    """Free wheel (gravity off): the velocity motor reaches the commanded speed; in
    torque mode the motor is off and omega = tau t / I_yy."""
    rover = MujocoRover(single_wheel_rig_xml(wheel_mass=1.0, wheel_radius=0.1), ["wheel"], gravity=(0, 0, 0))
    rover.set_wheel_speeds([5.0])
    rover.advance(0.2)  # motor time constant I/kv = 2.5e-4 s
    assert rover.wheel_spin_rates()[0] == pytest.approx(5.0, rel=1e-6)
    np.testing.assert_allclose(rover.wheel_kinematics()[0].angular_velocity, [0, 5.0, 0], atol=1e-6)

    i_yy = 0.5 * 1.0 * 0.1**2
    rover.set_wheel_torques([0.01])
    rover.advance(0.7)
    assert rover.wheel_spin_rates()[0] == pytest.approx(5.0 + 0.01 * 0.5 / i_yy, rel=1e-9)
    rover.set_wheel_speeds([-2.0])
    rover.advance(1.0)
    assert rover.wheel_spin_rates()[0] == pytest.approx(-2.0, rel=1e-6)


def test_unknown_wheel_body_lists_the_bodies():
    with pytest.raises(KeyError) as err:
        MujocoRover(mmx_rover_xml(), ["wheel_fl", "wheel_front_left"])
    message = str(err.value)
    assert "wheel_front_left" in message and "wheel_rr" in message and "leg_fl" in message


def test_unknown_actuator_lists_the_actuators():
    with pytest.raises(KeyError, match="wheel_fl_motor"):
        MujocoRover(mmx_rover_xml(), ["wheel_fl"], wheel_actuators=["nope"])


def test_assets_load_and_match_their_generators():
    rig = MujocoRover(asset_path("single_wheel_rig.xml"), ["wheel"])
    assert rig.total_mass == pytest.approx(15.0)
    rover = MujocoRover(asset_path("mmx_rover.xml"), list(MMX_WHEELS))
    assert rover.total_mass == pytest.approx(25.0)
    # Wheels start touching z = 0: hub height = radius.
    for k in rover.wheel_kinematics():
        assert k.position[2] == pytest.approx(0.1)
    # The soil provides all contact: no geom may collide in MuJoCo.
    for m in (rig.model, rover.model):
        assert not m.geom_contype.any() and not m.geom_conaffinity.any()
    bigger = MujocoRover(mmx_rover_xml(wheel_radius=0.15, wheel_width=0.1), list(MMX_WHEELS))
    assert bigger.wheel_kinematics()[0].position[2] == pytest.approx(0.15)
    geom = bigger.model.geom("wheel_fl_geom")
    np.testing.assert_allclose(geom.size[:2], [0.15, 0.05])


# --- held wrenches and motors over many steps: what a MuJoCo release must not change ---------
#
# The soil's wrench is held over a macro step while MuJoCo takes its own steps, the last
# one shortened. These tests follow a held wrench through many (uneven) steps and compare
# with closed-form physics, so a change of the integrator, of xfrc_applied's point of
# application or of the velocity actuator's law in a MuJoCo release fails here, not as a
# changed granular trajectory far downstream.


def _semi_implicit_euler(x0, v0, a, steps):
    """Position and velocity after steps h_1, h_2, ... of semi-implicit (symplectic) Euler,
    v += h a; x += h v, the update of MuJoCo's Euler and implicitfast integrators."""
    x, v = np.array(x0, dtype=float), np.array(v0, dtype=float)
    for h in steps:
        v = v + h * a
        x = x + h * v
    return x, v


def _mujoco_steps(t_ends, timestep):
    """The step sizes MujocoRover.advance takes to reach each of t_ends in turn [s]."""
    out, t = [], 0.0
    for t_end in t_ends:
        while t_end - t > 1e-9 * timestep:
            h = min(timestep, t_end - t)
            if t_end - t - h <= 1e-9 * timestep:
                h = t_end - t
            out.append(h)
            t += h
        t = t_end
    return out


def test_held_hub_wrench_moves_the_centre_of_mass_along_the_analytic_path():
    """Free body, CoM 0.1 m off the hub, gravity on. The held hub wrench is a force F and
    the torque (p_com - p_hub) x F, i.e. no torque about the CoM: the body must not turn
    and its CoM must follow a = F/m + g exactly as semi-implicit Euler integrates it,
    through uneven macro steps with shortened last MuJoCo steps. A force applied at the
    hub without the shift (or at the wrong point) turns the body."""
    com_local = np.array([0.06, -0.05, 0.06])
    mass = 1.7
    xml = FREE_BODY.format(
        body_quat="1 0 0 0",
        com=" ".join(map(str, com_local)),
        inertial_quat="1 0 0 0",
        mass=mass,
        inertia="0.01 0.02 0.03",
    ).replace('gravity="0 0 0"', 'gravity="0 0 -9.81"')
    rover = MujocoRover(xml, ["hub"])
    assert rover.timestep == 1e-4
    force = np.array([0.8, -0.3, 25.0])
    p_com0 = rover.data.xipos[1].copy()
    p_hub0 = rover.data.xpos[1].copy()
    rover.apply_wheel_wrenches([WheelWrench(force=force, torque=np.cross(p_com0 - p_hub0, force))])
    t_ends = np.cumsum([3.3e-4, 2.5e-4, 1.07e-3, 4.4e-4] * 25)  # 0.209 s, never a whole number of steps
    for t_end in t_ends:
        rover.advance(t_end)
    a = force / mass + np.array([0, 0, -9.81])
    x, v = _semi_implicit_euler(p_com0, np.zeros(3), a, _mujoco_steps(t_ends, 1e-4))
    np.testing.assert_allclose(rover.data.xipos[1], x, rtol=0, atol=1e-12)
    # the hub moves with the CoM (no rotation): the adapter reports the hub's velocity
    (k,) = rover.wheel_kinematics()
    np.testing.assert_allclose(k.linear_velocity, v, rtol=0, atol=1e-12)
    np.testing.assert_allclose(k.angular_velocity, 0.0, atol=1e-12)
    np.testing.assert_allclose(k.position - rover.data.xipos[1], p_hub0 - p_com0, atol=1e-12)
    # and against continuous physics: semi-implicit Euler is off by a h t / 2
    t = t_ends[-1]
    assert np.all(np.abs(x - (p_com0 + a * t**2 / 2)) <= np.abs(a) * 1e-4 * t / 2 + 1e-12)


def test_velocity_motor_against_a_held_soil_torque():
    """Wheel on its hinge (gravity off), velocity motor tau = kv (ctrl - omega), soil
    torque T about the axle held at the hub. implicitfast takes the motor's damping
    implicitly: omega_{n+1} = (I omega_n + h (kv ctrl + T)) / (I + h kv), whose fixed
    point is the steady state omega = ctrl + T / kv of the continuous motor, reached as
    exp(-kv t / I) up to O(h)."""
    kv, radius, wheel_mass = 0.5, 0.1, 1.0
    rover = MujocoRover(
        single_wheel_rig_xml(wheel_mass=wheel_mass, wheel_radius=radius, motor_kv=kv, timestep=1e-3),
        ["wheel"],
        gravity=(0, 0, 0),
    )
    i_yy = 0.5 * wheel_mass * radius**2
    ctrl, soil_torque = 6.0, -0.4  # the soil resists the drive
    rover.set_wheel_speeds([ctrl])
    rover.apply_wheel_wrenches([WheelWrench(force=np.zeros(3), torque=np.array([0.0, soil_torque, 0.0]))])
    omega = 0.0
    times = [0.0]
    for t_end in np.arange(1, 31) * 2.5e-3:  # macro steps of 2.5 MuJoCo steps
        rover.advance(t_end)
        times.append(t_end)
    for h in _mujoco_steps(times[1:], 1e-3):
        omega = (i_yy * omega + h * (kv * ctrl + soil_torque)) / (i_yy + h * kv)
    assert rover.wheel_spin_rates()[0] == pytest.approx(omega, rel=1e-12)
    steady = ctrl + soil_torque / kv
    t = times[-1]
    continuous = steady * (1 - np.exp(-kv * t / i_yy))
    assert rover.wheel_spin_rates()[0] == pytest.approx(continuous, rel=0.05)  # O(h kv / I) = 5 %
    rover.advance(1.0)  # 200 time constants
    assert rover.wheel_spin_rates()[0] == pytest.approx(steady, rel=1e-12)


def test_rover_on_four_hub_forces_summing_to_its_weight_stays_at_rest():
    """The symmetric MMX-like rover (legs' CoMs off the hubs) held by four upward hub
    forces of m g / 4 each, wheels held by their motors at zero speed: no net force or
    moment, so it stays at rest, at Earth and at Phobos gravity alike; with 1 % less
    force it falls at 0.01 g."""
    for g in (9.81, 5.7e-3):
        rover = MujocoRover(mmx_rover_xml(), list(MMX_WHEELS), gravity=(0, 0, -g))
        rover.set_wheel_speeds([0.0] * 4)
        weight = rover.total_mass * g
        start = rover.data.qpos.copy()
        rover.apply_wheel_wrenches([WheelWrench(force=np.array([0, 0, weight / 4]))] * 4)
        rover.advance(0.5)
        np.testing.assert_allclose(rover.data.qvel, 0.0, atol=1e-9 * g)
        np.testing.assert_allclose(rover.data.qpos, start, atol=1e-9 * g)
        rover.apply_wheel_wrenches([WheelWrench(force=np.array([0, 0, 0.99 * weight / 4]))] * 4)
        rover.advance(1.0)
        vz = [k.linear_velocity[2] for k in rover.wheel_kinematics()]
        np.testing.assert_allclose(vz, -0.01 * g * 0.5, rtol=1e-9)
