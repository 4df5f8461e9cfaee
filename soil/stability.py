"""Divergence detection (docs/physics.md section 2): stop an exploding simulation, keep the last good state.

An explicit DEM step that is too large for the contact stiffness pumps energy into the
contacts: overlaps deepen, speeds grow without bound, then values turn NaN. The
DivergenceMonitor compares the state with bounds taken from the scene itself when it
is armed (start of a run):

- speed:   max_i max(|v_i|, r_i |w_i|) <= speed_factor * (sqrt(2 |g| H) + v0 + v_el + v_body + speed_floor)
           H: height span of the grains along gravity (+ 2 r_max) [m]; v0: largest initial
           speed; v_el = sqrt(2 E_el0 / m_min): speed the initial overlaps can give;
           v_body: largest rim speed of the wheels seen so far (their motion is input);
- energy:  kinetic energy <= energy_factor * (KE0 + E_el0 + M |g| H + M v_body^2 / 2 + M speed_floor^2 / 2)
           (what gravity, initial motion, initial overlaps and the wheels can supply);
- overlap: max contact overlap / radius <= max_overlap_ratio (a Hertz contact deeper than
           that is far outside the law's validity: a stiffness/time-step problem);
- finite:  no NaN / inf anywhere.

A check is one reduction kernel over the particles (plus a host sum of the kinetic
energy) and runs every N steps; between checks the state is copied (device to device)
into a snapshot, the "last good state". On failure SimulationDiverged names the time,
the step, the worst particle and its position, carries the snapshot as numpy arrays in
`last_good`, and, if the Simulation has a checkpoint_path, writes it there atomically.
"""

import json
import math
import os
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .boundaries import MOTION_LOADED
from .errors import RegolithError
from .files import atomic_path
from .precision import kernel_factory, kernel_module, soil_kernel
from .sdf import sdf_functions
from .state import STATE_UNITS, SoilState, storage_functions

# Columns of the divergence-check summary (shape (CHECK_COLUMNS,), dtype hi).
CHECK_SPEED = 0
"""max_i max(|v_i|, r_i |w_i|) [m/s]."""
CHECK_OVERLAP = 1
"""max over contacts of overlap / radius [-] (grain-grain and grain-wall)."""
CHECK_NONFINITE = 2
"""1 if any particle state is not finite."""
CHECK_COLUMNS = 3


@kernel_factory
def check_kernels(hi, mid, lo, slot_major: bool = False):
    """The divergence-check kernel for precision types (hi, mid, lo)."""
    module = kernel_module("check", hi, mid, lo, *(("slot",) if slot_major else ()))
    kernel = soil_kernel(module)
    entry = storage_functions(module, slot_major).entry
    vec_hi = wp.types.vector(3, hi)
    vec_mid = wp.types.vector(3, mid)
    boundary_contact = sdf_functions(hi).boundary_contact

    @kernel
    def divergence_metrics(
        x_in: wp.array(dtype=vec_hi),
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_mid),
        radius: wp.array(dtype=lo),
        inv_mass: wp.array(dtype=lo),
        neighbours: wp.array3d(dtype=wp.int32),
        neighbour_count: wp.array2d(dtype=wp.int32),
        row: int,
        boundary_kind: wp.array(dtype=wp.int32),
        boundary_geometry: wp.array2d(dtype=hi),
        boundary_displacement: wp.array(dtype=vec_hi),
        order: wp.array(dtype=wp.int32),
        world_size: int,
        walls_per_world: int,
        # outputs
        speed_out: wp.array(dtype=hi),
        overlap_out: wp.array(dtype=hi),
        summary_out: wp.array(dtype=hi),
    ):
        """Per grain (storage order): speed [m/s] and the largest overlap / radius [-] over its
        neighbour-list row and its world's walls (soil.worlds); maxima into summary_out (atomic max:
        order-independent).

        A non-finite grain gets speed = overlap = +inf so that the host can locate it.
        """
        i = wp.tid()
        xi = x_in[i]
        ri = hi(radius[i])
        wi = vec_hi(w_in[i])
        if not (wp.isfinite(xi) and wp.isfinite(v_in[i]) and wp.isfinite(wi)):
            inf = hi(wp.inf)
            speed_out[i] = inf
            overlap_out[i] = inf
            wp.atomic_max(summary_out, CHECK_NONFINITE, hi(1.0))
            return
        worst = hi(0.0)
        for k in range(neighbour_count[row, i]):
            j = entry(neighbours, row, i, k)
            rj = hi(radius[j])
            overlap = ri + rj - wp.length(x_in[j] - xi)
            worst = wp.max(worst, overlap / wp.min(ri, rj))
        if inv_mass[i] > lo(0.0):
            first_wall = (order[i] // world_size) * walls_per_world
            for b in range(first_wall, first_wall + walls_per_world):
                overlap, n = boundary_contact(boundary_kind[b], boundary_geometry, b, xi - boundary_displacement[b], ri)
                worst = wp.max(worst, overlap / ri)
        speed = wp.max(wp.length(v_in[i]), ri * wp.length(wi))  # spin counts at the surface
        speed_out[i] = speed
        overlap_out[i] = worst
        wp.atomic_max(summary_out, CHECK_SPEED, speed)
        wp.atomic_max(summary_out, CHECK_OVERLAP, worst)

    return dict(divergence_metrics=divergence_metrics)


class SimulationDiverged(RegolithError, RuntimeError):
    """The simulation became unstable; `last_good` holds the last good state as numpy arrays.

    Attributes: time [s] and step of the failure, particle (model index, or None), position [m]
    of that particle (3,), reason (str), last_good (dict of numpy arrays, SoilState.to_numpy()
    plus 'step'), checkpoint (path written, or None), elsewhere (True: found in another world of
    a batch, soil.worlds; this world's own state is sound).
    """

    def __init__(
        self,
        message: str,
        last_good: dict | None = None,
        *,
        time: float | None = None,
        step: int | None = None,
        particle: int | None = None,
        position=None,
        reason: str = "",
        checkpoint: str | None = None,
        elsewhere: bool = False,
    ):
        super().__init__(message)
        self.elsewhere = elsewhere
        self.last_good = last_good
        self.time = time
        self.step = step
        self.particle = particle
        self.position = position
        """Position of that particle [m], shape (3,), or None."""
        self.reason = reason
        self.checkpoint = checkpoint


CHECKSUM_KEY = "integrity/sha256"
"""The key of a checkpoint's checksum: SHA-256 over every other array (name, dtype, shape, bytes)."""
UNITS_KEY = "units"
"""The key of a saved state's units (write_checkpoint's `units`): a JSON object {array name: unit}."""


def checkpoint_digest(data: dict) -> str:
    """SHA-256 (hex) over the arrays of a state dict, in key order (name, dtype, shape and bytes of each)."""
    import hashlib

    digest = hashlib.sha256()
    for key in sorted(k for k in data if k != CHECKSUM_KEY):
        value = np.ascontiguousarray(np.asarray(data[key]))
        digest.update(f"{key}|{value.dtype.str}|{value.shape}|".encode())
        digest.update(value.tobytes())
    return digest.hexdigest()


def write_checkpoint(path, data: dict, units: dict[str, str] | None = None) -> str:
    """Write a state dict (numpy arrays) to `path` as .npz atomically (soil.files.atomic_path),
    so a crash never leaves half a checkpoint; its checksum goes with it (read_checkpoint verifies it).
    units: {name: unit} of the arrays: stored under UNITS_KEY as JSON, for those it names (a missing
    unit must not cost a diverged run its last good state; the tests check the tables are complete)."""
    path = os.fspath(path)
    arrays: dict = {key: np.asarray(value) for key, value in data.items() if key not in (CHECKSUM_KEY, UNITS_KEY)}
    if units is not None:
        arrays[UNITS_KEY] = np.array(json.dumps({key: units[key] for key in arrays if key in units}))
    arrays[CHECKSUM_KEY] = np.array(checkpoint_digest(arrays))
    with atomic_path(path, ".npz.tmp") as temporary:  # an OSError names `path`
        with open(temporary, "wb") as f:
            np.savez(f, **arrays)
    return path


def read_checkpoint(path) -> dict:
    """A checkpoint's arrays (no pickles), its checksum verified; DamagedFileError naming the file when
    it is not a readable .npz (cut short, bytes changed) or its arrays do not match their checksum."""
    from .errors import DamagedFileError

    path = os.fspath(path)
    try:
        with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as stored:  # closed also on failure
            data = {key: stored[key] for key in stored.files}
    except (FileNotFoundError, PermissionError):
        raise
    except Exception as error:  # zipfile.BadZipFile, a bad CRC, a cut header, a garbled array header
        raise DamagedFileError(
            f"{path}: the checkpoint is damaged (not a readable .npz archive: {error}); it was left as it is"
        ) from None
    saved = data.pop(CHECKSUM_KEY, None)
    if saved is not None and str(saved) != checkpoint_digest(data):
        raise DamagedFileError(
            f"{path}: the checkpoint is damaged (its arrays do not match their SHA-256 checksum); it was left as it is"
        )
    data.pop(UNITS_KEY, None)  # the arrays' units are the writer's (STATE_UNITS for a soil state)
    return data


@dataclass
class DivergenceMonitor:
    """Physical bounds on the state; see the module docstring. One per Simulation."""

    speed_factor: float = 10.0
    """Allowed speed as a multiple of the scene's speed scale [-]."""
    energy_factor: float = 10.0
    """Allowed kinetic energy as a multiple of the energy the scene can supply [-]."""
    max_overlap_ratio: float = 0.5
    """Largest allowed contact overlap / radius [-]."""
    height: float | None = None
    """Fall height H [m]; None: the grains' span along gravity + 2 r_max at arming."""
    speed_floor: float = 0.0
    """Extra speed the scene may reach [m/s] (e.g. external forces the monitor cannot see)."""
    enabled: bool = True
    """False: no checks except non-finite values."""
    armed: bool = field(default=False, repr=False)
    speed_bound: float = field(default=math.inf, repr=False)
    """Current speed bound [m/s] (after arming)."""
    energy_bound: float = field(default=math.inf, repr=False)
    """Current kinetic-energy bound [J] (after arming)."""

    def __post_init__(self):
        self._good = None  # the last-good snapshot (a SoilState), made by arm()/check()
        self._good_step = 0

    # -- bounds ------------------------------------------------------------------
    def arm(self, sim) -> None:
        """Take the scene's scales from the current state and snapshot it as the last good state."""
        model = sim.model
        free = model.inv_mass.numpy() > 0
        mass = model.mass_numpy()
        radius = model.radius_numpy()
        x = sim.positions()
        g = float(np.linalg.norm(model.gravity))
        if self.height is not None:
            height = float(self.height)
        elif g > 0 and free.any():
            along = x[free] @ (-model.gravity / g)
            height = float(along.max() - along.min()) + 2.0 * model.max_radius
        else:
            height = 2.0 * model.max_radius
        v = np.linalg.norm(sim.velocities(), axis=1)
        spin = radius * np.linalg.norm(sim.angular_velocities(), axis=1)
        elastic = max(sim.elastic_energy(), 0.0) if np.isfinite(x).all() else 0.0
        m_free = mass[free] if free.any() else mass
        self._g, self._height = g, height
        self._mass_total = float(m_free.sum())
        self._v0 = float(np.max(np.maximum(v, spin)[free])) if free.any() else 0.0
        self._v_elastic = math.sqrt(2.0 * elastic / float(m_free.min()))
        self._energy0 = sim.kinetic_energy() + elastic
        self._body_reach = model.body_shape.numpy()[:, 5].astype(np.float64) if model.body_count else np.zeros(0)
        self._v_body = 0.0
        self._update_bounds(sim)
        self.armed = True
        self._good = None
        self.snapshot(sim)

    def _update_bounds(self, sim) -> None:
        control = sim.control
        if len(self._body_reach):
            rim = (
                np.linalg.norm(control.body_velocity_host, axis=1)
                + np.linalg.norm(control.body_angular_velocity_host, axis=1) * self._body_reach
            )
            self._v_body = max(self._v_body, float(rim.max()))
        load_work = 0.0
        if sim.model.boundary_count:  # moving walls drive the grains like wheels; loads do work
            walls = np.linalg.norm(sim.boundary_velocities(), axis=1)
            self._v_body = max(
                self._v_body, float(walls.max()), float(np.linalg.norm(control.boundary_velocity_host, axis=1).max())
            )
            loaded = control.boundary_mode_host == MOTION_LOADED
            travel = np.linalg.norm(sim.boundary_displacements(), axis=1) + self._height
            load_work = float(np.sum(np.abs(control.boundary_load_host[loaded]) * travel[loaded]))
        scale = math.sqrt(2.0 * self._g * self._height) + self._v0 + self._v_elastic + self._v_body + self.speed_floor
        self.speed_bound = self.speed_factor * scale
        supply = (
            self._energy0
            + self._mass_total * self._g * self._height
            + load_work
            + 0.5 * self._mass_total * (self._v_body**2 + self.speed_floor**2)
        )
        self.energy_bound = self.energy_factor * supply

    def for_new_grains(self) -> "DivergenceMonitor":
        """A monitor with this one's settings (factors, overlap limit, speed floor, on or off), not
        armed: for a simulation of other grains (a moved soil patch), whose scales it takes when it
        is armed on them; the fall height is measured on them again (not carried over)."""
        return DivergenceMonitor(
            speed_factor=self.speed_factor,
            energy_factor=self.energy_factor,
            max_overlap_ratio=self.max_overlap_ratio,
            speed_floor=self.speed_floor,
            enabled=self.enabled,
        )

    _SCALES = ("_g", "_height", "_mass_total", "_v0", "_v_elastic", "_energy0", "_v_body", "_body_reach")

    def state_dict(self) -> dict:
        """Settings, and once armed the scene's scales and bounds, as numpy scalars/arrays."""
        data = {
            "speed_factor": np.float64(self.speed_factor),
            "energy_factor": np.float64(self.energy_factor),
            "max_overlap_ratio": np.float64(self.max_overlap_ratio),
            "height": np.float64(np.nan if self.height is None else self.height),
            "speed_floor": np.float64(self.speed_floor),
            "enabled": np.bool_(self.enabled),
            "armed": np.bool_(self.armed),
        }
        if self.armed:
            data.update(speed_bound=np.float64(self.speed_bound), energy_bound=np.float64(self.energy_bound))
            data.update({name[1:]: np.asarray(getattr(self, name), dtype=np.float64) for name in self._SCALES})
        return data

    def load_state_dict(self, data: dict) -> None:
        """Restore from state_dict(); the last good state is then taken by snapshot()."""
        for name in ("speed_factor", "energy_factor", "max_overlap_ratio", "speed_floor"):
            setattr(self, name, float(data[name]))
        self.height = None if np.isnan(data["height"]) else float(data["height"])
        self.enabled = bool(data["enabled"])
        self.armed = bool(data["armed"])
        if self.armed:
            self.speed_bound = float(data["speed_bound"])
            self.energy_bound = float(data["energy_bound"])
            for name in self._SCALES:
                value = np.asarray(data[name[1:]], dtype=np.float64)
                setattr(self, name, value.copy() if name == "_body_reach" else float(value))

    STATE_UNITS = {
        "speed_factor": "1",
        "energy_factor": "1",
        "max_overlap_ratio": "1",
        "height": "m",
        "speed_floor": "m/s",
        "enabled": "1",
        "armed": "1",
        "speed_bound": "m/s",
        "energy_bound": "J",
        "g": "m/s^2",
        "mass_total": "kg",
        "v0": "m/s",
        "v_elastic": "m/s",
        "energy0": "J",
        "v_body": "m/s",
        "body_reach": "m",
    }
    """The unit of each entry of state_dict() (flags: "1")."""

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}."""
        return dict(self.STATE_UNITS)

    # -- the last good state -------------------------------------------------------
    def snapshot(self, sim) -> None:
        """Copy the current state into the last-good buffer (device to device)."""
        state = sim.state
        if self._good is None:
            self._good = SoilState.for_model(sim.model, state.capacity, state.rigid_capacity)
        self._good.assign(state)  # arrays (and its own layout) follow the state's shapes
        self._good_step = sim.steps

    def bytes_per_grain(self) -> float:
        """Device memory of the last good state per grain [B] (0 before the first snapshot)."""
        if self._good is None:
            return 0.0
        return self._good.bytes_per_grain() + self._good.layout.bytes_per_grain()

    def last_good(self) -> dict:
        assert self._good is not None, "no good state was kept yet"
        data = self._good.to_numpy()
        data["step"] = np.int64(self._good_step)
        return data

    # -- checks --------------------------------------------------------------------
    def check_speed(self, sim, speed: float) -> None:
        """Cheap per-step check of the largest speed [m/s] an integrator already reduced."""
        if not self.armed:
            self.arm(sim)
        if not math.isfinite(speed) or (self.enabled and speed > self.speed_bound):
            self.check(sim)  # locates the particle (and raises); passes only if the bound moved

    def check(self, sim) -> None:
        """Full check of sim.state; raises SimulationDiverged, or snapshots the state as good."""
        if not self.armed:
            self.arm(sim)
            return
        model = sim.model
        prec = model.precision
        kernels = check_kernels(prec.hi, prec.mid, prec.lo, sim.model.slot_major)
        n = model.particle_count
        state = sim.state
        layout = state.layout
        speed = wp.zeros(n, dtype=prec.hi, device=model.device)
        overlap = wp.zeros(n, dtype=prec.hi, device=model.device)
        summary = wp.zeros(CHECK_COLUMNS, dtype=prec.hi, device=model.device)
        row = sim.contacts.current_list(state)
        wp.launch(
            kernels.divergence_metrics,
            dim=n,
            inputs=[
                state.position,
                state.velocity,
                state.angular_velocity,
                layout.radius,
                layout.inv_mass,
                layout.neighbours,
                layout.neighbour_count,
                row,
                model.boundary_kind,
                model.boundary_geometry,
                state.boundary_displacement,
                layout.order,
                max(model.world_size, 1),
                model.walls_per_world,
            ],
            outputs=[speed, overlap, summary],
            device=model.device,
        )
        values = summary.numpy().astype(np.float64)
        self._update_bounds(sim)

        def worst_grain(per_slot: wp.array, pick) -> int:  # the model index of the worst grain
            return int(layout.order.numpy()[pick(per_slot.numpy())])

        if values[CHECK_NONFINITE] > 0:
            self.fail(
                sim, "non-finite particle state (NaN or inf)", worst_grain(speed, lambda v: np.argmax(~np.isfinite(v)))
            )
        if not self.enabled:
            self.snapshot(sim)
            return
        if values[CHECK_SPEED] > self.speed_bound:
            self.fail(
                sim,
                f"speed {values[CHECK_SPEED]:.4g} m/s exceeds the bound {self.speed_bound:.4g} m/s",
                worst_grain(speed, np.argmax),
            )
        if values[CHECK_OVERLAP] > self.max_overlap_ratio:
            self.fail(
                sim,
                f"overlap {values[CHECK_OVERLAP]:.4g} x radius exceeds {self.max_overlap_ratio:g} x radius",
                worst_grain(overlap, np.argmax),
            )
        kinetic = sim.kinetic_energy()
        if not kinetic <= self.energy_bound:
            self.fail(
                sim,
                f"kinetic energy {kinetic:.4g} J exceeds the bound {self.energy_bound:.4g} J "
                "(gravity, initial motion, overlaps and wheels cannot supply it)",
                worst_grain(speed, np.argmax),
            )
        self.snapshot(sim)

    def fail(self, sim, reason: str, particle: int | None, state: SoilState | None = None) -> None:
        """Raise SimulationDiverged for `state` (default sim.state) with the last good state attached."""
        state = state or sim.state
        position = None
        where = ""
        if particle is not None and 0 <= particle < sim.model.particle_count:
            assert state.layout is not None  # every state of a Simulation has its layout
            position = state.position.numpy()[int(state.layout.slot.numpy()[particle])].astype(np.float64)
            builder_index = (
                int(sim.model.particle_order[particle]) if sim.model.particle_order is not None else particle
            )
            where = (
                f" at particle {particle} (builder index {builder_index}), position "
                f"({position[0]:.6g}, {position[1]:.6g}, {position[2]:.6g}) m"
            )
        good = self.last_good() if self._good is not None else None
        checkpoint = None
        saved = ""
        if good is not None:
            saved = f"; the last good state (t = {float(good['time']):.9g} s, step {int(good['step'])}) is kept"
            if getattr(sim, "checkpoint_path", None):
                checkpoint = write_checkpoint(sim.checkpoint_path, good, STATE_UNITS)
                saved += f" and {checkpoint}"
        message = f"simulation diverged at t = {state.time:.9g} s (step {sim.steps}): {reason}{where}{saved}"
        raise SimulationDiverged(
            message,
            good,
            time=state.time,
            step=sim.steps,
            particle=particle,
            position=position,
            reason=reason,
            checkpoint=checkpoint,
        )
