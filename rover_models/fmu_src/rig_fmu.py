"""Single-wheel rig as a pythonfmu (FMI 2.0 co-simulation) slave.

The same rig as rover_models.mjcf.single_wheel_rig_xml, integrated the way MuJoCo's
'implicitfast' integrator does it for this model (semi-implicit Euler, the wheel motor's
damping kv taken implicitly), with the same internal step, so its trajectories match the
MJCF model's up to rounding.

Degrees of freedom: carriage x (moves everything, total mass), ballast z (ballast +
wheel mass), wheel spin about y (wheel inertia I_yy). The soil wrench acts at the hub
(the wheel CoM): force.x on the x dof, force.z on the z dof, torque.y on the spin; the
other components meet the rig's constraints and do no work.

Variables follow regolith-cosim's FMU convention (wheel_0.force.x, ... see FmuRover).
Discard on demand: with max_step > 0, a doStep longer than max_step is refused (returns
False, pythonfmu's Discard/Error answer) without changing the state.
"""

import math
from collections.abc import Callable

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real

AXES = ("x", "y", "z")


class RigFmu(Fmi2Slave):
    author = "regolith-cosim"
    description = "Single-wheel test rig (carriage x, ballast z, wheel hinge y)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.p = {  # parameters, SI units
            "gravity.x": 0.0,
            "gravity.y": 0.0,
            "gravity.z": -9.81,
            "total_mass": 15.0,
            "vertical_mass": 10.0,
            "wheel_inertia": 0.005,
            "motor_kv": 20.0,
            "hub_height": 0.1,
            "internal_step": 1.0e-3,
            "max_step": 0.0,
        }
        self.u = {f"wheel_0.{q}.{a}": 0.0 for q in ("force", "torque") for a in AXES}
        self.u["wheel_0.speed_command"] = 0.0
        self.s = {"x": 0.0, "vx": 0.0, "z": 0.0, "vz": 0.0, "theta": 0.0, "omega": 0.0}
        self.z_started = False

        def reg(name, store, causality, variability):
            self.register_variable(
                Real(
                    name,
                    causality=causality,
                    variability=variability,
                    getter=lambda: store[name],
                    setter=lambda v: store.__setitem__(name, v),
                ),
                nested=False,
            )

        for name in self.p:
            reg(name, self.p, Fmi2Causality.parameter, Fmi2Variability.tunable)
        for name in self.u:
            reg(name, self.u, Fmi2Causality.input, Fmi2Variability.continuous)
        outputs: dict[str, Callable[..., float]] = {}
        for a in AXES:
            outputs[f"wheel_0.position.{a}"] = lambda a=a: {
                "x": self.s["x"],
                "y": 0.0,
                "z": self.p["hub_height"] + self.s["z"],
            }[a]

        def half():
            return 0.5 * self.s["theta"]

        outputs["wheel_0.orientation.w"] = lambda: math.cos(half())
        outputs["wheel_0.orientation.x"] = lambda: 0.0
        outputs["wheel_0.orientation.y"] = lambda: math.sin(half())
        outputs["wheel_0.orientation.z"] = lambda: 0.0
        for a in AXES:
            outputs[f"wheel_0.velocity.{a}"] = lambda a=a: {"x": self.s["vx"], "y": 0.0, "z": self.s["vz"]}[a]
            outputs[f"wheel_0.angular_velocity.{a}"] = lambda a=a: self.s["omega"] if a == "y" else 0.0
        for name, getter in outputs.items():
            self.register_variable(
                Real(name, causality=Fmi2Causality.output, variability=Fmi2Variability.continuous, getter=getter),
                nested=False,
            )

    def _substep(self, h):
        p, u, s = self.p, self.u, self.s
        m, mz, inertia, kv = p["total_mass"], p["vertical_mass"], p["wheel_inertia"], p["motor_kv"]
        # Velocities first (semi-implicit Euler); the motor torque kv (cmd - omega) implicitly.
        s["vx"] += h * (u["wheel_0.force.x"] + m * p["gravity.x"]) / m
        s["vz"] += h * (u["wheel_0.force.z"] + mz * p["gravity.z"]) / mz
        s["omega"] = (inertia * s["omega"] + h * (u["wheel_0.torque.y"] + kv * u["wheel_0.speed_command"])) / (
            inertia + h * kv
        )
        s["x"] += h * s["vx"]
        s["z"] += h * s["vz"]
        s["theta"] += h * s["omega"]

    def do_step(self, current_time, step_size):
        if self.p["max_step"] > 0.0 and step_size > self.p["max_step"] * (1 + 1e-12):
            return False  # refuse the step; the state is left untouched
        h = self.p["internal_step"]
        remaining = step_size
        # Same stepping as MujocoRover.advance: full steps, the last one shortened.
        while remaining > 1e-9 * h:
            dt = min(h, remaining)
            if remaining - dt <= 1e-9 * h:
                dt = remaining
            self._substep(dt)
            remaining -= dt
        return True
