"""The static soil model: everything that does not change while the soil moves."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .contact import ContactLaw
from .materials import MaterialTable
from .precision import Precision


@dataclass
class SoilModel:
    """Particles' constants, materials, boundaries and the contact-law switches.

    Built by `SoilBuilder.finalize()`. Arrays live on `device`; `hi`/`lo` are the
    precision's types (see soil.precision).
    """

    device: str
    precision: Precision
    law: ContactLaw
    materials: MaterialTable
    gravity: np.ndarray
    """Gravity vector [m/s^2], shape (3,)."""
    particle_count: int
    radius: wp.array
    """Particle radii [m], shape (particle_count,), dtype lo."""
    mass: wp.array
    """Particle masses [kg], shape (particle_count,), dtype lo."""
    inv_mass: wp.array
    """Inverse masses [1/kg], shape (particle_count,), dtype lo; 0 for fixed particles."""
    inv_inertia: wp.array
    """Inverse moments of inertia [1/(kg m^2)], shape (particle_count,), dtype lo; 0 when rotation is locked."""
    material: wp.array
    """Material index per particle [-], shape (particle_count,), int32."""
    pair: wp.array
    """Pair contact parameters, shape (material_count**2, PAIR_COLUMNS), dtype lo; each column in its own
    unit (soil.materials.PAIR_*: E* and G* [Pa], damping ratio [-], tangents of the friction angles [-],
    stick speed [m/s], rolling friction [-], cohesion [Pa], shear root [-])."""
    boundary_kind: wp.array
    """Boundary type per boundary (BOUNDARY_PLANE or BOUNDARY_BOX) [-], shape (boundary_count,), int32."""
    boundary_geometry: wp.array
    """Initial boundary geometry rows [m], shape (boundary_count, 6), dtype hi (see soil.sdf);
    a boundary that moves is there displaced by state.boundary_displacement."""
    boundary_material: wp.array
    """Material index per boundary [-], shape (boundary_count,), int32."""
    max_radius: float
    """Largest particle radius [m]."""
    boundary_column: wp.array | None = None
    """Column of each boundary in the per-particle force scratch [-], shape (boundary_count,), int32;
    -1 for boundaries built with report=False (their force and torque are not summed)."""
    particle_order: np.ndarray | None = field(default=None)
    """Builder index of each model particle [-], shape (particle_count,), int64 (identity unless permuted)."""
    bodies: list = field(default_factory=list)
    """Wheel geometries (GrouserWheel or MeshWheel), one per body."""
    body_kind: wp.array | None = None
    """BODY_WHEEL or BODY_MESH per body [-], shape (body_count,), int32."""
    body_shape: wp.array | None = None
    """Geometry row per body [m], shape (body_count, 6), dtype hi (see soil.sdf)."""
    body_mesh: wp.array | None = None
    """Warp mesh id per body (0 for parametric wheels) [-], shape (body_count,), uint64."""
    body_material: wp.array | None = None
    """Material index per body [-], shape (body_count,), int32."""
    mesh_points: wp.array | None = None
    """All mesh vertices in their wheel frames [m], shape (vertex_count,), vec3 hi."""
    mesh_indices: wp.array | None = None
    """All mesh triangles' vertex indices, flattened [-], shape (3 * triangle_count,), int32."""
    body_point_offset: wp.array | None = None
    """First vertex of each body's mesh in mesh_points [-], shape (body_count,), int32."""
    body_index_offset: wp.array | None = None
    """First index of each body's mesh in mesh_indices [-], shape (body_count,), int32."""
    meshes: list = field(default_factory=list)
    """The wp.Mesh objects (kept alive here), one per mesh body."""
    slot_major: bool = False
    """The storage order of the neighbour lists and the contact history (soil.state): False, per
    grain (a grain's entries side by side: what one CPU thread reads in turn); True, per slot
    (entry k of every grain side by side: what neighbouring GPU threads read at once). The physics
    is the same to the last bit (docs/performance.md section 2)."""
    world_count: int = 1
    """Independent copies of one scene in this model (soil.worlds): world w holds grains
    w * world_size .. (w + 1) * world_size - 1 (model order), and its walls and wheels likewise
    (walls_per_world, bodies_per_world); a grain touches only its own world's."""

    @property
    def world_size(self) -> int:
        """Grains per world [-]."""
        return self.particle_count // self.world_count

    @property
    def walls_per_world(self) -> int:
        """Boundaries per world [-]."""
        return self.boundary_count // self.world_count

    @property
    def bodies_per_world(self) -> int:
        """Bodies (wheels) per world [-]."""
        return self.body_count // self.world_count

    @property
    def body_count(self) -> int:
        return len(self.bodies)

    @property
    def material_count(self) -> int:
        return len(self.materials.materials)

    @property
    def boundary_count(self) -> int:
        return int(self.boundary_kind.shape[0])

    @property
    def boundary_reports(self) -> np.ndarray:
        """Whether each boundary's force and torque are summed, shape (boundary_count,), bool (host)."""
        if self.boundary_column is None:
            return np.ones(self.boundary_count, dtype=bool)
        return self.boundary_column.numpy() >= 0

    def boundary_geometry_numpy(self) -> np.ndarray:
        """Initial boundary geometry rows [m], shape (boundary_count, 6), float64."""
        return self.boundary_geometry.numpy().astype(np.float64).reshape(-1, 6)

    def radius_numpy(self) -> np.ndarray:
        """Grain radii [m], shape (particle_count,), float64 (a host copy)."""
        return self.radius.numpy().astype(np.float64)

    def mass_numpy(self) -> np.ndarray:
        """Grain masses [kg], shape (particle_count,), float64 (a host copy)."""
        return self.mass.numpy().astype(np.float64)
