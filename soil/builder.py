"""Build a soil scene (particles, materials, boundaries), then finalize it on a device."""

from __future__ import annotations

import math
import reprlib
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from .contact import ContactLaw
from .control import SoilControl
from .devices import warp_device
from .errors import OverlapWarning, SoilInputError, is_real
from .geometry import GrouserWheel, MeshWheel
from .grains import rows_in_partner_order
from .gravity import gravity_vector
from .materials import Material, MaterialTable
from .model import SoilModel
from .precision import get_precision
from .sdf import BODY_MESH, BODY_WHEEL, BOUNDARY_BOX, BOUNDARY_PLANE
from .state import SoilState, current_format, per_grain

DEEP_OVERLAP = 0.1
"""Overlap, as a fraction of the smaller radius, above which finalize() warns that grains
were created inside each other (or inside a wall) (OverlapWarning)."""


STORAGE_ORDERS = ("grain", "slot")
"""Orders of the neighbour lists and contact history in memory (SoilBuilder.finalize's storage)."""


def grain_range_problem(radius: float, density: float, precision) -> str | None:
    """Why grains of `radius` [m] and `density` [kg/m^3] cannot be stepped in `precision` (None: they can):
    the smallest grain's inverse mass or inverse inertia beyond the float type its constants are stored in
    (nanometre grains in single or mixed precision: inf, then a NaN state in the first steps)."""
    prec = get_precision(precision)
    mass = density * (4.0 / 3.0) * math.pi * radius**3
    if not (mass > 0 and math.isfinite(mass)):
        return None  # no grains (inf radius) or a density refused elsewhere
    limit = float(np.finfo(prec.np_lo).max)
    for name, value in (("inverse mass", 1.0 / mass), ("inverse inertia", 1.0 / (0.4 * mass * radius**2))):
        if not value < limit:
            return (
                f"grains of radius {radius:.3g} m have an {name} of {value:.3g} (SI units), beyond {prec.name} "
                f"precision's range ({limit:.3g}): larger grains (bed.radius_mean), or precision 'double'"
            )
    return None


def _brief(value) -> str:
    """A short repr of an argument for a message (a long array cut to its ends)."""
    return reprlib.repr(value.tolist() if isinstance(value, np.ndarray) else value)


def _is_complex(value) -> bool:
    """Whether `value` holds complex numbers (False for a ragged list: _real_array names that)."""
    try:
        return bool(np.iscomplexobj(value))
    except ValueError:
        return False


def _real_array(value, name: str, allowed: str) -> np.ndarray:
    """`value` as a float64 array, or a SoilInputError naming `name` and what is `allowed`: numpy would read
    a text of digits as a number and a bool as 0 or 1, and says only "inhomogeneous shape" of a ragged list."""
    try:
        kind = np.asarray(value).dtype.kind
        if kind in "iufO":  # O: Python objects that may convert (large integers, Fractions)
            return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        pass
    raise SoilInputError(f"{name} must be real numbers, {allowed}, got {_brief(value)}")


class SoilBuilder:
    """Collects particles, materials and boundaries; `finalize()` makes model, state, control (at
    rest, or in a saved state given with `start_from`, e.g. a settled bed: soil.bed.SavedBed.builder)."""

    def __init__(self, gravity="earth") -> None:
        self.gravity = gravity_vector(gravity)
        """The scene's gravity vector [m/s^2], shape (3,)."""
        self.materials = MaterialTable()
        self._positions: list[np.ndarray] = []
        self._radii: list[np.ndarray] = []
        self._material: list[np.ndarray] = []
        self._velocity: list[np.ndarray] = []
        self._spin: list[np.ndarray] = []
        self._fixed: list[np.ndarray] = []
        self._lock_rotation: list[np.ndarray] = []
        self._boundaries: list[tuple[int, list[float], int, bool]] = []  # kind, geometry row, material, report
        self._bodies: list[tuple[GrouserWheel | MeshWheel, int]] = []
        self._start: _SavedStart | None = None

    # -- materials ---------------------------------------------------------------
    def add_material(self, material: Material) -> int:
        """Register a material; returns its index."""
        return self.materials.add(material)

    def _material_indices(self, material, n: int) -> np.ndarray:
        """Material index of each of n new grains, int32 shape (n,): one material (a Material or an
        index) for all, or an index per grain."""
        try:
            indices = np.asarray(material)
        except ValueError:  # a ragged list: numpy says only "inhomogeneous shape"
            indices = np.asarray([None])
        if indices.ndim == 0:
            return np.full(n, self._material_index(material), dtype=np.int32)
        if indices.shape != (n,) or not np.issubdtype(indices.dtype, np.integer):
            raise SoilInputError(
                f"material must be one material, one index or an index per grain, shape ({n},), "
                f"got shape {indices.shape} ({indices.dtype})"
            )
        count = len(self.materials.materials)
        if n and not (indices.min() >= 0 and indices.max() < count):
            raise SoilInputError(f"material indices must be in [0, {count}), got {indices.min()} .. {indices.max()}")
        return indices.astype(np.int32)

    def _material_index(self, material) -> int:
        if isinstance(material, Material):
            return self.add_material(material)
        if isinstance(material, np.ndarray) and material.ndim == 0:
            material = material[()]
        # checked before the default material is added: int() would cut 0.7 to index 0
        count = max(1, len(self.materials.materials))  # index 0 of an empty table: the default Material()
        if not (is_real(material) and math.isfinite(material) and float(material).is_integer()):
            raise SoilInputError(
                f"material must be a soil.Material or a material index (an integer in [0, {count})), got {material!r}"
            )
        index = int(material)
        if not 0 <= index < count:
            raise SoilInputError(f"material index must be in [0, {count}), got {material!r}")
        if not self.materials.materials:
            self.add_material(Material())
        return index

    # -- particles ---------------------------------------------------------------
    @property
    def particle_count(self) -> int:
        return int(sum(len(r) for r in self._radii))

    def add_particles(
        self, positions, radii, material=0, velocities=None, angular_velocities=None, fixed=False, lock_rotation=False
    ) -> np.ndarray:
        """Add spheres. positions [m] shape (n, 3); radii [m] shape (n,) or one radius for all;
        material: a Material or a material index for all, or an index per grain, shape (n,);
        velocities [m/s] and angular_velocities [rad/s] shape (n, 3) or (3,) for all; fixed and
        lock_rotation: one flag or shape (n,).

        Returns the builder indices of the new particles, shape (n,).
        """
        for name, value in (("positions", positions), ("radii", radii)):
            if _is_complex(value):  # numpy would drop the imaginary part with only a warning
                raise SoilInputError(f"{name} must be real numbers [m], got complex values")
        positions = _real_array(positions, "positions", "shape (n, 3) [m] (x, y, z per grain)")
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise SoilInputError(
                f"positions must have shape (n, 3) [m] (x, y, z per grain), got shape {positions.shape}"
            )
        n = len(positions)
        radii = _real_array(radii, "radii", f"one radius or shape (n,) = ({n},) [m]")
        if radii.ndim == 0:
            radii = np.full(n, float(radii))
        elif radii.shape != (n,):
            raise SoilInputError(
                f"radii must be one radius or shape (n,) = ({n},), one per position [m], got shape {radii.shape}"
            )
        bad = ~np.isfinite(positions).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise SoilInputError(
                f"positions must be finite [m]: {int(bad.sum())} are not, e.g. positions[{i}] = "
                f"{tuple(float(v) for v in positions[i])}"
            )
        bad = ~(np.isfinite(radii) & (radii > 0))
        if bad.any():
            i = int(np.argmax(bad))
            raise SoilInputError(
                f"radii must be finite and > 0 [m]: {int(bad.sum())} are not, e.g. radii[{i}] = {float(radii[i])!r}"
            )

        def vectors(values, name):
            if values is None:
                return np.zeros((n, 3))
            values = _real_array(values, name, f"shape (n, 3) = ({n}, 3) or (3,)")
            if values.shape not in ((3,), (n, 3)):
                raise SoilInputError(f"{name} must have shape (n, 3) = ({n}, 3) or (3,), got shape {values.shape}")
            values = np.broadcast_to(values, (n, 3)).copy()
            if not np.all(np.isfinite(values)):
                raise SoilInputError(f"{name} must be finite")
            return values

        def flags(values, name):
            try:
                values = np.asarray(values)
            except ValueError:  # a ragged list
                raise SoilInputError(f"{name} must be one flag or shape (n,) = ({n},), got {_brief(values)}") from None
            if values.shape not in ((), (n,)):
                raise SoilInputError(f"{name} must be one flag or shape (n,) = ({n},), got shape {values.shape}")
            # a flag is a bool or 0/1: astype(bool) would read any text or other number as true
            if not (values.dtype.kind == "b" or (values.dtype.kind in "iuf" and np.all((values == 0) | (values == 1)))):
                raise SoilInputError(f"{name} must be True/False or 0/1 (one, or one per grain), got {_brief(values)}")
            return np.broadcast_to(values.astype(bool), (n,)).copy()

        start = self.particle_count
        velocities = vectors(velocities, "velocities [m/s]")
        spins = vectors(angular_velocities, "angular_velocities [rad/s]")
        fixed, lock_rotation = flags(fixed, "fixed"), flags(lock_rotation, "lock_rotation")
        materials = self._material_indices(material, n)
        self._positions.append(positions)
        self._radii.append(radii)
        self._material.append(materials)
        self._velocity.append(velocities)
        self._spin.append(spins)
        self._fixed.append(fixed)
        self._lock_rotation.append(lock_rotation)
        return np.arange(start, start + n)

    def add_particle(
        self, position, radius, material=0, velocity=None, angular_velocity=None, fixed=False, lock_rotation=False
    ) -> int:
        """Add one sphere: position [m] (3,), radius [m]; returns its builder index."""
        if _is_complex(position):
            raise SoilInputError("position must be real numbers [m], got complex values")
        position = _real_array(position, "position", "3 numbers (x, y, z) [m]")
        if position.shape != (3,):
            raise SoilInputError(f"position must be 3 numbers (x, y, z) [m], got shape {position.shape}")
        if np.ndim(radius) != 0:
            raise SoilInputError(f"radius must be one number [m], got {radius!r}")
        return int(
            self.add_particles([position], [radius], material, velocity, angular_velocity, fixed, lock_rotation)[0]
        )

    # -- boundaries --------------------------------------------------------------
    def add_plane(self, point, normal, material=0, report: bool = True) -> int:
        """Add a half-space wall through `point` [m]; particles stay on the side `normal` points to.

        Returns its boundary index. report: sum the grains' force and torque on it
        (state.boundary_force); False reads zero there and refuses a load (set_boundary_load). It saves
        no memory and no launch: the walls' sums are one tree over every wall (soil.solver).
        Its torque is reported about `point`.
        """
        point = np.asarray(point, dtype=np.float64).reshape(3)
        normal = np.asarray(normal, dtype=np.float64).reshape(3)
        length = np.linalg.norm(normal)
        if not np.all(np.isfinite(point)):
            raise SoilInputError(f"plane point must be a finite 3-vector [m], got {point}")
        if not np.isfinite(length) or length == 0:
            raise SoilInputError(f"plane normal must be a non-zero finite 3-vector, got {normal}")
        return self._add_boundary(BOUNDARY_PLANE, [*point, *(normal / length)], self._material_index(material), report)

    def add_box(self, lower, upper, material=0, report: bool = True) -> int:
        """Add a solid axis-aligned box obstacle from `lower` to `upper` corner [m].

        Returns its boundary index; report as in add_plane. Its torque is reported about its centre.
        """
        lower, upper = (np.asarray(corner, dtype=np.float64) for corner in (lower, upper))
        if lower.shape != (3,) or upper.shape != (3,):
            raise SoilInputError(f"container corners must be 3-vectors (x, y, z) [m], got {lower} .. {upper}")
        if not np.all(upper > lower):
            raise SoilInputError(f"box upper corner must exceed lower corner on every axis, got {lower} .. {upper}")
        return self._add_boundary(BOUNDARY_BOX, [*lower, *upper], self._material_index(material), report)

    def add_boundary(self, kind: int, geometry, material=0, report: bool = True) -> int:
        """Add a boundary from its geometry row as SoilModel.boundary_geometry stores it (e.g. a
        saved bed's walls); returns its boundary index.

        kind: soil.sdf.BOUNDARY_PLANE (geometry: a point [m] (3) and the unit normal (3)) or
        BOUNDARY_BOX (geometry: lower and upper corner [m], 3 + 3). The row is kept as given:
        add_plane normalises its normal, which could change the last bit of a saved one.
        material and report as in add_plane.
        """
        row = np.asarray(geometry, dtype=np.float64)
        if row.shape != (6,) or not np.all(np.isfinite(row)):
            raise SoilInputError(f"boundary geometry must be 6 finite numbers, got {geometry!r}")
        if kind == BOUNDARY_PLANE:
            if not np.any(row[3:]):
                raise SoilInputError(f"plane normal must be a non-zero 3-vector, got {row[3:]}")
        elif kind == BOUNDARY_BOX:
            if not np.all(row[3:] > row[:3]):
                raise SoilInputError(f"box upper corner must exceed lower corner on every axis, got {row}")
        else:
            raise SoilInputError(
                f"boundary kind must be BOUNDARY_PLANE ({BOUNDARY_PLANE}) or BOUNDARY_BOX "
                f"({BOUNDARY_BOX}), got {kind!r}"
            )
        return self._add_boundary(kind, row, self._material_index(material), report)

    def _add_boundary(self, kind: int, row, material: int, report: bool = True) -> int:
        self._boundaries.append((int(kind), [float(g) for g in row], int(material), bool(report)))
        return len(self._boundaries) - 1

    def add_container(self, lower, upper, material=0, open_top=True, report: bool = True) -> list[int]:
        """Walls of a box-shaped container from `lower` to `upper` [m] (Z up): planes in the order
        floor, -x, +x, -y, +y (, lid); returns their boundary indices. report as in add_plane."""
        lower, upper = (np.asarray(corner, dtype=np.float64) for corner in (lower, upper))
        if lower.shape != (3,) or upper.shape != (3,):
            raise SoilInputError(f"container corners must be 3-vectors (x, y, z) [m], got {lower} .. {upper}")
        if not np.all(upper > lower):
            raise SoilInputError(
                f"container upper corner must exceed lower corner on every axis, got {lower} .. {upper}"
            )
        walls = [self.add_plane(lower, (0, 0, 1), material, report)]
        for axis in range(2):
            inward = np.zeros(3)
            inward[axis] = 1.0
            walls.append(self.add_plane(lower, inward, material, report))
            walls.append(self.add_plane(upper, -inward, material, report))
        if not open_top:
            walls.append(self.add_plane(upper, (0, 0, -1), material, report))
        return walls

    # -- wheels (rigid bodies moved by the control) --------------------------------
    def add_wheel(self, shape, material=0) -> int:
        """Add a wheel (GrouserWheel or MeshWheel) whose motion the control prescribes; returns its body index."""
        if not isinstance(shape, (GrouserWheel, MeshWheel)):
            raise TypeError(f"wheel shape must be a GrouserWheel or MeshWheel, got {type(shape).__name__}")
        self._bodies.append((shape, self._material_index(material)))
        return len(self._bodies) - 1

    # -- a saved state to start from ------------------------------------------------
    def start_from(self, state: dict, constants: dict | None = None, time: float = 0.0) -> None:
        """Let finalize() start the soil in a saved state instead of at rest (a settled bed).

        state: SoilState.to_numpy() output of a soil whose grains are this builder's, in
        builder order (the saved model's order): kinematics, forces and contact history,
        neighbours by builder index (data with keyed history slots, written before the
        neighbour list existed, is converted). Wheels and boundaries beyond the saved ones
        (added to this builder after the bed was saved) start at rest with no force; body
        arrays are not taken from it.
        constants: the grains' 'mass' [kg], 'inv_mass' [1/kg], 'inv_inertia' [1/(kg m^2)], each
        shape (n,), builder order, used as given instead of recomputed from the radii
        (recomputing them from rounded radii could change the last bit); None: computed.
        time: the clock of the finalized state [s] (a run on a bed starts at 0 when the bed is ready).
        finalize() permutes it all with order_seed like the grains.
        """
        if "position" not in state or ("neighbours" not in state and "contact_partner" not in state):
            raise SoilInputError("a saved state needs SoilState.to_numpy()'s arrays (position, neighbours, ...)")
        self._start = _SavedStart(dict(state), dict(constants or {}), float(time))

    # -- finalize ----------------------------------------------------------------
    def finalize(
        self,
        device: str | None = None,
        precision="double",
        law: ContactLaw | None = None,
        contact_capacity: int = 16,
        order_seed: int | None = None,
        rigid_capacity: int = 4,
        storage: str = "grain",
    ):
        """Create (model, state, control) on `device` ("cpu", "cuda:0", None = Warp's default).

        law: contact-law switches; by default rolling and cohesion are on only if a
        material uses them. contact_capacity: neighbour-list slots per grain;
        rigid_capacity: contact slots per grain for walls and wheels (both grown
        automatically when exceeded, the macro step then redone). order_seed: permute
        particle indices (changes only the summation order, for scatter studies). storage: the
        neighbour lists' and contact history's order in memory, "grain" (per grain) or "slot"
        (per slot, for coalesced GPU reads; SoilModel.slot_major).
        """
        if storage not in STORAGE_ORDERS:
            raise SoilInputError(f"storage must be one of {', '.join(STORAGE_ORDERS)}, got {storage!r}")
        prec = get_precision(precision)
        device = warp_device(device)
        if order_seed is not None and (
            isinstance(order_seed, bool) or not isinstance(order_seed, (int, np.integer)) or order_seed < 0
        ):
            raise SoilInputError(f"order_seed must be None or an integer >= 0, got {order_seed!r}")
        if self.particle_count == 0:
            raise SoilInputError("the scene has no particles")
        if not self.materials.materials:
            self.add_material(Material())
        if law is None:
            mats = self.materials.materials
            law = ContactLaw(
                rolling=any(m.rolling_friction > 0 for m in mats), cohesion=any(m.cohesion > 0 for m in mats)
            )
        for name, value in (("contact_capacity", contact_capacity), ("rigid_capacity", rigid_capacity)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise SoilInputError(f"{name} must be an integer >= 1, got {value!r}")
        self._check_inside()
        self._check_overlaps()

        positions = np.concatenate(self._positions)
        radii = np.concatenate(self._radii)
        material = np.concatenate(self._material)
        velocity = np.concatenate(self._velocity)
        spin = np.concatenate(self._spin)
        fixed = np.concatenate(self._fixed)
        locked = np.concatenate(self._lock_rotation)
        order = np.arange(len(radii))
        if order_seed is not None:
            order = np.random.default_rng(order_seed).permutation(len(radii))
        positions, radii, material, velocity, spin, fixed, locked = (
            a[order] for a in (positions, radii, material, velocity, spin, fixed, locked)
        )

        density = np.array([self.materials.materials[m].density for m in material])
        mass = density * (4.0 / 3.0) * math.pi * radii**3
        inertia = 0.4 * mass * radii**2
        inv_mass = np.where(fixed, 0.0, 1.0 / mass)
        inv_inertia = np.where(fixed | locked, 0.0, 1.0 / inertia)
        start = self._start
        if start is not None:
            start.check(len(radii))
            given = start.constants
            mass, inv_mass, inv_inertia = (
                np.asarray(given[name])[order] if name in given else computed
                for name, computed in (("mass", mass), ("inv_mass", inv_mass), ("inv_inertia", inv_inertia))
            )

        lo, hi = prec.np_lo, prec.np_hi
        limit = float(np.finfo(lo).max)
        for name, values in (("inverse mass", inv_mass), ("inverse inertia", inv_inertia)):
            values = np.abs(np.asarray(values, dtype=np.float64))
            if len(values) and not values.max() < limit:  # nanometre grains in float32: inf, then a NaN state
                k = int(np.argmax(np.where(np.isnan(values), np.inf, values)))
                raise SoilInputError(
                    f"a grain of radius {radii[k]:.3g} m has an {name} of {values[k]:.3g} (SI units), beyond "
                    f"{prec.name} precision's range ({limit:.3g}): larger grains, or precision 'double'"
                )
        kinds = np.array([b[0] for b in self._boundaries], dtype=np.int32)
        geometry = np.array([b[1] for b in self._boundaries], dtype=hi).reshape(-1, 6)
        bmat = np.array([b[2] for b in self._boundaries], dtype=np.int32)
        reports = np.array([b[3] for b in self._boundaries], dtype=bool)
        columns = np.where(reports, np.cumsum(reports) - 1, -1).astype(np.int32)

        body_arrays = self._body_arrays(prec, device)
        model = SoilModel(
            device=device,
            precision=prec,
            law=law,
            materials=self.materials,
            gravity=self.gravity.copy(),
            particle_count=len(radii),
            radius=wp.array(radii.astype(lo), dtype=prec.lo, device=device),
            mass=wp.array(mass.astype(lo), dtype=prec.lo, device=device),
            inv_mass=wp.array(inv_mass.astype(lo), dtype=prec.lo, device=device),
            inv_inertia=wp.array(inv_inertia.astype(lo), dtype=prec.lo, device=device),
            material=wp.array(material, dtype=wp.int32, device=device),
            pair=wp.array(self.materials.pair_table().astype(lo), dtype=prec.lo, device=device),
            boundary_kind=wp.array(kinds, dtype=wp.int32, device=device),
            boundary_geometry=wp.array(geometry, dtype=prec.hi, device=device),
            boundary_material=wp.array(bmat, dtype=wp.int32, device=device),
            boundary_column=wp.array(columns, dtype=wp.int32, device=device),
            max_radius=float(radii.max()),
            particle_order=order,
            slot_major=storage == "slot",
            **body_arrays,
        )
        state = SoilState.for_model(model, int(contact_capacity), int(rigid_capacity))
        state.position.assign(positions.astype(hi))
        state.velocity.assign(velocity.astype(hi))
        state.angular_velocity.assign(spin.astype(hi))
        control = SoilControl.for_model(model)
        if start is not None:
            _load_saved_state(model, state, start.state, start.time)
        return model, state, control

    def _check_inside(self) -> None:
        """Free grains whose centre lies behind a wall (outside the container) or inside a box are an error."""
        if not self._boundaries:
            return
        positions = np.concatenate(self._positions)
        free = ~np.concatenate(self._fixed)
        for b, (kind, values, _, _) in enumerate(self._boundaries):
            row = np.asarray(values, dtype=np.float64)
            if kind == BOUNDARY_PLANE:
                outside = free & ((positions - row[:3]) @ row[3:] < 0)
                where = (
                    f"behind boundary {b}, the plane through {tuple(float(v) for v in row[:3])} m (grains "
                    f"stay on the side its normal {tuple(float(v) for v in row[3:])} points to)"
                )
            else:
                outside = free & np.all((positions > row[:3]) & (positions < row[3:]), axis=1)
                where = (
                    f"inside boundary {b}, the solid box {tuple(float(v) for v in row[:3])} .. "
                    f"{tuple(float(v) for v in row[3:])} m"
                )
            if outside.any():
                i = int(np.argmax(outside))
                raise SoilInputError(
                    f"{int(outside.sum())} grain(s) have their centre {where}, e.g. particle {i} "
                    f"at {tuple(float(v) for v in positions[i])} m: move them inside the container "
                    "(or fix them)"
                )

    def _check_overlaps(self) -> None:
        """Warn when grains were created deep inside each other or inside a wall (OverlapWarning)."""
        from scipy.spatial import cKDTree

        positions = np.concatenate(self._positions)
        radii = np.concatenate(self._radii)
        fixed = np.concatenate(self._fixed)
        worst, where, count = 0.0, "", 0
        if len(radii) > 1:
            reach = 2.0 * radii.max() - DEEP_OVERLAP * radii.min()
            pairs = cKDTree(positions).query_pairs(reach, output_type="ndarray")
            if len(pairs):
                i, j = pairs[:, 0], pairs[:, 1]
                depth = radii[i] + radii[j] - np.linalg.norm(positions[i] - positions[j], axis=1)
                ratio = depth / np.minimum(radii[i], radii[j])
                deep = (ratio > DEEP_OVERLAP) & ~(fixed[i] & fixed[j])
                count += int(deep.sum())
                if deep.any():
                    k = int(np.argmax(np.where(deep, ratio, -np.inf)))
                    worst, where = float(ratio[k]), f"particles {int(i[k])} and {int(j[k])} by {depth[k]:.3g} m"
        for b, (kind, values, _, _) in enumerate(self._boundaries):
            if kind != BOUNDARY_PLANE:
                continue
            row = np.asarray(values, dtype=np.float64)
            depth = radii - (positions - row[:3]) @ row[3:]
            ratio = np.where(fixed, -np.inf, depth / radii)
            deep = ratio > DEEP_OVERLAP
            count += int(deep.sum())
            if deep.any() and ratio.max() > worst:
                k = int(np.argmax(ratio))
                worst, where = float(ratio[k]), f"particle {k} and boundary {b} by {depth[k]:.3g} m"
        if count:
            # a saved state (a settled bed) that overlaps this deep was pressed so by its own load
            remedy = (
                "the saved grains were pressed this deep by their load: the soil is too soft for it (raise its "
                "Young's modulus: the paper's eq. 10, `cosim advise`)"
                if self._start is not None
                else "their first contact throws the grains apart; space them out"
            )
            warnings.warn(
                f"{count} contact(s) were created with an overlap above {DEEP_OVERLAP:g} x the smaller "
                f"radius (the deepest: {where}, {worst:.3g} x its radius): {remedy}",
                OverlapWarning,
                stacklevel=3,
            )

    def _body_arrays(self, prec, device) -> dict:
        kinds, shapes, materials, point_offsets, index_offsets = [], [], [], [], []
        points, indices, meshes, mesh_ids = [], [], [], []
        n_points = n_indices = 0
        for shape, material in self._bodies:
            materials.append(material)
            point_offsets.append(n_points)
            index_offsets.append(n_indices)
            if isinstance(shape, GrouserWheel):
                kinds.append(BODY_WHEEL)
                shapes.append(shape.shape_row())
                mesh_ids.append(0)
                continue
            kinds.append(BODY_MESH)
            shapes.append([0, 0, 0, 0, 0, shape.bounding_radius])
            mesh = wp.Mesh(
                points=wp.array(shape.vertices.astype(np.float32), dtype=wp.vec3, device=device),
                indices=wp.array(shape.triangles.reshape(-1), dtype=wp.int32, device=device),
            )
            meshes.append(mesh)
            mesh_ids.append(mesh.id)
            points.append(shape.vertices)
            indices.append(shape.triangles.reshape(-1))
            n_points += len(shape.vertices)
            n_indices += shape.triangles.size
        all_points = np.concatenate(points) if points else np.zeros((1, 3))
        all_indices = np.concatenate(indices) if indices else np.zeros(3, dtype=np.int32)
        return dict(
            bodies=[shape for shape, _ in self._bodies],
            body_kind=wp.array(np.array(kinds, dtype=np.int32), dtype=wp.int32, device=device),
            body_shape=wp.array(np.array(shapes, dtype=prec.np_hi).reshape(-1, 6), dtype=prec.hi, device=device),
            body_mesh=wp.array(np.array(mesh_ids, dtype=np.uint64), dtype=wp.uint64, device=device),
            body_material=wp.array(np.array(materials, dtype=np.int32), dtype=wp.int32, device=device),
            mesh_points=wp.array(all_points.astype(prec.np_hi), dtype=prec.vec_hi, device=device),
            mesh_indices=wp.array(all_indices.astype(np.int32), dtype=wp.int32, device=device),
            body_point_offset=wp.array(np.array(point_offsets, dtype=np.int32), dtype=wp.int32, device=device),
            body_index_offset=wp.array(np.array(index_offsets, dtype=np.int32), dtype=wp.int32, device=device),
            meshes=meshes,
        )


@dataclass
class _SavedStart:
    """What SoilBuilder.start_from was given: state arrays and constants in builder order, the clock [s]."""

    state: dict
    constants: dict
    time: float

    def check(self, particle_count: int) -> None:
        """SoilInputError when the saved arrays are not one row per grain of the builder."""
        rows = {name: values for name, values in self.state.items() if per_grain(name)}
        for name, values in {**rows, **self.constants}.items():
            count = np.shape(values)[0] if np.ndim(values) else None
            if count != particle_count:
                raise SoilInputError(
                    f"the saved {name!r} has {count} rows, the builder {particle_count} grains "
                    "(start_from takes the state of the builder's own grains)"
                )


def _load_saved_state(model: SoilModel, state: SoilState, saved: dict, time: float) -> None:
    """Fill a fresh state with saved arrays (SoilBuilder.start_from: builder order, neighbours by builder
    index), permuted into model order; wheels and boundaries the saved state lacks start at rest."""
    n = model.particle_count
    order = model.particle_order  # builder index (= the saved model index) of each model particle
    inverse = np.empty_like(order)
    inverse[order] = np.arange(n)
    data = current_format(saved, n)
    for name in list(data):
        if name != "time" and per_grain(name):
            data[name] = np.asarray(data[name])[order]
    neighbours = data["neighbours"]
    data["neighbours"] = np.where(neighbours >= 0, inverse[np.maximum(neighbours, 0)], -1).astype(np.int32)
    data = rows_in_partner_order(data)  # renumbered partners, listed as a build lists them
    current = state.to_numpy()
    for name, values in current.items():
        if name.startswith("body_") or name not in data:  # fields added after the state was saved
            data[name] = values
        elif name.startswith("boundary_") and len(data[name]) < len(values):
            padded = values.copy()  # boundaries added after the state was saved: at rest
            padded[: len(data[name])] = data[name]
            data[name] = padded
    data["time"] = time
    state.load_numpy(data)
