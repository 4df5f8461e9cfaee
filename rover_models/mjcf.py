"""MJCF generators for the rover models (pure string building, no MuJoCo import).

Conventions shared by every model here (and expected by MujocoRover / the terrain):
- a wheel is a body whose frame origin is the hub centre and whose spin axis is the
  body's +y axis; its hinge joint is about +y, so a positive speed rolls it towards +x;
- every geom has contype = conaffinity = 0: the soil (DEM or analytic terrain) provides
  all wheel contact, MuJoCo's own contact must not act (the ground plane is visual only);
- each wheel hinge has a velocity actuator named "<wheel>_motor" (ctrl = speed [rad/s]);
- the integrator is 'implicitfast' (semi-implicit Euler with the velocity actuators'
  damping taken implicitly, so a stiff motor stays stable), the default timestep 1 ms.
"""

from __future__ import annotations

import math


def _cylinder_inertia(mass: float, radius: float, width: float) -> tuple[float, float, float]:
    """Principal inertia [kg m^2] of a solid cylinder whose axis is y: (Ixx, Iyy, Izz)."""
    axial = 0.5 * mass * radius**2
    transverse = mass * (3 * radius**2 + width**2) / 12.0
    return transverse, axial, transverse


def _box_inertia(mass: float, sx: float, sy: float, sz: float) -> tuple[float, float, float]:
    """Principal inertia [kg m^2] of a solid box with full side lengths sx, sy, sz [m]."""
    return (
        mass * (sy**2 + sz**2) / 12.0,
        mass * (sx**2 + sz**2) / 12.0,
        mass * (sx**2 + sy**2) / 12.0,
    )


def _fmt(values) -> str:
    return " ".join(f"{v:.10g}" for v in values)


def single_wheel_rig_xml(
    wheel_radius: float = 0.1,
    wheel_width: float = 0.06,
    wheel_mass: float = 1.0,
    carriage_mass: float = 5.0,
    ballast_mass: float = 9.0,
    motor_kv: float = 20.0,
    hub_height: float | None = None,
    timestep: float = 1.0e-3,
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81),
) -> str:
    """MJCF of a single-wheel test rig (the classic single-wheel testbed).

    world -> carriage (slide x) -> ballast (slide z) -> wheel (hinge y, velocity motor).
    The carriage mass moves only horizontally; ballast + wheel mass rest on the wheel, so
    the vertical load is (ballast_mass + wheel_mass) g and the mass driven along x is the
    total. Masses [kg], lengths [m], motor_kv [N m s/rad], timestep [s], gravity [m/s^2].
    With hub_height None the wheel starts touching z = 0 (hub at wheel_radius).
    """
    z = wheel_radius if hub_height is None else hub_height
    ixx, iyy, izz = _cylinder_inertia(wheel_mass, wheel_radius, wheel_width)
    return f"""<mujoco model="single_wheel_rig">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep:.10g}" gravity="{_fmt(gravity)}" integrator="implicitfast"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <geom name="ground" type="plane" size="5 1 0.1" rgba="0.55 0.45 0.35 1"/>
    <body name="carriage" pos="0 0 {z:.10g}">
      <joint name="carriage_x" type="slide" axis="1 0 0"/>
      <inertial pos="0 0 0" mass="{carriage_mass:.10g}" diaginertia="0.1 0.1 0.1"/>
      <geom type="box" size="0.15 0.02 0.02" pos="0 0 {wheel_radius + 0.1:.10g}" rgba="0.3 0.3 0.8 1"/>
      <body name="ballast">
        <joint name="ballast_z" type="slide" axis="0 0 1"/>
        <inertial pos="0 0 0" mass="{ballast_mass:.10g}" diaginertia="0.05 0.05 0.05"/>
        <geom type="box" size="0.04 0.04 0.04" pos="0 -{wheel_width / 2 + 0.06:.10g} 0" rgba="0.6 0.6 0.6 1"/>
        <body name="wheel">
          <joint name="wheel_hinge" type="hinge" axis="0 1 0"/>
          <inertial pos="0 0 0" mass="{wheel_mass:.10g}" diaginertia="{_fmt((ixx, iyy, izz))}"/>
          <geom name="wheel_geom" type="cylinder" size="{wheel_radius:.10g} {wheel_width / 2:.10g}"
                euler="1.5707963267948966 0 0" rgba="0.2 0.2 0.2 1"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <velocity name="wheel_motor" joint="wheel_hinge" kv="{motor_kv:.10g}"/>
  </actuator>
</mujoco>
"""


MMX_WHEELS = ("wheel_fl", "wheel_fr", "wheel_rl", "wheel_rr")
"""Wheel body names of the MMX-like rover, front-left, front-right, rear-left, rear-right."""


def _check_mmx(values: dict) -> None:
    """mmx_rover_xml's arguments as [rover.mmx] takes them (cosim.scene.MmxSection): a negative mass
    compiled and ran as another rover, a nan timestep froze it. ArgumentError naming the argument."""
    from soil.errors import ArgumentError, is_real

    def real(value) -> bool:
        return is_real(value) and math.isfinite(value)

    positive = ("wheel_radius", "wheel_width", "body_mass", "leg_mass", "wheel_mass", "wheelbase", "track")
    for name in (*positive, "motor_kv", "timestep", "leg_drop", "clearance"):
        value = values[name]
        at_least = 0.0 if name in ("leg_drop", "clearance") else None
        if not real(value) or (value < at_least if at_least is not None else value <= 0):
            allowed = ">= 0" if at_least is not None else "> 0"
            raise ArgumentError(f"mmx_rover_xml: {name} must be a finite number {allowed}, got {value!r}")
    for name, count in (("body_size", 3), ("gravity", 3)):
        vector = tuple(values[name])
        if len(vector) != count or not all(real(v) and (name == "gravity" or v > 0) for v in vector):
            what = "three sizes > 0 [m]" if name == "body_size" else "three finite numbers [m/s^2]"
            raise ArgumentError(f"mmx_rover_xml: {name} must be {what}, got {values[name]!r}")


def mmx_rover_xml(
    wheel_radius: float = 0.1,
    wheel_width: float = 0.06,
    body_mass: float = 17.0,
    leg_mass: float = 0.5,
    wheel_mass: float = 1.5,
    body_size: tuple[float, float, float] = (0.41, 0.37, 0.30),
    wheelbase: float = 0.40,
    track: float = 0.50,
    leg_drop: float = 0.15,
    motor_kv: float = 20.0,
    clearance: float = 0.0,
    timestep: float = 1.0e-3,
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81),
) -> str:
    """MJCF of an MMX-like four-wheeled rover (about 25 kg with the defaults).

    A free-floating body box (full sizes `body_size` [m]) carries four legs, fixed at their
    shoulders, each holding a wheel on a velocity-controlled hinge. Hubs sit at
    (+-wheelbase/2, +-track/2, -leg_drop) from the body centre [m]. With clearance 0 the
    wheels start touching z = 0. Masses [kg]: total = body + 4 (leg + wheel).
    """
    _check_mmx(locals())
    sx, sy, sz = body_size
    z_body = wheel_radius + leg_drop + clearance
    ibx = _box_inertia(body_mass, sx, sy, sz)
    iw = _cylinder_inertia(wheel_mass, wheel_radius, wheel_width)
    legs = []
    for name in MMX_WHEELS:
        x = wheelbase / 2 if name[-2] == "f" else -wheelbase / 2
        y = track / 2 if name[-1] == "l" else -track / 2
        # The leg is a strut from the body side down to the hub; its mass sits halfway.
        shoulder_y = (sy / 2) if y > 0 else -(sy / 2)
        legs.append(
            f"""      <body name="leg_{name[-2:]}" pos="{x:.10g} {shoulder_y:.10g} 0">
        <inertial pos="0 {(y - shoulder_y) / 2:.10g} {-leg_drop / 2:.10g}" mass="{leg_mass:.10g}"
                  diaginertia="1e-3 1e-3 1e-3"/>
        <geom type="capsule" fromto="0 0 0 0 {y - shoulder_y:.10g} {-leg_drop:.10g}" size="0.015" rgba="0.7 0.7 0.7 1"/>
        <body name="{name}" pos="0 {y - shoulder_y:.10g} {-leg_drop:.10g}">
          <joint name="{name}_hinge" type="hinge" axis="0 1 0"/>
          <inertial pos="0 0 0" mass="{wheel_mass:.10g}" diaginertia="{_fmt(iw)}"/>
          <geom name="{name}_geom" type="cylinder" size="{wheel_radius:.10g} {wheel_width / 2:.10g}"
                euler="1.5707963267948966 0 0" rgba="0.2 0.2 0.2 1"/>
        </body>
      </body>"""
        )
    motors = "\n".join(
        f'    <velocity name="{name}_motor" joint="{name}_hinge" kv="{motor_kv:.10g}"/>' for name in MMX_WHEELS
    )
    legs_xml = "\n".join(legs)
    return f"""<mujoco model="mmx_rover">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep:.10g}" gravity="{_fmt(gravity)}" integrator="implicitfast"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <geom name="ground" type="plane" size="5 5 0.1" rgba="0.55 0.45 0.35 1"/>
    <body name="body" pos="0 0 {z_body:.10g}">
      <freejoint name="body_free"/>
      <inertial pos="0 0 0" mass="{body_mass:.10g}" diaginertia="{_fmt(ibx)}"/>
      <geom name="body_geom" type="box" size="{sx / 2:.10g} {sy / 2:.10g} {sz / 2:.10g}" rgba="0.85 0.85 0.8 1"/>
{legs_xml}
    </body>
  </worldbody>
  <actuator>
{motors}
  </actuator>
</mujoco>
"""
