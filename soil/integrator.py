"""Time integrators. Every integrator has step(model, state_in, state_out, control, dt, contacts).

- VelocityVerlet: plain explicit velocity Verlet, fixed step.
- JoltBeeman: the jolt-Beeman predictor-corrector (DESIGN.md section 3), one force
  evaluation per step, with the predictor/corrector gap as local error estimate; used
  with a fixed step (Simulation.run) or with the PID StepController
  (Simulation.run_adaptive).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np
import warp as wp

from . import boundaries
from .control import SoilControl
from .integrator_kernels import (
    SUMMARY_COLUMNS,
    SUMMARY_NONFINITE,
    SUMMARY_POSITION_GAP,
    SUMMARY_SPEED,
    SUMMARY_VELOCITY_GAP,
    SUMMARY_WORST,
    make_integrator_kernels,
)
from .model import SoilModel
from .solver import ContactSolver
from .state import SoilState


class VelocityVerlet:
    """Plain explicit velocity Verlet (kick-drift-kick), one force evaluation per step.

    Velocity-dependent forces (damping, friction) see the half-step velocity, as in
    LAMMPS' fix nve/sphere.
    """

    name = "verlet"

    def step(self, model: SoilModel, state_in: SoilState, state_out: SoilState, control: SoilControl,
             dt: float, contacts: ContactSolver) -> None:
        prec = model.precision
        gravity = prec.vec_hi(*model.gravity)
        hi_dt = prec.hi(dt)
        control.push()  # the boundaries move with this step's control
        wp.launch(contacts.kernels["kick_drift"], dim=model.particle_count,
                  inputs=[state_in.position, state_in.velocity, state_in.angular_velocity, state_in.force,
                          state_in.torque, model.inv_mass, model.inv_inertia, gravity, hi_dt],
                  outputs=[state_out.position, state_out.velocity, state_out.angular_velocity],
                  device=model.device)
        boundaries.verlet_first_half(model, state_in, state_out, control, dt)
        contacts.compute(state_in, state_out, control, dt)
        wp.launch(contacts.kernels["kick"], dim=model.particle_count,
                  inputs=[state_out.force, state_out.torque, model.inv_mass, model.inv_inertia, gravity, hi_dt],
                  outputs=[state_out.velocity, state_out.angular_velocity], device=model.device)
        boundaries.verlet_second_half(model, state_out, control, dt)
        # Verlet keeps no multi-step history: a jolt-Beeman step after it starts afresh (zero jolt)
        state_out.step_previous.zero_()
        state_out.time = state_in.time + dt


class JoltBeeman:
    """Jolt-Beeman predictor-corrector, translation and rotation, one force evaluation per step.

    With a = a(t), a_minus = a(t - dt) and a+ = a(t + dt):

    1. predict (explicit, constant jolt (a - a_minus)/dt):
       x+ = x + v dt + (4 a - a_minus) dt^2/6,  v_pred = v + (3 a - a_minus) dt/2,
       and the same for the spin with the angular acceleration T / I;
    2. evaluate forces and torques at (x+, v_pred, w_pred) (the only force evaluation);
    3. correct: v+ = v + (2 a+ + 5 a - a_minus) dt/6 (Beeman), same for the spin.

    Variable steps: the state keeps the force of the previous state and the length of
    the step between them (SoilState.force_previous, step_previous). With a new step
    dt != dt_previous the constant-jolt line through a(t - dt_previous) and a(t) is
    extrapolated to t - dt: a_minus = a - (dt/dt_previous) (a - a(t - dt_previous)).
    Both Beeman formulas with that a_minus are exactly the Taylor/backward-Taylor
    expansions with constant jolt, so the scheme keeps its order at any step ratio
    (it is the variable-step Beeman form, written with a rescaled a_minus).
    The first step (step_previous = 0) assumes zero jolt: a_minus = a.

    Local error estimate (the predictor/corrector gap), per particle:
    |v+ - v_pred| = |a+ - 2 a + a_minus| dt/3 [m/s] (and r |w+ - w_pred| for the spin),
    and the position gap dt/2 of that, divided by the radius [-]. After each step the
    maxima are in `summary` (device array, see soil.integrator_kernels SUMMARY_*);
    `read_summary()` copies them to the host.
    """

    name = "jolt-beeman"
    error_order = 3
    """The error estimate scales as dt^3 where the motion is smooth."""

    def __init__(self):
        self.gaps = None
        """Per-particle gaps of the last step: [position gap / r, velocity gap m/s], shape
        (particle_count, 2), dtype hi (for the RMS error norm)."""
        self.summary = None
        """Per-step maxima [position gap / r, velocity gap m/s, speed m/s, non-finite flag, index],
        shape (SUMMARY_COLUMNS,), dtype hi, on the model's device."""

    def step(self, model: SoilModel, state_in: SoilState, state_out: SoilState, control: SoilControl,
             dt: float, contacts: ContactSolver) -> None:
        prec = model.precision
        kernels = make_integrator_kernels(prec.hi, prec.lo, model.law)
        gravity = prec.vec_hi(*model.gravity)
        hi_dt = prec.hi(dt)
        n = model.particle_count
        if self.summary is None or self.summary.device != wp.get_device(model.device) or self.gaps.shape[0] != n:
            self.summary = wp.zeros(SUMMARY_COLUMNS, dtype=prec.hi, device=model.device)
            self.gaps = wp.zeros((n, 2), dtype=prec.hi, device=model.device)
        control.push()  # the boundaries move with this step's control
        wp.launch(kernels["beeman_predict"], dim=n,
                  inputs=[state_in.position, state_in.velocity, state_in.angular_velocity, state_in.force,
                          state_in.torque, state_in.force_previous, state_in.torque_previous,
                          state_in.step_previous, model.inv_mass, model.inv_inertia, gravity, hi_dt],
                  outputs=[state_out.position, state_out.velocity, state_out.angular_velocity,
                           state_out.force_previous, state_out.torque_previous, state_out.step_previous],
                  device=model.device)
        boundaries.beeman_predict(model, state_in, state_out, control, dt)
        contacts.compute(state_in, state_out, control, dt)
        self.summary.zero_()
        wp.launch(kernels["beeman_correct"], dim=n,
                  inputs=[state_in.velocity, state_in.angular_velocity, state_out.position, state_in.force,
                          state_in.torque, state_in.force_previous, state_in.torque_previous,
                          state_in.step_previous, state_out.force, state_out.torque, model.inv_mass,
                          model.inv_inertia, model.radius, gravity, hi_dt],
                  outputs=[state_out.velocity, state_out.angular_velocity, self.summary, self.gaps],
                  device=model.device)
        boundaries.beeman_correct(model, state_in, state_out, control, dt)
        state_out.time = state_in.time + dt

    def read_summary(self) -> dict:
        """The last step's maxima on the host: position_gap [-] (/ radius), velocity_gap [m/s],
        speed [m/s], nonfinite (bool), worst (index of a non-finite particle or -1)."""
        values = self.summary.numpy().astype(np.float64)
        nonfinite = bool(values[SUMMARY_NONFINITE] > 0)
        return {"gaps": self.gaps.numpy().astype(np.float64),
                "position_gap": float(values[SUMMARY_POSITION_GAP]),
                "velocity_gap": float(values[SUMMARY_VELOCITY_GAP]),
                "speed": float(values[SUMMARY_SPEED]),
                "nonfinite": nonfinite,
                "worst": int(values[SUMMARY_WORST]) if nonfinite else -1}


@dataclass
class StepController:
    """PID step-size control in Soderlind's form (DESIGN.md section 3) on a NORMALISED error.

    The local error of a step is the jolt-Beeman predictor/corrector gap, made
    dimensionless with the scene's own scales:

        e_i = max( |dx_i| / r_i ,  |dv_i| / V ),
        V   = max( sqrt(|g| r_mean),  largest speed seen in this run,  velocity_scale ),
        err = max( sqrt(mean_i e_i^2), max_i e_i / grain_factor )   (norm='rms', default)
        err = max_i e_i                                              (norm='max'),

    so a scene scaled to another gravity (E ~ g, times ~ sqrt(r/g), speeds ~ sqrt(g r))
    gets the same errors and the same steps with the same tolerance; an absolute
    tolerance (the paper's) does not (`normalise=False` reproduces that: err in m/s).

    The RMS norm (Hairer's choice for large systems) keeps one chattering contact (a
    stick/slip switch makes a force jump, whose gap shrinks only like dt) from setting the
    step of a whole bed; the max norm bounds every grain's error. The RMS over N grains
    dilutes one grain's error by sqrt(N), so a grain going unstable could hide in a large
    bed (it did: 20k grains at twice the advised step, BENCHMARKS.md); the guard term
    keeps every grain within grain_factor x tolerance.

    With c = (tolerance / err)^(1/k) (k = error order, 3 for jolt-Beeman), the step
    factor is rho = c_n^b1 c_(n-1)^b2 c_(n-2)^b3, b1 = kI + kP + kD, b2 = -(kP + 2 kD),
    b3 = kD, limited to [rho_min, rho_max]; dt_next = rho dt within [dt_min, dt_max].
    A step is rejected (and redone with dt * min(0.9 c_n, 0.9), at least rho_min) when
    rho < reject_below AND err > tolerance: a step that met the tolerance is kept even if
    the controller slows down for the next one. At dt_min a step is always accepted
    (counted in `forced`); a non-finite error at dt_min is a divergence.

    Defaults kI = 0.4, kP = 0.3, kD = 0.05: the closed loop on a log-linear error model,
    z^3 + (b1 - 1) z^2 + b2 z + b3, has its roots at |z| <= 0.72 (smooth, no ringing);
    Gustafsson's PI (0.3, 0.4, 0) is the classic alternative.
    """

    tolerance: float = 1e-4
    """Normalised local error per step [-]."""
    dt_max: float | None = None
    """Largest step [s]; None: the advisor's recommended limit for the model (soil.advisor)."""
    dt_min: float | None = None
    """Smallest step [s]; None: dt_max * 1e-4."""
    dt_initial: float | None = None
    """First step [s]; None: dt_max / 10 (the first step has no jolt history)."""
    k_i: float = 0.4
    """Integral gain [-]."""
    k_p: float = 0.3
    """Proportional gain [-]."""
    k_d: float = 0.05
    """Derivative gain [-]."""
    order: float = 3.0
    """k: the error estimate scales as dt^k [-]."""
    rho_min: float = 0.2
    """Smallest step factor per decision [-]."""
    rho_max: float = 2.0
    """Largest step factor per decision [-]."""
    reject_below: float = 0.9
    """A step whose factor rho falls below this (and whose error exceeds the tolerance) is redone [-]."""
    velocity_scale: float = 0.0
    """Extra floor of the velocity scale V [m/s] (e.g. a wheel speed); 0: from gravity and motion only."""
    normalise: bool = True
    """False: absolute error in m/s (the paper's original controller, breaks at milli-g)."""
    norm: str = "rms"
    """'rms' (root mean square over grains) or 'max' (the worst grain)."""
    grain_factor: float = 10.0
    """With norm='rms': no single grain's error may exceed grain_factor x tolerance [-]; inf: pure RMS."""
    history: list = field(default_factory=list, repr=False)
    """c values of the last accepted steps, newest last (internal)."""
    dt: float | None = field(default=None, repr=False)
    """The step the controller proposes next [s] (internal; None before setup)."""
    speed_seen: float = field(default=0.0, repr=False)
    """Largest speed seen so far [m/s] (internal)."""

    def __post_init__(self):
        if not (math.isfinite(self.tolerance) and self.tolerance > 0):
            raise ValueError(f"tolerance must be > 0, got {self.tolerance!r}")
        if self.norm not in ("rms", "max"):
            raise ValueError(f"norm must be 'rms' or 'max', got {self.norm!r}")
        if not self.grain_factor >= 1.0:
            raise ValueError(f"grain_factor must be >= 1 (inf: pure RMS), got {self.grain_factor!r}")
        if not 0 < self.rho_min < self.reject_below <= 1.0 < self.rho_max:
            raise ValueError("need 0 < rho_min < reject_below <= 1 < rho_max, got "
                             f"{self.rho_min}, {self.reject_below}, {self.rho_max}")

    _OPTIONAL = ("dt_max", "dt_min", "dt_initial", "dt")

    def state_dict(self) -> dict:
        """Settings and control state as numpy scalars/arrays (None stored as NaN)."""
        data = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "history":
                data[f.name] = np.asarray(value, dtype=np.float64).reshape(-1)
            elif value is None:
                data[f.name] = np.float64(np.nan)
            elif isinstance(value, str):
                data[f.name] = np.str_(value)
            else:
                data[f.name] = np.asarray(value)[()]
        return data

    def load_state_dict(self, data: dict) -> None:
        """Restore from state_dict() (unknown keys are an error; missing keys keep their value)."""
        known = {f.name for f in fields(self)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"step controller: unknown fields {sorted(unknown)}")
        for name, value in data.items():
            value = np.asarray(value)
            if name == "history":
                setattr(self, name, [float(v) for v in value.reshape(-1)])
            elif name in self._OPTIONAL:
                setattr(self, name, None if np.isnan(value) else float(value))
            elif value.dtype.kind == "U":
                setattr(self, name, str(value))
            elif value.dtype.kind == "b":
                setattr(self, name, bool(value))
            else:
                setattr(self, name, float(value))
        self.__post_init__()

    @property
    def exponents(self) -> tuple[float, float, float]:
        """(b1, b2, b3) of the Soderlind form."""
        return (self.k_i + self.k_p + self.k_d, -(self.k_p + 2.0 * self.k_d), self.k_d)

    def setup(self, sim) -> None:
        """Resolve the defaults for a Simulation (once; later calls keep the state of the control)."""
        model = sim.model
        if self.dt_max is None:
            from .advisor import recommended_time_step

            self.dt_max = recommended_time_step(sim).dt_max
        if self.dt_min is None:
            self.dt_min = 1e-4 * self.dt_max
        if not 0 < self.dt_min <= self.dt_max:
            raise ValueError(f"need 0 < dt_min <= dt_max, got {self.dt_min!r}, {self.dt_max!r} [s]")
        if self.dt is None:
            self.dt = float(np.clip(self.dt_initial or 0.1 * self.dt_max, self.dt_min, self.dt_max))
        self._gravity_speed = math.sqrt(float(np.linalg.norm(model.gravity)) * float(model.radius_numpy().mean()))

    def error(self, summary: dict) -> float:
        """Normalised error [-] of a step from JoltBeeman.read_summary()."""
        if summary["nonfinite"]:
            return math.inf
        rms = self.norm == "rms" and "gaps" in summary
        if not self.normalise:
            return self._rms_norm(summary["gaps"][:, 1]) if rms else summary["velocity_gap"]
        self.speed_seen = max(self.speed_seen, summary["speed"])
        scale = max(self._gravity_speed, self.speed_seen, self.velocity_scale)
        if rms:
            gaps = summary["gaps"]
            per_grain = np.maximum(gaps[:, 0], gaps[:, 1] / scale if scale > 0 else np.where(gaps[:, 1] > 0, np.inf, 0))
            return self._rms_norm(per_grain)
        velocity = summary["velocity_gap"] / scale if scale > 0 else (math.inf if summary["velocity_gap"] > 0 else 0.0)
        return max(summary["position_gap"], velocity)

    def _rms_norm(self, per_grain: np.ndarray) -> float:
        """RMS over grains, raised to max / grain_factor where one grain stands out (it must not hide)."""
        return float(max(np.sqrt(np.mean(per_grain**2)), per_grain.max(initial=0.0) / self.grain_factor))

    def decide(self, err: float, dt: float) -> tuple[bool, float]:
        """(accept, next step [s]) for a step of length dt [s] with normalised error err."""
        k = self.order
        if not math.isfinite(err):
            return False, max(self.dt_min, self.rho_min * dt)
        # an error ~0 (free flight) would make c huge and dominate the next decisions
        c = (self.tolerance / max(err, 1e-3 * self.tolerance)) ** (1.0 / k)
        previous = self.history[-1] if self.history else 1.0
        before = self.history[-2] if len(self.history) > 1 else previous
        b1, b2, b3 = self.exponents
        rho = float(np.clip(c**b1 * previous**b2 * before**b3, self.rho_min, self.rho_max))
        if rho < self.reject_below and err > self.tolerance:
            return False, max(self.dt_min, dt * max(self.rho_min, min(0.9 * c, 0.9)))
        self.history = (self.history + [c])[-2:]
        return True, float(np.clip(rho * dt, self.dt_min, self.dt_max))
