"""Soil beds: fill a box with grains, settle them, measure, save and reload (HDF5)."""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass

import numpy as np

from .builder import SoilBuilder
from .errors import DamagedFileError
from .files import atomic_path
from .materials import Material

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

    def __post_init__(self):
        for name in ("length", "width", "depth", "radius_mean"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"bed.{name} must be > 0 [m], got {value!r}")
        if not 0 <= self.radius_spread < 1:
            raise ValueError(f"bed.radius_spread must be in [0, 1), got {self.radius_spread!r}")
        if min(self.length, self.width, self.depth) < 4 * self.radius_mean * (1 + self.radius_spread):
            raise ValueError(
                "bed.length, width and depth must each hold at least two grains "
                f"(> {4 * self.radius_mean * (1 + self.radius_spread):.4g} m)"
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
    r_max = spec.radius_mean * (1 + spec.radius_spread)
    a = 2.0 * r_max * 1.02  # centre-to-centre distance of lattice neighbours
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


def settle(
    sim, dt: float, ke_ratio: float = 1e-4, max_time: float = 20.0, check_interval: float | None = None, progress=None
) -> dict:
    """Run until the kinetic energy falls below the gravity-scaled threshold: fixed steps dt [s],
    or, when the simulation has a step control (Simulation.enable_step_control), PID substeps
    (Simulation.run).

    Returns {'time': settling time [s], 'kinetic_energy': [J], 'threshold': [J], 'settled': bool}.
    """
    threshold = kinetic_energy_threshold(sim, ke_ratio)
    interval = check_interval or max(50 * dt, 0.01 * max_time)
    start = sim.time
    energy = sim.kinetic_energy()
    while sim.time - start < max_time:
        sim.run(interval, dt)  # with a step control: PID substeps in macro steps of 200 dt
        sim.check_finite()
        energy = sim.kinetic_energy()
        if progress is not None:
            progress(sim.time - start, energy, threshold)
        if energy < threshold and sim.time - start > 10 * interval:
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


def save_bed(path, sim, spec: BedSpec | None = None, metrics: dict | None = None, key: str = "") -> None:
    """Write the soil (grains, materials, walls, full state incl. contact history) to HDF5.

    Walls are saved where they are now (moved walls become the bed's initial geometry, with
    zero displacement); their velocities and the grains' forces on them are kept. The
    control (prescribed wall motion, loads) is not part of a bed: set it again after loading.
    `key` (optional) ties the file to what it was made for (a scene's bed key: read_bed_header['key']).
    Written to a temporary file first and renamed, so an existing file is never left half-written.
    """
    import h5py

    model = sim.model
    if model.body_count:
        raise ValueError("save_bed saves soil only: save the bed before adding wheels")
    with atomic_path(path, ".h5.tmp") as temporary:
        with h5py.File(temporary, "w") as f:
            f.attrs["format"] = BED_FORMAT
            f.attrs["bed_key"] = key
            f.attrs["precision"] = model.precision.name
            f.attrs["gravity"] = model.gravity
            f.attrs["materials"] = json.dumps([asdict(m) for m in model.materials.materials])
            f.attrs["pair_overrides"] = json.dumps([[list(k), v] for k, v in model.materials.overrides.items()])
            if spec is not None:
                f.attrs["spec"] = json.dumps(
                    {k: v for k, v in asdict(spec).items() if k not in ("material", "wall_material")}
                )
            for key, value in (metrics or {}).items():
                f.attrs[f"metric_{key}"] = value
            particles = f.create_group("particles")
            particles["radius"] = model.radius.numpy()
            particles["material"] = model.material.numpy()
            particles["mass"] = model.mass.numpy()
            particles["inv_mass"] = model.inv_mass.numpy()
            particles["inv_inertia"] = model.inv_inertia.numpy()
            boundaries = f.create_group("boundaries")
            boundaries["kind"] = model.boundary_kind.numpy()
            boundaries["geometry"] = sim.boundary_geometry().astype(model.boundary_geometry.numpy().dtype)
            boundaries["material"] = model.boundary_material.numpy()
            boundaries["report"] = model.boundary_reports
            state = f.create_group("state")
            for name, value in sim.state.to_numpy().items():
                if name == "boundary_displacement":
                    value = np.zeros_like(value)  # the displacement is in the saved geometry
                if not name.startswith("body_"):
                    state[name] = value


def _open_bed(path):
    """The bed file opened for reading; DamagedFileError (a ValueError) naming the path when it is not a
    readable bed: truncated, another format, or another HDF5 file (a results.h5)."""
    import h5py

    from .errors import DamagedFileError
    from .files import check_hdf5

    path = os.fspath(path)
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
    try:
        with _open_bed(path) as f:
            return _header(f)
    except (KeyError, TypeError, ValueError, OSError) as error:
        if isinstance(error, (FileNotFoundError, DamagedFileError)):
            raise
        raise DamagedFileError(f"{os.fspath(path)!r}: the bed file is damaged ({error})") from None


def _header(f) -> dict:
    return {
        "spec": json.loads(f.attrs["spec"]) if "spec" in f.attrs else None,
        "gravity": np.asarray(f.attrs["gravity"], dtype=np.float64),
        "materials": [Material(**values) for values in json.loads(f.attrs["materials"])],
        "metrics": {k[len("metric_") :]: f.attrs[k] for k in f.attrs if k.startswith("metric_")},
        "particle_count": int(f["particles/radius"].shape[0]),
        "key": str(f.attrs.get("bed_key", "")),
    }


def load_bed(path) -> tuple[SoilBuilder, dict]:
    """Read a saved bed: a SoilBuilder with the grains and walls (add wheels to it, then
    finalize) and the saved state for `restore_state`."""
    path = os.fspath(path)
    with _open_bed(path) as f:
        builder = SoilBuilder(gravity=np.asarray(f.attrs["gravity"]))
        for values in json.loads(f.attrs["materials"]):
            builder.add_material(Material(**values))
        for (i, j), values in json.loads(f.attrs["pair_overrides"]):
            builder.materials.set_pair(i, j, **values)
        radius = f["particles/radius"][()]
        material = f["particles/material"][()]
        inv_mass = f["particles/inv_mass"][()]
        inv_inertia = f["particles/inv_inertia"][()]
        saved = {name: f["state"][name][()] for name in f["state"]}
        saved["model"] = {name: f["particles"][name][()] for name in ("mass", "inv_mass", "inv_inertia")}
        kinds = f["boundaries/kind"][()]
        reports = f["boundaries/report"][()] if "report" in f["boundaries"] else np.ones(len(kinds), dtype=bool)
        for kind, geometry, wall, report in zip(
            kinds, f["boundaries/geometry"][()], f["boundaries/material"][()], reports
        ):
            builder._add_boundary(int(kind), geometry, int(wall), bool(report))
        saved["precision"] = f.attrs["precision"]
        saved["metrics"] = {k[len("metric_") :]: f.attrs[k] for k in f.attrs if k.startswith("metric_")}
    builder.add_particles(
        saved["position"],
        radius,
        0,
        velocities=saved["velocity"],
        angular_velocities=saved["angular_velocity"],
        fixed=inv_mass == 0,
        lock_rotation=inv_inertia == 0,
    )
    builder._material[-1] = material.astype(np.int32)
    return builder, saved


def restore_state(model, state, saved: dict) -> None:
    """Put a saved bed state (from load_bed) into a freshly finalized state, contact history included.

    Handles particle permutations (order_seed), beds written before the neighbour list
    existed (their keyed history is converted), and wheels and boundaries added after the
    bed was saved (they start at rest, with no force).
    The clock restarts at t = 0: a run on a bed starts when the bed is ready.
    """
    from .state import current_format, per_grain

    n = model.particle_count
    order = model.particle_order  # builder index (= the saved model index) of each model particle
    inverse = np.empty_like(order)
    inverse[order] = np.arange(n)
    data = current_format({k: v for k, v in saved.items() if k not in ("precision", "metrics", "model")}, n)
    # masses as saved (recomputing them from rounded radii could change the last bit)
    for name, values in saved.get("model", {}).items():
        array = getattr(model, name)
        array.assign(values[order].astype(array.numpy().dtype))
    state.layout.gather_constants(model)
    for name in list(data):
        if name != "time" and per_grain(name):
            data[name] = np.asarray(data[name])[order]
    neighbours = data["neighbours"]
    data["neighbours"] = np.where(neighbours >= 0, inverse[np.maximum(neighbours, 0)], -1).astype(np.int32)
    current = state.to_numpy()
    for name, values in current.items():
        if name.startswith("body_") or name not in data:  # fields added after the bed was written
            data[name] = values
        elif name.startswith("boundary_") and len(data[name]) < len(values):
            padded = values.copy()  # boundaries added after loading the bed: at rest
            padded[: len(data[name])] = data[name]
            data[name] = padded
    data["time"] = 0.0
    state.load_numpy(data)


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
    dt = dt or 0.2 * rayleigh_time_step(spec.material, spec.radius_mean * (1 - spec.radius_spread))
    report = settle(sim, dt, ke_ratio=ke_ratio, max_time=max_time, progress=progress)
    metrics = bed_metrics(sim, spec)
    return sim, report, metrics
