"""A traction (slip) controller as a pythonfmu (FMI 2.0 co-simulation) slave, for cosim.fmu_controller.

The control law of cosim.controllers.SlipController, per wheel i: with the hub velocity v along
the wheel's rolling direction (axle x up), its spin omega about the axle and s* the target slip,

    e = v - (1 - s*) omega r,   integral += e * (step size),
    speed_command = clamp([v + kp e + ki integral] / ((1 - s*) r), omega_min, omega_max),

the integral frozen while the command is clamped (anti-windup). Inputs wheel_<i>.velocity.*,
wheel_<i>.angular_velocity.*, wheel_<i>.orientation.* (world frame, SI); output
wheel_<i>.speed_command [rad/s]; parameters target_slip [-], wheel_radius [m], kp [-], ki [1/s],
omega_min, omega_max [rad/s]. WHEELS is set when the FMU is built (build_fmus.build_slip_controller_fmu).
The FMU can save and restore its state.
"""

import math

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real

WHEELS = 4


def _frame(q):
    """Axle (body +y) and rolling direction (axle x +z) in the world frame of a quaternion (w, x, y, z)."""
    w, x, y, z = q
    axle = (2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x))
    forward = (axle[1], -axle[0], 0.0)
    norm = math.hypot(forward[0], forward[1])
    return axle, ((forward[0] / norm, forward[1] / norm, 0.0) if norm > 1e-9 else (0.0, 0.0, 0.0))


class SlipControllerFmu(Fmi2Slave):
    author = "regolith-cosim"
    description = "PI traction controller holding the driving slip of every wheel at a target"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.p = {"target_slip": 0.2, "wheel_radius": 0.1, "kp": 1.0, "ki": 20.0, "omega_min": 0.01, "omega_max": 100.0}
        self.u = {}
        for i in range(WHEELS):
            for quantity, axes in (("velocity", "xyz"), ("angular_velocity", "xyz"), ("orientation", "wxyz")):
                for a in axes:
                    self.u[f"wheel_{i}.{quantity}.{a}"] = 1.0 if (quantity, a) == ("orientation", "w") else 0.0
        self.integral = [0.0] * WHEELS

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
        for i in range(WHEELS):
            self.register_variable(
                Real(
                    f"wheel_{i}.speed_command",
                    causality=Fmi2Causality.output,
                    variability=Fmi2Variability.continuous,
                    getter=lambda i=i: self._law(i, 0.0)[0],
                ),
                nested=False,
            )

    def _law(self, i, dt):
        """(command, error, clamped) of wheel i from the current inputs and the integral plus e dt."""
        p, u = self.p, self.u
        q = [u[f"wheel_{i}.orientation.{a}"] for a in "wxyz"]
        axle, forward = _frame(q)
        v = sum(u[f"wheel_{i}.velocity.{a}"] * f for a, f in zip("xyz", forward))
        rim = sum(u[f"wheel_{i}.angular_velocity.{a}"] * c for a, c in zip("xyz", axle)) * p["wheel_radius"]
        keep = 1.0 - p["target_slip"]
        error = v - keep * rim
        raw = (v + p["kp"] * error + p["ki"] * (self.integral[i] + error * dt)) / (keep * p["wheel_radius"])
        command = min(max(raw, p["omega_min"]), p["omega_max"])
        return command, error, command != raw

    def do_step(self, current_time, step_size):
        for i in range(WHEELS):
            _, error, clamped = self._law(i, step_size)
            if not clamped:
                self.integral[i] += error * step_size
        return True

    def _get_fmu_state(self):
        state = super()._get_fmu_state()
        state["_integral"] = list(self.integral)
        return state

    def _set_fmu_state(self, state):
        integral = state.pop("_integral", None)
        super()._set_fmu_state({k: v for k, v in state.items() if k in self.p or k in self.u})
        if integral is not None:
            self.integral = list(integral)
