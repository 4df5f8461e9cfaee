"""Soil beds: fill a box with grains, settle them, measure, keep them in memory (SavedBed), save and
read them back (HDF5, value for value), and open one as a ready simulation with wheels (open_bed)."""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .builder import SoilBuilder
from .errors import DamagedFileError, SoilInputError
from .files import atomic_path
from .materials import MATERIAL_UNITS, Material
from .state import STATE_UNITS

if TYPE_CHECKING:
    from .simulation import Simulation

# Phobos-like regolith for DEM (coarse-grained): the sources are listed in README.md.
PHOBOS_REGOLITH = Material(
    youngs_modulus=2.0e5,  # macroscopic stiffness adapted to milli-g (paper eq. 10, see soil.advisor)
    poisson_ratio=0.15,  # Phobos regolith estimate (paper section 1.2)
    density=2600.0,  # silicate grain density
    restitution=0.3,
    stick_angle=math.radians(25.0),
    slip_angle=math.radians(20.0),  # bulk friction angle ~20 deg (paper section 1.2)
    stick_speed=1.0e-4,
    rolling_friction=0.1,  # rolling resistance mimics non-spherical grains
    cohesion=0.0,  # 0 .. 1000 Pa is possible on Phobos; off by default
)


def radius_range(radius_mean: float, radius_spread: float) -> tuple[float, float]:
    """Smallest and largest grain radius [m] of radii uniform in radius_mean (1 -+ radius_spread)."""
    return radius_mean * (1 - radius_spread), radius_mean * (1 + radius_spread)


@dataclass(frozen=True)
class BedSpec:
    """A box of grains: size, grain size distribution, materials."""

    length: float = 0.25
    """Bed length along X (travel direction) [m]."""
    width: float = 0.08
    """Bed width along Y [m]."""
    depth: float = 0.04
    """Height of the inserted grains before settling [m]."""
    radius_mean: float = 2.5e-3
    """Mean grain radius [m]."""
    radius_spread: float = 0.2
    """Relative half-width of the uniform radius distribution [-] (0.2: radii in mean * [0.8, 1.2])."""
    material: Material = PHOBOS_REGOLITH
    """Grain material."""
    wall_material: Material | None = None
    """Container material (None: the grain material)."""
    seed: int = 1
    """Random seed of the insertion [-]."""

    @property
    def radius_min(self) -> float:
        """Smallest grain radius [m]: radius_mean (1 - radius_spread)."""
        return radius_range(self.radius_mean, self.radius_spread)[0]

    @property
    def radius_max(self) -> float:
        """Largest grain radius [m]: radius_mean (1 + radius_spread)."""
        return radius_range(self.radius_mean, self.radius_spread)[1]

    def __post_init__(self):
        for name in ("length", "width", "depth", "radius_mean"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise SoilInputError(f"bed.{name} must be > 0 [m], got {value!r}")
        if not 0 <= self.radius_spread < 1:
            raise SoilInputError(f"bed.radius_spread must be in [0, 1), got {self.radius_spread!r}")
        if min(self.length, self.width, self.depth) < 4 * self.radius_max:
            raise SoilInputError(
                f"bed.length, width and depth must each hold at least two grains (> {4 * self.radius_max:.4g} m)"
            )


def insert_grains(spec: BedSpec) -> tuple[np.ndarray, np.ndarray]:
    """Random non-overlapping insertion on a jittered hexagonal close-packed lattice filling the bed box.

    The lattice spacing fits the largest grain (2 r_max x 1.02), so no two grains touch; each
    grain is then moved at random within the room its own radius leaves it. HCP starts the
    bed at about 40 % packing (a cubic lattice would give 29 %), so less fill falls less far.
    Returns positions [m] shape (n, 3) (bed floor at z = 0, corner at x = y = 0) and radii [m] shape (n,).
    """
    rng = np.random.default_rng(spec.seed)
    a, row, layer, counts = _lattice(spec)
    i, j, k = (g.reshape(-1) for g in np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"))
    lattice = np.column_stack([(i + 0.5 * (j % 2) + 0.5 * (k % 2)) * a, (j + (k % 2) / 3.0) * row, k * layer])
    radii = spec.radius_mean * (1 + spec.radius_spread * rng.uniform(-1, 1, len(lattice)))
    slack = 0.5 * a - radii  # each grain may move this far without touching a neighbour
    direction = rng.normal(size=(len(lattice), 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    positions = 0.5 * a + lattice + direction * (slack * rng.uniform(0, 1, len(lattice)))[:, None]
    return positions, radii


def _lattice(spec: BedSpec) -> tuple[float, float, float, list[int]]:
    """The insertion lattice: neighbour spacing a, row and layer spacing [m], sites along x, y, z."""
    a = 2.0 * spec.radius_max * 1.02  # centre-to-centre distance of lattice neighbours
    row, layer = a * math.sqrt(3.0) / 2.0, a * math.sqrt(2.0 / 3.0)
    # a lattice site lies 0.5 a from the walls or more: a grain jittered by its slack still clears them
    counts = [
        int((spec.length - 2.0 * a) // a) + 1,
        int((spec.width - a - row / 3.0) // row) + 1,
        int((spec.depth - a) // layer) + 1,
    ]
    return a, row, layer, counts


def grain_count(spec: BedSpec) -> int:
    """How many grains insert_grains puts into the bed, computed without allocating them."""
    return math.prod(_lattice(spec)[3])


def build_bed(spec: BedSpec, gravity="phobos", wall_height: float | None = None) -> SoilBuilder:
    """A SoilBuilder holding the bed's grains in an open-top container (floor at z = 0)."""
    builder = SoilBuilder(gravity=gravity)
    grain = builder.add_material(spec.material)
    wall = builder.add_material(spec.wall_material) if spec.wall_material else grain
    height = wall_height if wall_height is not None else 4 * spec.depth
    builder.add_container((0.0, 0.0, 0.0), (spec.length, spec.width, height), wall)
    positions, radii = insert_grains(spec)
    builder.add_particles(positions, radii, grain)
    return builder


def rayleigh_time_step(material: Material, radius: float) -> float:
    """Rayleigh time step of `material` grains of `radius` [m] (soil.advisor.rayleigh_time_step) [s]."""
    from .advisor import rayleigh_time_step as rayleigh

    return rayleigh(material.youngs_modulus, material.poisson_ratio, material.density, radius)


def kinetic_energy_threshold(sim, ratio: float = 1e-4) -> float:
    """Settled when the kinetic energy is below ratio * N * m_mean * |g| * r_mean [J]:
    a threshold that scales with gravity, so the same ratio means 'still' on Earth and Phobos."""
    g = float(np.linalg.norm(sim.model.gravity))
    mass = sim.model.mass_numpy()
    radius = sim.model.radius_numpy()
    return ratio * len(mass) * float(mass.mean()) * g * float(radius.mean())


def still_time(sim, ratio: float) -> float:
    """How long grains released from rest stay under the settling threshold in free fall [s]: a grain's
    kinetic energy m g^2 t^2 / 2 reaches ratio m g r at t = sqrt(2 ratio r / g) (0 at g = 0). Before it a
    falling fill reads as settled: at 1e-3 m/s^2 a bed was 'settled' at 0.11 s, its grains not yet moved."""
    g = float(np.linalg.norm(sim.model.gravity))
    return math.sqrt(2.0 * ratio * float(sim.model.radius_numpy().mean()) / g) if g > 0 else 0.0


def settle(
    sim, dt: float, ke_ratio: float = 1e-4, max_time: float = 20.0, check_interval: float | None = None, progress=None
) -> dict:
    """Run until the kinetic energy falls below the gravity-scaled threshold: fixed steps dt [s],
    or, when the simulation has a step control (Simulation.enable_step_control), PID substeps
    (Simulation.run). Judged only after 10 check intervals and 10 x `still_time` (a fill still falling has
    then 100 x the threshold's energy), so a milli-g fill is not called settled before it has fallen.

    Returns {'time': settling time [s], 'kinetic_energy': [J], 'threshold': [J], 'settled': bool}.
    """
    threshold = kinetic_energy_threshold(sim, ke_ratio)
    interval = check_interval or max(50 * dt, 0.01 * max_time)
    earliest = max(10 * interval, 10.0 * still_time(sim, ke_ratio))
    start = sim.time
    energy = sim.kinetic_energy()
    while sim.time - start < max_time:
        sim.run(interval, dt)  # with a step control: PID substeps in macro steps of 200 dt
        sim.check_finite()
        energy = sim.kinetic_energy()
        if progress is not None:
            progress(sim.time - start, energy, threshold)
        if energy < threshold and sim.time - start > earliest:
            return {"time": sim.time - start, "kinetic_energy": energy, "threshold": threshold, "settled": True}
    return {"time": sim.time - start, "kinetic_energy": energy, "threshold": threshold, "settled": False}


def bed_metrics(sim, spec: BedSpec, margin: float | None = None) -> dict:
    """Bed height and packing fraction of a settled bed.

    height [m]: mean top (z + r) of the highest grain in each column of a 2r_mean grid
    over the bed, away from the walls; packing fraction [-]: grain volume below
    height - 2 r_mean in that central region over the region's volume.
    """
    x = sim.positions()
    r = sim.model.radius_numpy()
    margin = 3 * spec.radius_mean if margin is None else margin
    inside = (
        (x[:, 0] > margin) & (x[:, 0] < spec.length - margin) & (x[:, 1] > margin) & (x[:, 1] < spec.width - margin)
    )
    cell = 2 * spec.radius_mean
    ij = np.floor(x[inside, :2] / cell).astype(int)
    tops = x[inside, 2] + r[inside]
    keys = ij[:, 0] * 100000 + ij[:, 1]
    order = np.lexsort((tops, keys))
    last = np.r_[keys[order][1:] != keys[order][:-1], True]
    height = float(np.mean(tops[order][last]))
    cut = height - 2 * spec.radius_mean
    below = inside & (x[:, 2] < cut)
    volume = (spec.length - 2 * margin) * (spec.width - 2 * margin) * cut
    packing = float(np.sum(4 / 3 * math.pi * r[below] ** 3) / volume) if volume > 0 else float("nan")
    return {"height": height, "packing_fraction": packing, "particle_count": int(len(r))}


# -- save / load ----------------------------------------------------------------
BED_FORMAT = "regolith-cosim bed 1"
PARTICLE_UNITS = {
    "radius": ("m", "grain radius"),
    "material": ("1", "material index of the grain (the file's `materials` table)"),
    "mass": ("kg", "grain mass"),
    "inv_mass": ("1/kg", "inverse mass; 0: a fixed grain"),
    "inv_inertia": ("1/(kg m^2)", "inverse moment of inertia; 0: a fixed or rotation-locked grain"),
}
"""A bed file's particles/ datasets (bed order): (units, description)."""
BOUNDARY_UNITS = {
    "kind": ("1", "0 plane (point, unit normal), 1 box (lower corner, upper corner)"),
    "geometry": ("m", "each wall's geometry row when saved (plane: point [m], normal [1]; box: corners [m])"),
    "material": ("1", "material index of the wall"),
    "report": ("1", "1: the wall's force is summed; 0: it reads zero"),
}
"""A bed file's boundaries/ datasets: (units, description)."""
METRIC_UNITS = {"height": "m", "packing_fraction": "1", "particle_count": "count"}
"""The units of bed_metrics()'s values (a bed file's metric_* attributes)."""
SPEC_UNITS = {"length": "m", "width": "m", "depth": "m", "radius_mean": "m", "radius_spread": "1", "seed": "1"}
"""The units of a bed file's `spec` (BedSpec's fields but its materials)."""


@dataclass(eq=False)
class SavedBed:
    """A settled bed in memory: what save_bed writes to a file and read_bed reads back, value for
    value and dtype for dtype (the file is this, cached between processes).

    Open it with open_bed; builder() gives its SoilBuilder for adding walls or materials first.
    Per-grain arrays are in the saved model's order ("bed order"); nothing here is changed by
    opening the bed, so one SavedBed opens any number of simulations.
    """

    gravity: np.ndarray
    """Gravity the bed settled under [m/s^2], shape (3,), float64."""
    materials: list[Material]
    """Material table by index (the grains' first)."""
    pair_overrides: dict
    """Pair property overrides {(i, j): {field: value}} of the material table."""
    precision: str
    """Precision the bed was simulated in (soil.precision name)."""
    radius: np.ndarray
    """Grain radii [m], shape (n,), the saved model's lo dtype."""
    material: np.ndarray
    """Material index per grain [-], shape (n,), int32."""
    mass: np.ndarray
    """Grain masses [kg], shape (n,)."""
    inv_mass: np.ndarray
    """Inverse masses [1/kg], shape (n,); 0: a fixed grain."""
    inv_inertia: np.ndarray
    """Inverse moments of inertia [1/(kg m^2)], shape (n,); 0: a fixed or rotation-locked grain."""
    boundary_kind: np.ndarray
    """Boundary kinds (soil.sdf.BOUNDARY_*) [-], shape (B,), int32."""
    boundary_geometry: np.ndarray
    """Boundary rows where the walls were when saved [m], shape (B, 6) (SoilBuilder.add_boundary)."""
    boundary_material: np.ndarray
    """Material index per boundary [-], shape (B,), int32."""
    boundary_report: np.ndarray
    """Whether the grains' force on each boundary is summed [-], shape (B,), bool."""
    state: dict
    """SoilState.to_numpy() arrays in bed order, body arrays left out, boundary displacements zero
    (the displacement is in boundary_geometry)."""
    spec: dict | None = None
    """The BedSpec fields without its materials, or None."""
    metrics: dict = field(default_factory=dict)
    """bed_metrics() results ('height' [m], 'packing_fraction' [-], ...), or empty."""
    key: str = ""
    """What the bed was made for (a scene's bed key), "" when none."""

    @property
    def particle_count(self) -> int:
        """Number of grains [-]."""
        return len(self.radius)

    @classmethod
    def from_simulation(cls, sim, spec: BedSpec | None = None, metrics: dict | None = None, key: str = "") -> SavedBed:
        """The soil of `sim` as a saved bed (grains, materials, walls, the full state incl. contact
        history), copied: later steps of `sim` do not change it.

        Walls are saved where they are now (moved walls become the bed's initial geometry, with
        zero displacement); their velocities and the grains' forces on them are kept. The
        control (prescribed wall motion, loads) is not part of a bed: set it again after opening.
        SoilInputError when `sim` has wheels: a bed is soil only.
        """
        model = sim.model
        if model.body_count:
            raise SoilInputError("a saved bed is soil only: save the bed before adding wheels")
        state = {}
        for name, value in sim.state.to_numpy().items():
            if name == "boundary_displacement":
                value = np.zeros_like(value)  # the displacement is in the saved geometry
            if not name.startswith("body_"):
                state[name] = value
        return cls(
            gravity=np.array(model.gravity, dtype=np.float64),
            materials=list(model.materials.materials),
            pair_overrides={tuple(k): dict(v) for k, v in model.materials.overrides.items()},
            precision=model.precision.name,
            radius=model.radius.numpy().copy(),  # on the CPU .numpy() is a view of the device array
            material=model.material.numpy().copy(),
            mass=model.mass.numpy().copy(),
            inv_mass=model.inv_mass.numpy().copy(),
            inv_inertia=model.inv_inertia.numpy().copy(),
            boundary_kind=model.boundary_kind.numpy().copy(),
            boundary_geometry=sim.boundary_geometry().astype(model.boundary_geometry.numpy().dtype),
            boundary_material=model.boundary_material.numpy().copy(),
            boundary_report=np.array(model.boundary_reports, dtype=bool),
            state=state,
            spec=None if spec is None else _spec_fields(spec),
            metrics=dict(metrics or {}),
            key=key,
        )

    def builder(self, gravity=None) -> SoilBuilder:
        """A SoilBuilder holding the bed's materials, walls and grains, whose finalize() starts from
        the saved state (contact history included, the clock at 0; SoilBuilder.start_from).

        Add wheels, walls and materials to it before finalize(); add no grains. gravity: as
        SoilBuilder's (a preset name or [m/s^2] (3,)); None: the gravity the bed settled under.
        """
        builder = SoilBuilder(gravity=self.gravity if gravity is None else gravity)
        for material in self.materials:
            builder.add_material(material)
        for (i, j), values in self.pair_overrides.items():
            builder.materials.set_pair(i, j, **values)
        for kind, geometry, wall, report in zip(
            self.boundary_kind, self.boundary_geometry, self.boundary_material, self.boundary_report
        ):
            builder.add_boundary(int(kind), geometry, int(wall), bool(report))
        builder.add_particles(
            self.state["position"],
            self.radius,
            self.material,
            velocities=self.state["velocity"],
            angular_velocities=self.state["angular_velocity"],
            fixed=self.inv_mass == 0,
            lock_rotation=self.inv_inertia == 0,
        )
        builder.start_from(self.state, {"mass": self.mass, "inv_mass": self.inv_mass, "inv_inertia": self.inv_inertia})
        return builder

    def write(self, path) -> None:
        """Write the bed to an HDF5 bed file (read_bed reads it back unchanged). Written to a
        temporary file first and renamed, so an existing file is never left half-written."""
        import h5py

        with atomic_path(path, ".h5.tmp") as temporary:
            with h5py.File(temporary, "w") as f:
                f.attrs["format"] = BED_FORMAT
                f.attrs["bed_key"] = self.key
                f.attrs["precision"] = self.precision
                f.attrs["gravity"] = self.gravity
                f.attrs["materials"] = json.dumps([asdict(m) for m in self.materials])
                f.attrs["pair_overrides"] = json.dumps([[list(k), v] for k, v in self.pair_overrides.items()])
                if self.spec is not None:
                    f.attrs["spec"] = json.dumps(self.spec)
                for name, value in self.metrics.items():
                    f.attrs[f"metric_{name}"] = value
                f.attrs["units"] = json.dumps(
                    {
                        "gravity": "m/s^2",
                        "materials": MATERIAL_UNITS,  # each entry's fields (angles in radians)
                        "spec": SPEC_UNITS,
                        **{f"metric_{name}": METRIC_UNITS[name] for name in self.metrics if name in METRIC_UNITS},
                    }
                )
                for group, table, prefix in (
                    ("particles", PARTICLE_UNITS, ""),
                    ("boundaries", BOUNDARY_UNITS, "boundary_"),
                ):
                    for name, (units, description) in table.items():
                        f[f"{group}/{name}"] = getattr(self, prefix + name)
                        f[f"{group}/{name}"].attrs.update(units=units, description=description)
                for name, value in self.state.items():  # a unit the table lacks must not lose a settled bed
                    f[f"state/{name}"] = value
                    f[f"state/{name}"].attrs.update(
                        units=STATE_UNITS.get(name, ""), description=f"SoilState.{name} (rows in model order)"
                    )
            with h5py.File(temporary, "a") as f:  # the digest of what a reader reads back
                f.attrs[DIGEST_ATTRIBUTE] = bed_digest(bed_datasets(f), f.attrs)


DIGEST_ATTRIBUTE = "sha256"
"""The bed file's root attribute holding bed_digest() of the rest (a file written before it has none)."""


def bed_datasets(f) -> dict[str, np.ndarray]:
    """Every dataset of an open bed file by its path ('particles/radius', 'state/neighbours', ...), read once."""
    found: dict[str, np.ndarray] = {}
    f.visititems(lambda name, item: found.__setitem__(name, item[()]) if hasattr(item, "dtype") else None)
    return found


def bed_digest(datasets: dict[str, np.ndarray], attrs) -> str:
    """SHA-256 (hex) of a bed file's datasets (bed_datasets: name, dtype, shape, values) and root
    attributes but DIGEST_ATTRIBUTE, in name order: a flipped bit anywhere in what a bed is read from
    changes it."""
    digest = hashlib.sha256()
    for name in sorted(datasets):
        values = np.ascontiguousarray(datasets[name])
        digest.update(f"{name}|{values.dtype.str}|{values.shape}|".encode())
        digest.update(values.reshape(-1).view(np.uint8).data)  # the array's own bytes, not a copy
    for name in sorted(k for k in attrs if k != DIGEST_ATTRIBUTE):
        value = attrs[name]
        digest.update(f"@{name}|".encode())
        digest.update(value.encode() if isinstance(value, str) else np.ascontiguousarray(value).tobytes())
    return digest.hexdigest()


def check_bed_grains(radius: np.ndarray, material: np.ndarray, materials: int, state: dict) -> None:
    """Refuse (ValueError naming the field and what is allowed) grains a bed cannot hold: radii not
    finite and > 0, a material index outside the table, positions not (n, 3) and finite."""
    n = len(radius)
    if radius.ndim != 1 or not np.all(np.isfinite(radius) & (radius > 0)):
        raise ValueError(f"particles/radius must be one finite radius > 0 [m] per grain, shape ({n},)")
    if material.shape != (n,) or material.min(initial=0) < 0 or material.max(initial=0) >= materials:
        raise ValueError(f"particles/material must be one index 0..{materials - 1} of the material table per grain")
    position = np.asarray(state.get("position", np.zeros((n, 3))))
    if position.shape != (n, 3) or not np.all(np.isfinite(position)):
        raise ValueError(f"state/position must be finite grain centres [m], shape ({n}, 3), got shape {position.shape}")


def check_bed_rows(state: dict, particle_count: int, boundary_count: int) -> None:
    """Refuse (ValueError naming the field and what is allowed) a saved state whose neighbour-list or
    contact rows point outside the bed: a kernel would read or write past its arrays."""
    count, neighbours = np.asarray(state["neighbour_count"]), np.asarray(state["neighbours"])
    width = neighbours.shape[1] if neighbours.ndim == 2 else -1
    if count.shape != (particle_count,) or neighbours.shape[0] != particle_count or width < 1:
        raise ValueError(
            f"state/neighbours and state/neighbour_count must have one row per grain ({particle_count}), "
            f"got shapes {neighbours.shape} and {count.shape}"
        )
    if count.min(initial=0) < 0 or count.max(initial=0) > width:
        raise ValueError(
            f"state/neighbour_count must be in 0..{width} (the list's width), got {count.min()}..{count.max()}"
        )
    if neighbours.min(initial=-1) < -1 or neighbours.max(initial=-1) >= particle_count:
        raise ValueError(f"state/neighbours must be grain indices 0..{particle_count - 1} or -1")
    keys, rigid = np.asarray(state["rigid_key"]), np.asarray(state["rigid_count"])
    rigid_width = keys.shape[1] if keys.ndim == 2 else -1
    if rigid.shape != (particle_count,) or keys.shape[0] != particle_count or rigid_width < 1:
        raise ValueError(f"state/rigid_key and state/rigid_count must have one row per grain ({particle_count})")
    if rigid.min(initial=0) < 0 or rigid.max(initial=0) > rigid_width:
        raise ValueError(f"state/rigid_count must be in 0..{rigid_width}, got {rigid.min()}..{rigid.max()}")
    if keys.min(initial=-1) < -1 or keys.max(initial=-1) >= boundary_count:
        raise ValueError(f"state/rigid_key must be wall indices 0..{boundary_count - 1} or -1 (a bed has no wheels)")
    for name, row_width in (("pair_tangential", width), ("pair_rolling", width), ("rigid_tangential", rigid_width)):
        values = np.asarray(state.get(name, np.zeros((particle_count, 0))))
        if values.shape[0] != particle_count or values.shape[1] not in (0, row_width):
            raise ValueError(
                f"state/{name} must have one row per grain of {row_width} entries (or none), got shape {values.shape}"
            )
    touching = np.asarray(state.get("pair_touching", np.zeros((particle_count, (width + 31) // 32))))
    if touching.shape != (particle_count, (width + 31) // 32):
        raise ValueError(
            f"state/pair_touching must have shape ({particle_count}, {(width + 31) // 32}), got {touching.shape}"
        )


def _spec_fields(spec: BedSpec) -> dict:
    """The BedSpec fields a bed file keeps (its materials are the file's material table)."""
    return {k: v for k, v in asdict(spec).items() if k not in ("material", "wall_material")}


def save_bed(path, sim, spec: BedSpec | None = None, metrics: dict | None = None, key: str = "") -> None:
    """Write the soil of `sim` (grains, materials, walls, full state incl. contact history) to an
    HDF5 bed file: SavedBed.from_simulation(sim, spec, metrics, key).write(path).

    `key` (optional) ties the file to what it was made for (a scene's bed key: read_bed_header['key']).
    """
    SavedBed.from_simulation(sim, spec, metrics, key).write(path)


def _open_bed(path):
    """The bed file opened for reading; DamagedFileError (a ValueError) naming the path when it is not a
    readable bed: truncated, another format, or another HDF5 file (a results.h5)."""
    import h5py

    from .files import check_hdf5

    path = os.fspath(path)
    if os.path.isdir(path):  # a run's or a bed's folder: its bed.h5 is meant
        inside = os.path.join(path, "bed.h5")
        hint = f"; its bed is {inside!r}" if os.path.isfile(inside) else ""
        raise IsADirectoryError(f"{path!r} is a folder, not a bed file{hint}")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"bed file not found: {path!r}")
    check_hdf5(path, "bed file")
    try:
        f = h5py.File(path, "r")
    except OSError as error:
        raise DamagedFileError(
            f"{path!r} is not a readable HDF5 bed file (truncated or another format): {error}"
        ) from None
    found = f.attrs.get("format")
    if found != BED_FORMAT:
        f.close()
        raise DamagedFileError(
            f"{path!r} is not a regolith-cosim bed file (format {found!r}, expected {BED_FORMAT!r}; "
            "beds are written by soil.bed.save_bed or a run's bed.h5)"
        )
    return f


def read_bed_header(path) -> dict:
    """What a saved bed was made of, without its state: {'gravity' [m/s^2] (3,), 'materials'
    (list of Material, the grains' first), 'metrics' (dict), 'particle_count', 'spec' (the BedSpec
    fields without materials, or None), 'key' (save_bed's key, "" when none)}."""
    return _reading(path, _header)


def _reading(path, read):
    """read(the open bed file); DamagedFileError naming the path when a part of it is missing or unreadable."""
    try:
        with _open_bed(path) as f:
            return read(f)
    except (KeyError, TypeError, ValueError, OSError) as error:
        if isinstance(error, (FileNotFoundError, IsADirectoryError, DamagedFileError)):
            raise
        raise DamagedFileError(f"{os.fspath(path)!r}: the bed file is damaged ({error})") from None


def _header(f) -> dict:
    return {
        "spec": json.loads(f.attrs["spec"]) if "spec" in f.attrs else None,
        "gravity": np.asarray(f.attrs["gravity"], dtype=np.float64),
        "materials": [Material(**values) for values in json.loads(f.attrs["materials"])],
        "metrics": _metrics(f),
        "particle_count": int(f["particles/radius"].shape[0]),
        "key": str(f.attrs.get("bed_key", "")),
    }


def _metrics(f) -> dict:
    return {k[len("metric_") :]: f.attrs[k] for k in f.attrs if k.startswith("metric_")}


def read_bed(path) -> SavedBed:
    """A bed file (save_bed, a run's bed.h5) in memory; FileNotFoundError, or DamagedFileError
    naming the path when it is not a readable bed."""
    return _reading(path, _read)


def _read(f) -> SavedBed:
    data = bed_datasets(f)  # each read once: checked against the digest, then kept
    saved_digest = f.attrs.get(DIGEST_ATTRIBUTE)
    if isinstance(saved_digest, bytes):
        saved_digest = saved_digest.decode("ascii", "replace")
    if saved_digest is not None and saved_digest != bed_digest(data, f.attrs):
        raise DamagedFileError(
            f"{f.filename!r}: the bed file is damaged (its content does not match its SHA-256 digest: "
            "a bit changed on disk or in a copy); settle the bed again or use an intact copy"
        )
    header = _header(f)
    kinds = data["boundaries/kind"]
    state = {name[len("state/") :]: values for name, values in data.items() if name.startswith("state/")}
    check_bed_grains(data["particles/radius"], data["particles/material"], len(header["materials"]), state)
    if "neighbours" in state:  # (a bed of the keyed-history format is converted as it opens)
        missing = [name for name in STATE_UNITS if name not in state and not name.startswith(("body_", "boundary_"))]
        missing = [name for name in missing if name != "step"]
        if missing:
            raise ValueError(
                f"state/{missing[0]} is missing{f' (and {len(missing) - 1} more)' if len(missing) > 1 else ''}"
            )
        check_bed_rows(state, header["particle_count"], len(kinds))
    return SavedBed(
        gravity=header["gravity"],
        materials=header["materials"],
        pair_overrides={(i, j): values for (i, j), values in json.loads(f.attrs["pair_overrides"])},
        precision=str(f.attrs["precision"]),
        radius=data["particles/radius"],
        material=data["particles/material"],
        mass=data["particles/mass"],
        inv_mass=data["particles/inv_mass"],
        inv_inertia=data["particles/inv_inertia"],
        boundary_kind=kinds,
        boundary_geometry=data["boundaries/geometry"],
        boundary_material=data["boundaries/material"],
        boundary_report=data.get("boundaries/report", np.ones(len(kinds), dtype=bool)),
        state=state,
        spec=header["spec"],
        metrics=header["metrics"],
        key=header["key"],
    )


def wheel_pairs(wheels) -> list:
    """`wheels` as a list of (shape, material) pairs (GrouserWheel or MeshWheel; a Material or a material
    index), checked: SoilInputError naming what is not one (one shape, one pair unlisted, shapes alone)."""
    from .geometry import GrouserWheel, MeshWheel

    shapes = (GrouserWheel, MeshWheel)
    pairs: list = [wheels] if isinstance(wheels, shapes) else list(wheels)
    if len(pairs) == 2 and isinstance(pairs[0], shapes) and not isinstance(pairs[1], shapes):  # one pair, unlisted
        raise SoilInputError("wheels must be a list of (shape, material) pairs: [(GrouserWheel(...), Material(...))]")
    for index, pair in enumerate(pairs):
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2 and isinstance(pair[0], shapes)):
            raise SoilInputError(
                f"wheels[{index}] must be a (shape, material) pair: (GrouserWheel or MeshWheel, Material or a "
                f"material index), got {type(pair).__name__}"
            )
    return pairs


def open_bed(
    bed,
    wheels=(),
    *,
    device: str | None = None,
    precision="double",
    law=None,
    order_seed: int | None = None,
    integrator=None,
    gravity=None,
    storage: str = "grain",
) -> Simulation:
    """A ready soil.Simulation on a settled bed: its grains in their saved state (contact history
    included, the clock at 0), plus one body per wheel.

    bed: a SavedBed (in memory) or the path of a bed file (read_bed). wheels: (shape, material)
    pairs in body order (GrouserWheel / MeshWheel; a Material or a material index). device,
    precision, law, order_seed, storage: as SoilBuilder.finalize; integrator: as Simulation (None: its
    default); gravity: the run's gravity (a preset name or [m/s^2] (3,); None: the bed's own).
    To add walls or materials first, use SavedBed.builder() and finalize it.
    """
    from .simulation import Simulation  # the simulation's kernels load on first use, not with soil.bed

    pairs = wheel_pairs(wheels)
    saved = bed if isinstance(bed, SavedBed) else read_bed(bed)
    builder = saved.builder(gravity)
    for shape, material in pairs:
        builder.add_wheel(shape, material)
    model, state, control = builder.finalize(
        device=device, precision=precision, law=law, order_seed=order_seed, storage=storage
    )
    return Simulation(model, state, control, integrator=integrator)


def make_settled_bed(
    spec: BedSpec,
    gravity,
    device=None,
    precision="double",
    dt=None,
    ke_ratio=1e-4,
    max_time=20.0,
    progress=None,
    step_control=None,
):
    """Fill, settle and measure a bed; returns (simulation, settle report, metrics).

    step_control: a soil.StepController to settle with PID substeps (jolt-Beeman), None: fixed steps dt."""
    from .simulation import Simulation

    builder = build_bed(spec, gravity)
    model, state, control = builder.finalize(device=device, precision=precision)
    sim = Simulation(model, state, control)
    if step_control is not None:
        sim.enable_step_control(step_control)
    dt = dt or 0.2 * rayleigh_time_step(spec.material, spec.radius_min)
    report = settle(sim, dt, ke_ratio=ke_ratio, max_time=max_time, progress=progress)
    metrics = bed_metrics(sim, spec)
    return sim, report, metrics
