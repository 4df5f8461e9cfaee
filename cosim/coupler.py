"""Macro-step coupling of a SoilSide with a RoverSide (docs/coupling.md, "Macro steps").

Schemes, macro step H, from t to t + H:

- 'gauss-seidel' (default): the soil advances first, moving the wheels with the rover's
  kinematics at t extrapolated at constant velocity, and returns the wrench averaged
  over [t, t+H]; the rover then advances to t+H holding that wrench. Explicit, first
  order in H, but the wrench belongs to the same interval it acts on.
- 'jacobi': both sides advance from the same t (they could run in parallel); the rover
  holds the wrench of the previous macro step (one-step lag; zero in the first step).

Energy bookkeeping per macro step, per wheel: the work the held wrench does on the
rover, W_rover = F . (p1 - p0) + tau . (w0 + w1) H / 2 (exact for the held force, trapezoid
for the torque), against the work done on the soil, W_soil = the soil's reported
work_on_soil (along the extrapolated wheel path) plus the work of the soil's end wrench
when its wheel is moved from the extrapolated end pose to the rover's actual pose (the
next step starts there). A lossless coupling has W_rover + W_soil = 0; a positive sum is
energy the coupling created (Gauss-Seidel: O(H^2) overall; Jacobi's lag: O(H)). When the accumulated created energy
exceeds `energy_atol + energy_rtol * sum |W_rover|` a CouplingEnergyWarning is issued
(once per coupler, not during the first `energy_warmup` steps).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from soil.control import quaternion_integrate, quaternion_multiply
from soil.errors import ArgumentError, RegolithError, RegolithWarning, is_real

from .contract import WRENCH_UNITS, RoverSide, SoilSide, WheelKinematics, WheelWrench, advance_soil
from .controllers import apply_command


class CouplingEnergyWarning(RegolithWarning, RuntimeWarning):
    """The coupling created more energy than the tolerance allows (H too large?)."""


class CouplingTimeError(RegolithError, RuntimeError):
    """The soil and rover sides did not reach the same time."""


@dataclass
class MacroStepRecord:
    """What one macro step produced: the wheels at its end and the wrenches they held."""

    time: float
    """End time of the step [s]."""
    kinematics: list[WheelKinematics]
    """Wheel kinematics at the end of the step, one per wheel."""
    wrenches: list[WheelWrench]
    """The soil wrench each wheel held during the step (force, torque: held values; force_end,
    torque_end: the soil's end values; contact_count, sinkage, work_on_soil)."""
    work_on_rover: np.ndarray
    """Work of the held wrench on the rover [J], shape (W,)."""
    work_on_soil: np.ndarray
    """Work done on the soil, including the jump to the rover's actual end pose [J], shape (W,)."""


def stack_records(records: Sequence[MacroStepRecord]) -> dict[str, np.ndarray]:
    """Records as arrays (S = records, W = wheels): time [s] (S,); position [m], linear_velocity
    [m/s], angular_velocity [rad/s], force [N], torque [N m] (S, W, 3); orientation (S, W, 4);
    sinkage [m], contact_count, work_on_rover, work_on_soil [J] (S, W)."""

    def wheels(get):
        return np.array([[get(k, w) for k, w in zip(r.kinematics, r.wrenches)] for r in records])

    return {
        "time": np.array([r.time for r in records], dtype=np.float64),
        "position": wheels(lambda k, w: k.position),
        "orientation": wheels(lambda k, w: k.orientation),
        "linear_velocity": wheels(lambda k, w: k.linear_velocity),
        "angular_velocity": wheels(lambda k, w: k.angular_velocity),
        "force": wheels(lambda k, w: w.force),
        "torque": wheels(lambda k, w: w.torque),
        "sinkage": wheels(lambda k, w: w.sinkage),
        "contact_count": wheels(lambda k, w: w.contact_count),
        "work_on_rover": np.array([r.work_on_rover for r in records]),
        "work_on_soil": np.array([r.work_on_soil for r in records]),
    }


class Coupler:
    """Couples one soil side and one rover side with a fixed macro step.

    Args:
        soil: SoilSide (DEM, analytic terrain, ...).
        rover: RoverSide (MuJoCo, FMU, ...); same wheel count and order as the soil.
        macro_step: H [s].
        scheme: 'gauss-seidel' or 'jacobi'.
        gravity: the scene's one gravity vector [m/s^2], shape (3,), pushed to both sides.
        controller: optional drive controller (see cosim.controllers), called at the
            start of every macro step; its command is held over the step.
        energy_rtol, energy_atol: tolerance of the energy check [-], [J].
        energy_warmup: macro steps before the energy check starts; the first steps of a
            contact exchange little energy, so their ratio is noise.
        time_tol: largest accepted difference between the sides' times [s].
    """

    def __init__(
        self,
        soil: SoilSide,
        rover: RoverSide,
        macro_step: float,
        scheme: str = "gauss-seidel",
        gravity: Sequence[float] = (0.0, 0.0, -9.81),
        controller: Callable | None = None,
        energy_rtol: float = 0.05,
        energy_atol: float = 1e-9,
        energy_warmup: int = 10,
        time_tol: float = 1e-12,
    ):
        if not isinstance(scheme, str) or scheme.lower().replace("_", "-") not in ("gauss-seidel", "jacobi"):
            raise ArgumentError(f"scheme must be 'gauss-seidel' or 'jacobi', got {scheme!r}")
        scheme = scheme.lower().replace("_", "-")
        if not (is_real(macro_step) and math.isfinite(macro_step) and macro_step > 0.0):  # inf never ended
            raise ArgumentError(f"macro_step must be a finite number > 0 [s], got {macro_step!r}")
        n = len(rover.wheel_names)
        if soil.wheel_count != n:
            raise ArgumentError(f"the soil has {soil.wheel_count} wheels, the rover {n} ({rover.wheel_names})")
        self.soil = soil
        self.rover = rover
        self.macro_step = float(macro_step)
        """Macro step H [s]."""
        self.scheme = scheme
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3).copy()
        """Scene gravity [m/s^2], shape (3,)."""
        self.controller = controller
        self.energy_rtol = float(energy_rtol)
        self.energy_atol = float(energy_atol)
        self.energy_warmup = int(energy_warmup)
        self.time_tol = float(time_tol)
        self.wheel_count = n

        soil.set_gravity(self.gravity)
        rover.set_gravity(self.gravity)
        self._check_times(soil.time, rover.time, "start")
        self.time = float(rover.time)
        """Coupled time [s]."""
        self.step_count = 0
        self._lagged = [WheelWrench() for _ in range(n)]  # Jacobi's previous wrench
        self._last = [WheelWrench() for _ in range(n)]  # wrench of the previous step (controller input)
        self.energy_created = 0.0
        """Accumulated W_rover + W_soil over all steps [J] (> 0: the coupling created energy)."""
        self.energy_exchanged = 0.0
        """Accumulated |W_rover| over all steps [J]."""
        self._warned = False

    # --------------------------------------------------------------------------------

    def _check_times(self, t_soil: float, t_rover: float, where: str) -> None:
        if abs(t_soil - t_rover) > self.time_tol:
            raise CouplingTimeError(f"{where}: soil at t={t_soil!r} s, rover at t={t_rover!r} s")

    def step(self, meanwhile: Callable[[], None] | None = None) -> MacroStepRecord:
        """Advance both sides by one macro step; returns what the step produced.

        meanwhile: the caller's own work that needs neither side (the records of the step
        before), done once while the soil computes when the soil offers that (SoilSide.advance),
        else after the soil's advance. It must not raise."""
        t0 = self.time
        t1 = t0 + self.macro_step
        rover, soil = self.rover, self.soil
        k0 = rover.wheel_kinematics()
        if self.controller is not None:
            apply_command(rover, self.controller(t0, k0, self._last))
        if self.scheme == "jacobi":
            held = self._lagged
            rover.apply_wheel_wrenches(held)
        wrenches = advance_soil(soil, t1, k0, None, meanwhile)
        if self.scheme == "gauss-seidel":
            held = wrenches
            rover.apply_wheel_wrenches(held)
            rover.advance(t1)
        else:
            rover.advance(t1)
            self._lagged = wrenches
        self._check_times(soil.time, rover.time, f"macro step {self.step_count}")
        if abs(rover.time - t1) > self.time_tol:
            raise CouplingTimeError(f"macro step {self.step_count}: sides at t={rover.time!r} s, expected {t1!r} s")
        k1 = rover.wheel_kinematics()
        self.time = t1
        self.step_count += 1
        self._last = wrenches

        # Energy bookkeeping (see module docstring).
        h = self.macro_step
        w_rover = np.array(
            [
                w.force @ (b.position - a.position)  # exact for a force held constant
                + w.torque @ (a.angular_velocity + b.angular_velocity) * (h / 2)
                for w, a, b in zip(held, k0, k1)
            ]
        )
        # The soil moved each wheel along the extrapolated path (end: p_ext, q_ext); the
        # next step starts it where the rover really is, a jump that does work on the
        # soil too. Without it, W_rover + W_soil carries a spurious +F . a H^2 / 2 per step.
        w_soil = np.array([w.work_on_soil - _jump_work(w, a, b, h) for w, a, b in zip(wrenches, k0, k1)])
        self.energy_created += float(np.sum(w_rover + w_soil))
        self.energy_exchanged += float(np.sum(np.abs(w_rover)))
        if (
            not self._warned
            and self.step_count > self.energy_warmup
            and self.energy_created > self.energy_atol + self.energy_rtol * self.energy_exchanged
        ):
            self._warned = True
            warnings.warn(
                f"coupling created {self.energy_created:.3e} J by t={t1:.6g} s "
                f"(exchanged {self.energy_exchanged:.3e} J, tolerance "
                f"{self.energy_atol:.1e} J + {self.energy_rtol:.1e} x exchanged); "
                f"reduce the macro step H={h:g} s",
                CouplingEnergyWarning,
                stacklevel=2,
            )
        return MacroStepRecord(t1, k1, list(held), w_rover, w_soil)

    @property
    def energy_over_tolerance(self) -> bool:
        """Whether the coupling created more energy than its tolerance (the CouplingEnergyWarning was issued)."""
        return self._warned

    def run(self, t_end: float, callback: Callable[[Coupler], None] | None = None) -> list[MacroStepRecord]:
        """Macro-step until t_end [s] (rounded to a whole number of steps); returns the records.

        callback(coupler) is called after every macro step.
        """
        if not (is_real(t_end) and math.isfinite(t_end) and t_end >= self.time - 0.5 * self.macro_step):
            raise ArgumentError(
                f"t_end must be a finite time [s] not before the coupler's {self.time!r} s, got {t_end!r}"
            )
        steps = int(round((float(t_end) - self.time) / self.macro_step))
        records = []
        for _ in range(steps):
            records.append(self.step())
            if callback is not None:
                callback(self)
        return records

    # -- checkpoints -------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The coupler's own state (the sides and the controller keep theirs)."""
        state: dict[str, Any] = {
            "time": self.time,
            "step_count": self.step_count,
            "energy_created": self.energy_created,
            "energy_exchanged": self.energy_exchanged,
            "warned": self._warned,
        }
        for name, wrenches in (("lagged", self._lagged), ("last", self._last)):
            for field in _WRENCH_FIELDS:
                state[f"{name}/{field}"] = np.array([getattr(w, field) for w in wrenches])
        return state

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}."""
        units = {"time": "s", "step_count": "count", "energy_created": "J", "energy_exchanged": "J", "warned": "1"}
        for name in ("lagged", "last"):
            units.update({f"{name}/{field}": WRENCH_UNITS[field] for field in _WRENCH_FIELDS})
        return units

    def load_state_dict(self, state: dict) -> None:
        self.time = float(state["time"])
        self.step_count = int(state["step_count"])
        self.energy_created = float(state["energy_created"])
        self.energy_exchanged = float(state["energy_exchanged"])
        self._warned = bool(state["warned"])
        for name in ("lagged", "last"):
            values = {field: state[f"{name}/{field}"] for field in _WRENCH_FIELDS}
            wrenches = []
            for i in range(self.wheel_count):
                fields: dict[str, Any] = {
                    field: (
                        int(v[i])
                        if field == "contact_count"
                        else float(v[i])
                        if np.ndim(v[i]) == 0
                        else np.array(v[i], dtype=np.float64)
                    )
                    for field, v in values.items()
                }
                wrenches.append(WheelWrench(**fields))
            setattr(self, f"_{name}", wrenches)


def _jump_work(w: WheelWrench, k0: WheelKinematics, k1: WheelKinematics, h: float) -> float:
    """Work [J] of the soil's end wrench on the wheel when it jumps from the extrapolated
    end pose (k0 moved at constant velocity for h) to the rover's actual pose k1."""
    dp = k1.position - (k0.position + k0.linear_velocity * h)
    q_ext = quaternion_integrate(k0.orientation, k0.angular_velocity, h)
    dq = quaternion_multiply(k1.orientation, q_ext * np.array([1.0, -1.0, -1.0, -1.0]))
    if dq[0] < 0.0:
        dq = -dq
    sin_half = np.linalg.norm(dq[1:])
    rotation = (2.0 * np.arctan2(sin_half, dq[0]) / sin_half) * dq[1:] if sin_half > 1e-15 else 2.0 * dq[1:]
    return float(w.force_end @ dp + w.torque_end @ rotation)


_WRENCH_FIELDS = ("force", "torque", "force_end", "torque_end", "contact_count", "sinkage", "work_on_soil")
