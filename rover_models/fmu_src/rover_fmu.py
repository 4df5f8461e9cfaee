"""The MMX-like four-wheeled rover as a pythonfmu (FMI 2.0 co-simulation) slave.

The same rover as rover_models.mjcf.mmx_rover_xml (same parameters, masses, inertias, hub
positions, wheel order fl, fr, rl, rr, velocity motors), written independently of MuJoCo:
a rigid body (the box, the legs fixed to it) carrying four axisymmetric wheels on hinges about
its +y axis. With the composite centre of mass c as reference point, the generalized
velocities u = (v_c world [m/s], omega body frame [rad/s], the hinge rates [rad/s]) have a
constant mass matrix

    M = [[m 1, 0, 0], [0, J, B], [0, B^T, diag(I_a)]],   B = [I_a e_y, ...]

(J: inertia of the whole rover about c in the body frame, I_a: axial wheel inertia), and the
equations of motion M du/dt = f with f = (sum F + m g, R^T tau_c - omega x L, tau_i . axle_i + motor_i)
(tau_c: the soil torques about c; L = J omega + sum I_a rate_i e_y, the angular momentum in the
body frame; an axisymmetric wheel adds no gyroscopic term to its own axis). Each internal step
integrates as MuJoCo's 'implicitfast' does: the velocity motors' damping kv implicitly,
(M + h D) u+ = M u + h (f + kv command), then the positions with u+ (semi-implicit Euler), the
body quaternion turned by omega h in the body frame. The two models differ in reference point
(MuJoCo integrates the body frame origin), so they agree to O(h), not bitwise.

Variables follow regolith-cosim's FMU rover convention (rover_models.fmu_rover):
wheel_<i>.force/torque inputs, wheel_<i>.position/orientation/velocity/angular_velocity outputs,
wheel_<i>.speed_command / torque_command inputs and drive_mode (0 speed, 1 torque), body.*
outputs, start.x/y/z/heading and gravity.* parameters, total_mass. The FMU can save and
restore its state (checkpoints).
"""

import math

import numpy as np
from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real

AXES = ("x", "y", "z")
WHEELS = ("fl", "fr", "rl", "rr")
_EY = np.array([0.0, 1.0, 0.0])


def _rotation(q):
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _multiply(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def _skew_inertia(mass, d):
    """Parallel-axis term m (|d|^2 1 - d d^T) [kg m^2]."""
    return mass * (float(d @ d) * np.eye(3) - np.outer(d, d))


class MmxRoverFmu(Fmi2Slave):
    author = "regolith-cosim"
    description = "MMX-like four-wheeled rover (rigid body, four wheel hinges, velocity motors)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.p = {  # parameters, SI units; the defaults of rover_models.mjcf.mmx_rover_xml
            "gravity.x": 0.0,
            "gravity.y": 0.0,
            "gravity.z": -9.81,
            "wheel_radius": 0.1,
            "wheel_width": 0.06,
            "body_mass": 17.0,
            "leg_mass": 0.5,
            "wheel_mass": 1.5,
            "body_size.x": 0.41,
            "body_size.y": 0.37,
            "body_size.z": 0.30,
            "wheelbase": 0.40,
            "track": 0.50,
            "leg_drop": 0.15,
            "motor_kv": 20.0,
            "internal_step": 1.0e-3,
            "start.x": 0.0,
            "start.y": 0.0,
            "start.z": 0.25,
            "start.heading": 0.0,
        }
        self.u = {}
        for i in range(4):
            for quantity in ("force", "torque"):
                for a in AXES:
                    self.u[f"wheel_{i}.{quantity}.{a}"] = 0.0
            self.u[f"wheel_{i}.speed_command"] = 0.0
            self.u[f"wheel_{i}.torque_command"] = 0.0
        self.u["drive_mode"] = 0.0
        self.ready = False
        self._cache = None  # the outputs of the current state: four wheels, then the body
        self._force_keys = [[f"wheel_{i}.force.{a}" for a in AXES] for i in range(4)]
        self._torque_keys = [[f"wheel_{i}.torque.{a}" for a in AXES] for i in range(4)]
        self.q = np.zeros(4)  # body quaternion (w, x, y, z), body -> world
        self.c = np.zeros(3)  # centre of mass, world [m]
        self.v = np.zeros(10)  # v_c (3), omega in the body frame (3), hinge rates (4)
        self.angle = np.zeros(4)  # hinge angles [rad]

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
        self.register_variable(
            Real(
                "total_mass",
                causality=Fmi2Causality.output,
                variability=Fmi2Variability.continuous,
                getter=lambda: self._geometry()["mass"],
            ),
            nested=False,
        )
        for i in range(4):
            for k, name in enumerate(
                ["position." + a for a in AXES]
                + ["orientation." + a for a in "wxyz"]
                + ["velocity." + a for a in AXES]
                + ["angular_velocity." + a for a in AXES]
            ):
                self.register_variable(
                    Real(
                        f"wheel_{i}.{name}",
                        causality=Fmi2Causality.output,
                        variability=Fmi2Variability.continuous,
                        getter=lambda i=i, k=k: self._outputs()[i][k],
                    ),
                    nested=False,
                )
        for k, name in enumerate(
            ["position." + a for a in AXES]
            + ["orientation." + a for a in "wxyz"]
            + ["velocity." + a for a in AXES]
            + ["angular_velocity." + a for a in AXES]
        ):
            self.register_variable(
                Real(
                    f"body.{name}",
                    causality=Fmi2Causality.output,
                    variability=Fmi2Variability.continuous,
                    getter=lambda k=k: self._outputs()[4][k],
                ),
                nested=False,
            )

    # -- the rover's constant geometry ---------------------------------------------------
    def _geometry(self):
        p = self.p
        wb, tr, drop, sy = p["wheelbase"], p["track"], p["leg_drop"], p["body_size.y"]
        r, width, mw, ml, mb = p["wheel_radius"], p["wheel_width"], p["wheel_mass"], p["leg_mass"], p["body_mass"]
        sx, sz = p["body_size.x"], p["body_size.z"]
        hubs, legs = [], []
        for name in WHEELS:
            x = wb / 2 if name[0] == "f" else -wb / 2
            y = tr / 2 if name[1] == "l" else -tr / 2
            shoulder = sy / 2 if y > 0 else -sy / 2
            hubs.append(np.array([x, y, -drop]))
            legs.append(np.array([x, (y + shoulder) / 2, -drop / 2]))
        mass = mb + 4 * (ml + mw)
        com = (sum(ml * leg for leg in legs) + sum(mw * hub for hub in hubs)) / mass
        axial = 0.5 * mw * r * r
        transverse = mw * (3 * r * r + width * width) / 12.0
        box = np.diag([mb * (sy * sy + sz * sz), mb * (sx * sx + sz * sz), mb * (sx * sx + sy * sy)]) / 12.0
        inertia = box + _skew_inertia(mb, -com)
        for leg, hub in zip(legs, hubs):
            inertia += 1e-3 * np.eye(3) + _skew_inertia(ml, leg - com)
            inertia += np.diag([transverse, axial, transverse]) + _skew_inertia(mw, hub - com)
        matrix = np.zeros((10, 10))
        matrix[0:3, 0:3] = mass * np.eye(3)
        matrix[3:6, 3:6] = inertia
        for i in range(4):
            matrix[3:6, 6 + i] = axial * _EY
            matrix[6 + i, 3:6] = axial * _EY
            matrix[6 + i, 6 + i] = axial
        return {
            "mass": mass,
            "com": com,
            "hubs": [h - com for h in hubs],
            "inertia": inertia,
            "axial": axial,
            "matrix": matrix,
        }

    def _start(self):
        if self.ready:
            return
        g = self._geometry()
        self.g = g
        heading = self.p["start.heading"]
        self.q = np.array([math.cos(heading / 2), 0.0, 0.0, math.sin(heading / 2)])
        origin = np.array([self.p["start.x"], self.p["start.y"], self.p["start.z"]])
        self.c = origin + _rotation(self.q) @ g["com"]
        self.v = np.zeros(10)
        self.angle = np.zeros(4)
        self.ready = True
        self._cache = None

    def exit_initialization_mode(self):
        self._start()

    # -- outputs ---------------------------------------------------------------------------
    def _outputs(self):
        if self._cache is None:
            self._start()
            self._cache = [self._wheel(i) for i in range(4)] + [self._body()]
        return self._cache

    def _wheel(self, i):
        rotation = _rotation(self.q)
        arm = rotation @ self.g["hubs"][i]
        omega = rotation @ self.v[3:6]
        half = 0.5 * self.angle[i]
        orientation = _multiply(self.q, np.array([math.cos(half), 0.0, math.sin(half), 0.0]))
        velocity = self.v[0:3] + np.cross(omega, arm)
        spin = rotation @ (self.v[3:6] + self.v[6 + i] * _EY)
        return [*(self.c + arm), *orientation, *velocity, *spin]

    def _body(self):
        rotation = _rotation(self.q)
        arm = -rotation @ self.g["com"]
        omega = rotation @ self.v[3:6]
        return [*(self.c + arm), *self.q, *(self.v[0:3] + np.cross(omega, arm)), *omega]

    # -- stepping --------------------------------------------------------------------------
    def _substep(self, h):
        g, u, p = self.g, self.u, self.p
        rotation = _rotation(self.q)
        axle = rotation @ _EY
        force = np.zeros(10)
        torque_c = np.zeros(3)
        gravity = np.array([p["gravity.x"], p["gravity.y"], p["gravity.z"]])
        force[0:3] = g["mass"] * gravity
        torque_mode = u["drive_mode"] > 0.5
        kv = p["motor_kv"]
        for i in range(4):
            f = np.array([u[key] for key in self._force_keys[i]])
            t = np.array([u[key] for key in self._torque_keys[i]])
            force[0:3] += f
            torque_c += t + np.cross(rotation @ g["hubs"][i], f)
            motor = u[f"wheel_{i}.torque_command"] if torque_mode else kv * u[f"wheel_{i}.speed_command"]
            force[6 + i] = float(axle @ t) + motor
        omega = self.v[3:6]
        momentum = g["inertia"] @ omega + g["axial"] * np.sum(self.v[6:10]) * _EY
        force[3:6] = rotation.T @ torque_c - np.cross(omega, momentum)
        matrix = g["matrix"]
        lhs = matrix.copy()
        if not torque_mode:
            lhs[6:10, 6:10] += h * kv * np.eye(4)
        self.v = np.linalg.solve(lhs, matrix @ self.v + h * force)
        self.c = self.c + h * self.v[0:3]
        turn = h * self.v[3:6]
        angle = float(np.linalg.norm(turn))
        if angle > 0.0:
            dq = np.array([math.cos(angle / 2), *(math.sin(angle / 2) * turn / angle)])
            self.q = _multiply(self.q, dq)
            self.q /= np.linalg.norm(self.q)
        self.angle = self.angle + h * self.v[6:10]

    def do_step(self, current_time, step_size):
        self._start()
        h = self.p["internal_step"]
        remaining = step_size
        while remaining > 1e-9 * h:  # full steps, the last one shortened (as MujocoRover.advance)
            dt = min(h, remaining)
            if remaining - dt <= 1e-9 * h:
                dt = remaining
            self._substep(dt)
            remaining -= dt
        self._cache = None
        return True

    # -- checkpoints (canGetAndSetFMUstate, canSerializeFMUstate) ------------------------------
    def _get_fmu_state(self):
        state = super()._get_fmu_state()
        state["_internal"] = {
            "ready": self.ready,
            "q": self.q.tolist(),
            "c": self.c.tolist(),
            "v": self.v.tolist(),
            "angle": self.angle.tolist(),
        }
        return state

    def _set_fmu_state(self, state):
        internal = state.pop("_internal", None)
        super()._set_fmu_state({k: v for k, v in state.items() if k in self.p or k in self.u})
        if internal is not None:
            self.ready = False
            if internal["ready"]:
                self._start()
                self.q, self.c = np.array(internal["q"]), np.array(internal["c"])
                self.v, self.angle = np.array(internal["v"]), np.array(internal["angle"])
            self._cache = None
