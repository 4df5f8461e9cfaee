"""Contact forces: each grain gathers the forces of its contacts, in its own thread, with no atomics.

Grain-grain contacts are found in the grain's row of the neighbour list (soil.neighbours);
both grains of a pair evaluate the same contact with mirrored inputs and keep their own
(mirrored) history, aligned with their rows. Contacts with rigid partners (walls, boxes,
wheels: the signed distances of soil.sdf) are evaluated by the same code for every kind of
partner, and their history is kept in slots keyed by the partner. The sums are in a fixed
order (the row, then the rigid partners by index), so runs repeat bit for bit on every
device, whatever the storage order.

The reaction of each rigid contact is written beside its slot and summed per wall and
wheel over a fixed tree of model indices (soil.reduction: `wrench_partial` the leaves,
`wrench_total` the last rows): deterministic, no atomics.

A grain's sums take two kernels, in the order one would add them (the same bits):
`grain_contacts` (the external load, then its row of grain contacts) and `rigid_contacts` (its
walls and wheels). The rigid distances (a wheel's grousers, a mesh's query) need about twice the
registers of a grain pair, and in one kernel they set the occupancy of every pair loop on a GPU
(docs/performance.md section 7).
"""

import numpy as np
import warp as wp

from . import status as status_columns
from .boundaries import update_acceleration
from .contact import ContactLaw, contact_functions, spin_history_type
from .control import SoilControl
from .model import SoilModel
from .neighbours import NeighbourList
from .precision import kernel_factory, kernel_module, soil_kernel
from .reduction import WorldTree, leaf_span
from .sdf import BODY_WHEEL, sdf_functions
from .state import SoilState, storage_functions

CONTACT_BLOCK_DIM = 128
"""Threads per block of the contact module's launches on a GPU. Warp compiles a module once per block
size, so it is both the module's option `block_dim` (the copy a preload before capture and an
ahead-of-time compile build) and every launch's (wp.launch takes 256 on a GPU unless told). Registers per
thread on sm_90 (benchmarks/kernel_resources.py: grain_contacts 76-160, rigid_contacts 162-255): from
129 to 168 an SM keeps one block of 256 threads resident, 8 warps, but 3 blocks of 128, 12 warps;
at other counts blocks of 128 keep as many warps as blocks of 256, never fewer."""


@kernel_factory
def contact_kernels(hi, mid, lo, law: ContactLaw, slot_major: bool = False):
    """The contact kernels and their argument bundles for precision types (hi, mid, lo), the switches
    and the storage order (soil.state).

    Spins and history are stored in `mid` (soil.precision): read into `hi`, rounded when stored."""
    module = kernel_module("contact", hi, mid, lo, law, *(("slot",) if slot_major else ()))
    wp.set_module_options({"block_dim": CONTACT_BLOCK_DIM}, module)
    kernel = soil_kernel(module)
    storage = storage_functions(module, slot_major)
    entry, list_capacity, at, put, slots = storage.entry, storage.list_capacity, storage.at, storage.put, storage.slots
    vec_hi = wp.types.vector(3, hi)
    vec_mid = wp.types.vector(3, mid)
    mat_hi = wp.types.matrix((3, 3), hi)
    contact_law = contact_functions(hi, lo, law).contact_law
    # A grain pair is evaluated in `lo` once its differences are taken in `hi` (docs/physics.md section 3)
    pair_law = contact_functions(lo, lo, law).contact_law
    vec_lo = wp.types.vector(3, lo)
    vec_spin_lo = spin_history_type(lo, law)
    sdf = sdf_functions(hi)
    boundary_contact, boundary_reference = sdf.boundary_contact, sdf.boundary_reference
    wheel_distance, mesh_distance = sdf.wheel_distance, sdf.mesh_distance
    FRICTION, SPIN = law.friction, law.spin
    vec_spin = spin_history_type(hi, law)  # the contact law's
    vec_spin_mid = spin_history_type(mid, law)  # as stored

    @wp.struct
    class Grains:
        """The grains' constants in storage order (GrainLayout), shape (grains,): order and material [-],
        radius [m], mass [kg], inv_mass [1/kg]; pair: SoilModel.pair (its columns' units there)."""

        order: wp.array(dtype=wp.int32)
        radius: wp.array(dtype=lo)
        mass: wp.array(dtype=lo)
        inv_mass: wp.array(dtype=lo)
        material: wp.array(dtype=wp.int32)
        pair: wp.array2d(dtype=lo)
        material_count: int
        world_size: int  # grains per world (soil.worlds): a grain's world is its model index // world_size

    @wp.struct
    class Walls:
        """Boundaries: model geometry and the state's displacement and velocity, shape (boundaries,): kind and
        material [-], geometry rows [m] (boundaries, 6), displacement [m], velocity [m/s]."""

        kind: wp.array(dtype=wp.int32)
        geometry: wp.array2d(dtype=hi)
        material: wp.array(dtype=wp.int32)
        displacement: wp.array(dtype=vec_hi)
        velocity: wp.array(dtype=vec_hi)
        per_world: int  # world w's walls are w * per_world .. (w + 1) * per_world - 1

    @wp.struct
    class Bodies:
        """Wheels: model geometry and the state's poses and velocities, shape (bodies,) (SoilModel's and
        SoilState's body_* of the same names): kind, mesh, material, posed and the mesh indices and offsets
        [-]; shape rows [m] (bodies, 6); mesh_points [m]; position [m], rotation body -> world [-],
        velocity [m/s], angular_velocity [rad/s]."""

        kind: wp.array(dtype=wp.int32)
        shape: wp.array2d(dtype=hi)
        mesh: wp.array(dtype=wp.uint64)
        material: wp.array(dtype=wp.int32)
        mesh_points: wp.array(dtype=vec_hi)
        mesh_indices: wp.array(dtype=wp.int32)
        point_offset: wp.array(dtype=wp.int32)
        index_offset: wp.array(dtype=wp.int32)
        position: wp.array(dtype=vec_hi)
        rotation: wp.array(dtype=mat_hi)
        velocity: wp.array(dtype=vec_hi)
        angular_velocity: wp.array(dtype=vec_hi)
        posed: wp.array(dtype=wp.int32)
        per_world: int  # world w's wheels are w * per_world .. (w + 1) * per_world - 1

    @wp.struct
    class History:
        """A state's contact history (SoilState pair_* and rigid_*, their shapes): tangential [m] and rolling
        [rad] springs; touching bits, rigid_key and rigid_count [-]."""

        touching: wp.array2d(dtype=wp.uint32)
        tangential: wp.array2d(dtype=vec_mid)
        rolling: wp.array2d(dtype=vec_spin_mid)
        rigid_key: wp.array2d(dtype=wp.int32)
        rigid_count: wp.array(dtype=wp.int32)
        rigid_tangential: wp.array2d(dtype=vec_mid)
        rigid_rolling: wp.array2d(dtype=vec_spin_mid)

    @wp.func
    def rigid_slot(history: History, i: int, key: int):
        """The slot of rigid partner `key` in grain i's history, -1 if it had none."""
        for s in range(wp.min(history.rigid_count[i], slots(history.rigid_key))):
            if at(history.rigid_key, i, s) == key:
                return s
        return -1

    @kernel
    def grain_contacts(
        position: wp.array(dtype=vec_hi),
        velocity: wp.array(dtype=vec_hi),
        angular_velocity: wp.array(dtype=vec_mid),
        grains: Grains,
        neighbours: wp.array3d(dtype=wp.int32),
        neighbour_count: wp.array2d(dtype=wp.int32),
        list_index: wp.array(dtype=wp.int32),
        rebuilt: wp.array(dtype=wp.int32),
        history_in: History,
        external_force: wp.array(dtype=vec_hi),
        external: int,
        step_length: wp.array(dtype=hi),
        world_size: int,
        # outputs
        force_out: wp.array(dtype=vec_hi),
        torque_sum_out: wp.array(dtype=vec_hi),
        contact_count_out: wp.array(dtype=wp.int32),
        history_out: History,
    ):
        """Force and torque on grain i from the external load and its grain contacts (the first
        terms of its sums, which rigid_contacts finishes), and its new pair history. After a
        rebuild the pair history was remapped into history_out, and is read from there."""
        i = wp.tid()
        dt = step_length[i // world_size]  # each world's step (soil.worlds: a world is one block of storage)
        xi = position[i]
        vi = velocity[i]
        wi = vec_lo(angular_velocity[i])
        ri = grains.radius[i]
        inv_mass_i = grains.inv_mass[i]
        total_force = vec_hi()
        if external != 0:
            total_force = external_force[grains.order[i]]
        total_torque = vec_hi()
        contacts = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)

        # grains: the row of the neighbour list; history bit k marks entry k in contact
        row = list_index[0]
        remapped = rebuilt[0] != 0
        count = neighbour_count[row, i]
        capacity = list_capacity(neighbours)
        for word in range(slots(history_out.touching)):
            held = at(history_out.touching, i, word)  # what the output buffer holds (remapped, or from before)
            was = held
            if not remapped:
                was = at(history_in.touching, i, word)
            now = wp.uint32(0)
            for k in range(word * 32, wp.min(word * 32 + 32, count)):
                j = entry(neighbours, row, i, k)
                gap = position[j] - xi
                rj = grains.radius[j]
                reach = hi(ri + rj)
                squared = wp.dot(gap, gap)
                distance = reach  # most entries are not in contact: no square root for them
                inv_sum = lo(0.0)
                if squared < reach * reach:
                    distance = wp.sqrt(squared)
                    inv_sum = inv_mass_i + grains.inv_mass[j]
                overlap = reach - distance
                if overlap > hi(0.0) and distance > hi(0.0) and inv_sum > lo(0.0):
                    # The milli-g scales live in the differences (an overlap of nm between positions of
                    # m, a relative velocity between grains that move together), taken above in hi;
                    # what follows is relative to them and needs no more than lo's 7 digits.
                    n = vec_lo(gap / distance)
                    ov = lo(overlap)
                    lever_i = ri - lo(0.5) * ov
                    lever_j = rj - lo(0.5) * ov
                    w_j = vec_lo(angular_velocity[j])
                    v_rel = vec_lo(vi - velocity[j]) + wp.cross(wi, lever_i * n) + wp.cross(w_j, lever_j * n)
                    bit = wp.uint32(1) << wp.uint32(k & 31)
                    t_hist = vec_lo()
                    r_hist = vec_spin_lo()
                    if (was & bit) != wp.uint32(0):
                        if wp.static(FRICTION):
                            if remapped:
                                t_hist = vec_lo(at(history_out.tangential, i, k))
                            else:
                                t_hist = vec_lo(at(history_in.tangential, i, k))
                        if wp.static(SPIN):
                            if remapped:
                                r_hist = vec_spin_lo(at(history_out.rolling, i, k))
                            else:
                                r_hist = vec_spin_lo(at(history_in.rolling, i, k))
                    pair_row = grains.material[i] * grains.material_count + grains.material[j]
                    f, m_roll, t_new, r_new = pair_law(
                        n,
                        ov,
                        v_rel,
                        wi - w_j,
                        ri * rj / (ri + rj),
                        lo(1.0) / inv_sum,
                        grains.pair,
                        pair_row,
                        t_hist,
                        r_hist,
                        lo(dt),
                    )
                    total_force = total_force + vec_hi(f)
                    total_torque = total_torque + vec_hi(wp.cross(lever_i * n, f) + m_roll)
                    if wp.static(FRICTION):
                        put(history_out.tangential, i, k, vec_mid(t_new))
                    if wp.static(SPIN):
                        put(history_out.rolling, i, k, vec_spin_mid(r_new))
                    now = now | bit
                    contacts += 1
            # entries out of contact hold zero: clear what the buffer held and no contact wrote
            clear = held & ~now
            if clear != wp.uint32(0):
                for k in range(word * 32, wp.min(word * 32 + 32, capacity)):
                    if (clear >> wp.uint32(k & 31)) & wp.uint32(1) != wp.uint32(0):
                        if wp.static(FRICTION):
                            put(history_out.tangential, i, k, vec_mid())
                        if wp.static(SPIN):
                            put(history_out.rolling, i, k, vec_spin_mid())
            put(history_out.touching, i, word, now)
        force_out[i] = total_force
        torque_sum_out[i] = total_torque
        contact_count_out[i] = contacts

    @kernel
    def rigid_contacts(
        position: wp.array(dtype=vec_hi),
        velocity: wp.array(dtype=vec_hi),
        angular_velocity: wp.array(dtype=vec_mid),
        grains: Grains,
        walls: Walls,
        bodies: Bodies,
        history_in: History,
        step_length: wp.array(dtype=hi),
        world_size: int,
        torque_sum: wp.array(dtype=vec_hi),
        # outputs (force_out and contact_count_out also read: grain_contacts' terms)
        force_out: wp.array(dtype=vec_hi),
        torque_out: wp.array(dtype=vec_mid),
        contact_count_out: wp.array(dtype=wp.int32),
        history_out: History,
        reaction_force_out: wp.array2d(dtype=vec_hi),
        reaction_torque_out: wp.array2d(dtype=vec_hi),
        status_out: wp.array(dtype=wp.int32),
    ):
        """Grain i's contacts with rigid partners added to the sums grain_contacts began (in the
        same order as one kernel would add them: the same bits), their history, and their
        reactions. A kernel of its own because the walls' and wheels' distances (a wheel's
        grousers, a mesh's query) need many more registers than a grain pair: in one kernel they
        set the register count, and so the occupancy, of every grain's pair loop too."""
        i = wp.tid()
        dt = step_length[i // world_size]
        xi = position[i]
        vi = velocity[i]
        wi = vec_hi(angular_velocity[i])
        ri = grains.radius[i]
        inv_mass_i = grains.inv_mass[i]
        total_force = force_out[i]
        total_torque = torque_sum[i]
        contacts = contact_count_out[i]

        # rigid partners of the grain's world: walls (fixed grains do not touch them), then wheels
        # (every grain); a partner's key is its index among all walls, then all wheels
        wall_count = walls.kind.shape[0]
        world = grains.order[i] // grains.world_size
        rigid_slots = slots(history_out.rigid_key)
        stored = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        for nth in range(walls.per_world + bodies.per_world):
            partner = world * walls.per_world + nth
            if nth >= walls.per_world:
                partner = wall_count + world * bodies.per_world + nth - walls.per_world
            overlap = hi(0.0)
            n = vec_hi()
            v_partner = vec_hi()
            w_partner = vec_hi()
            reference = vec_hi()
            mass_eff = lo(0.0)
            partner_material = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
            if partner < wall_count:
                if inv_mass_i > lo(0.0):
                    shift = walls.displacement[partner]
                    overlap, n = boundary_contact(walls.kind[partner], walls.geometry, partner, xi - shift, hi(ri))
                    v_partner = walls.velocity[partner]  # a translating wall: its contact point moves with it
                    reference = boundary_reference(walls.kind[partner], walls.geometry, partner) + shift
                    mass_eff = lo(1.0) / inv_mass_i
                    partner_material = walls.material[partner]
            else:
                b = partner - wall_count
                hub = bodies.position[b]
                rotation = bodies.rotation[b]
                local = wp.transpose(rotation) * (xi - hub)
                reach = bodies.shape[b, 5] + hi(ri)
                if bodies.posed[b] != 0 and wp.length(local) < reach:  # a body not yet posed is nowhere
                    distance = reach
                    n_out = vec_hi()
                    if bodies.kind[b] == BODY_WHEEL:
                        distance, n_out = wheel_distance(bodies.shape, b, local)
                    else:
                        distance, n_out = mesh_distance(
                            bodies.mesh[b],
                            bodies.mesh_points,
                            bodies.mesh_indices,
                            bodies.point_offset[b],
                            bodies.index_offset[b],
                            local,
                            hi(2.0) * reach,
                        )
                    overlap = hi(ri) - distance
                    n = -(rotation * n_out)  # from the grain towards the wheel
                    contact_point = xi + (hi(ri) - overlap) * n
                    w_partner = bodies.angular_velocity[b]
                    v_partner = bodies.velocity[b] + wp.cross(w_partner, contact_point - hub)
                    reference = hub
                    mass_eff = grains.mass[i]
                    partner_material = bodies.material[b]
            if overlap > hi(0.0):
                lever_i = hi(ri) - overlap
                v_rel = vi + wp.cross(wi, lever_i * n) - v_partner
                slot = rigid_slot(history_in, i, partner)
                t_hist = vec_hi()
                r_hist = vec_spin()
                if slot >= 0:
                    if wp.static(FRICTION):
                        t_hist = vec_hi(at(history_in.rigid_tangential, i, slot))
                    if wp.static(SPIN):
                        r_hist = vec_spin(at(history_in.rigid_rolling, i, slot))
                pair_row = grains.material[i] * grains.material_count + partner_material
                f, m_roll, t_new, r_new = contact_law(
                    n, overlap, v_rel, wi - w_partner, ri, mass_eff, grains.pair, pair_row, t_hist, r_hist, dt
                )
                total_force = total_force + f
                total_torque = total_torque + wp.cross(lever_i * n, f) + m_roll
                if stored < rigid_slots:
                    put(history_out.rigid_key, i, stored, partner)
                    if wp.static(FRICTION):
                        put(history_out.rigid_tangential, i, stored, vec_mid(t_new))
                    if wp.static(SPIN):
                        put(history_out.rigid_rolling, i, stored, vec_spin_mid(r_new))
                    put(reaction_force_out, i, stored, -f)
                    put(reaction_torque_out, i, stored, wp.cross(xi + lever_i * n - reference, -f) - m_roll)
                stored += 1
                contacts += 1
        history_out.rigid_count[i] = wp.min(stored, rigid_slots)
        for s in range(stored, rigid_slots):  # free slots hold zero (only those the buffer used are written)
            if at(history_out.rigid_key, i, s) >= 0:
                put(history_out.rigid_key, i, s, -1)
                if wp.static(FRICTION):
                    put(history_out.rigid_tangential, i, s, vec_mid())
                if wp.static(SPIN):
                    put(history_out.rigid_rolling, i, s, vec_spin_mid())
        if stored > rigid_slots:
            wp.atomic_max(status_out, status_columns.NEEDED_RIGID, stored)

        force_out[i] = total_force
        torque_out[i] = vec_mid(total_torque)
        contact_count_out[i] = contacts

    @kernel
    def elastic_energy(
        position: wp.array(dtype=vec_hi),
        grains: Grains,
        walls: Walls,
        neighbours: wp.array3d(dtype=wp.int32),
        neighbour_count: wp.array2d(dtype=wp.int32),
        row: int,
        # outputs
        energy_out: wp.array(dtype=hi),
    ):
        """Hertz strain energy (8/15) E* sqrt(R*) delta^2.5 per grain [J]; pairs split half-half."""
        i = wp.tid()
        xi = position[i]
        ri = grains.radius[i]
        total = hi(0.0)
        for k in range(neighbour_count[row, i]):
            j = entry(neighbours, row, i, k)
            rj = grains.radius[j]
            overlap = hi(ri + rj) - wp.length(position[j] - xi)
            if overlap > hi(0.0):
                r_eff = hi(ri * rj / (ri + rj))
                e_star = hi(grains.pair[grains.material[i] * grains.material_count + grains.material[j], 0])
                total += hi(0.5 * 8.0 / 15.0) * e_star * wp.sqrt(r_eff) * wp.pow(overlap, hi(2.5))
        first_wall = (grains.order[i] // grains.world_size) * walls.per_world
        for b in range(first_wall, first_wall + walls.per_world):
            overlap, n = boundary_contact(walls.kind[b], walls.geometry, b, xi - walls.displacement[b], hi(ri))
            if overlap > hi(0.0):
                e_star = hi(grains.pair[grains.material[i] * grains.material_count + walls.material[b], 0])
                total += hi(8.0 / 15.0) * e_star * wp.sqrt(hi(ri)) * wp.pow(overlap, hi(2.5))
        energy_out[i] = total

    @wp.func
    def partner_column(key: int, wall_count: int, walls_per_world: int, bodies_per_world: int):
        """(world, column) of rigid partner `key` (every world's walls, then every world's wheels):
        its world and its place among that world's walls, then wheels."""
        world = key // wp.max(walls_per_world, 1)
        column = key - world * walls_per_world
        if key >= wall_count:
            world = (key - wall_count) // wp.max(bodies_per_world, 1)
            column = walls_per_world + key - wall_count - world * bodies_per_world
        return wp.vec2i(world, column)

    @kernel
    def wrench_partial(
        slot: wp.array(dtype=wp.int32),
        rigid_key: wp.array2d(dtype=wp.int32),
        rigid_count: wp.array(dtype=wp.int32),
        reaction_force: wp.array2d(dtype=vec_hi),
        reaction_torque: wp.array2d(dtype=vec_hi),
        world_size: int,
        rows_per_world: int,
        walls_per_world: int,
        bodies_per_world: int,
        wall_count: int,
        # outputs
        moments_out: wp.array2d(dtype=vec_hi),
        contacts_out: wp.array2d(dtype=wp.int32),
    ):
        """The tree's leaves (soil.reduction): per LEAF model indices of one world, the reactions on
        each of the world's partners (column k: its walls, then its wheels), summed in model-index
        order. moments_out[c, k]: force [N]; moments_out[c, partners + k]: torque [N m]."""
        c = wp.tid()
        partners = walls_per_world + bodies_per_world
        for k in range(partners):
            moments_out[c, k] = vec_hi()
            moments_out[c, partners + k] = vec_hi()
            contacts_out[c, k] = 0
        span = leaf_span(c, rows_per_world, world_size)
        for p in range(span[0], span[1]):
            i = slot[p]
            for s in range(wp.min(rigid_count[i], slots(rigid_key))):
                k = partner_column(at(rigid_key, i, s), wall_count, walls_per_world, bodies_per_world)[1]
                moments_out[c, k] = moments_out[c, k] + at(reaction_force, i, s)
                moments_out[c, partners + k] = moments_out[c, partners + k] + at(reaction_torque, i, s)
                contacts_out[c, k] = contacts_out[c, k] + 1

    @kernel
    def wrench_total(
        moments_in: wp.array2d(dtype=vec_hi),
        contacts_in: wp.array2d(dtype=wp.int32),
        rows_per_world: int,
        wall_reported: wp.array(dtype=wp.int32),
        walls_per_world: int,
        bodies_per_world: int,
        # outputs
        wall_force_out: wp.array(dtype=vec_hi),
        wall_torque_out: wp.array(dtype=vec_hi),
        wall_contact_out: wp.array(dtype=wp.int32),
        body_force_out: wp.array(dtype=vec_hi),
        body_torque_out: wp.array(dtype=vec_hi),
        body_contact_out: wp.array(dtype=wp.int32),
    ):
        """Total of rigid partner `key` (walls first, then wheels) over its world's last rows of the
        tree, in order; walls built with report=False read zero."""
        key = wp.tid()
        wall_count = wall_reported.shape[0]
        partners = walls_per_world + bodies_per_world
        place = partner_column(key, wall_count, walls_per_world, bodies_per_world)
        world = place[0]
        k = place[1]
        summed = True
        if key < wall_count:
            summed = wall_reported[key] >= 0
        total_force = vec_hi()
        total_torque = vec_hi()
        contacts = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        if summed:
            for r in range(world * rows_per_world, world * rows_per_world + rows_per_world):
                total_force = total_force + moments_in[r, k]
                total_torque = total_torque + moments_in[r, partners + k]
                contacts += contacts_in[r, k]
        if key < wall_count:
            wall_force_out[key] = total_force
            wall_torque_out[key] = total_torque
            wall_contact_out[key] = contacts
        else:
            body_force_out[key - wall_count] = total_force
            body_torque_out[key - wall_count] = total_torque
            body_contact_out[key - wall_count] = contacts

    return dict(
        Grains=Grains,
        Walls=Walls,
        Bodies=Bodies,
        History=History,
        grain_contacts=grain_contacts,
        rigid_contacts=rigid_contacts,
        elastic_energy=elastic_energy,
        wrench_partial=wrench_partial,
        wrench_total=wrench_total,
    )


class ContactSolver:
    """Evaluates the contact law for every grain at a state's positions, through the neighbour list.

    One per Simulation: it owns the neighbour list (soil.neighbours), the per-grain reactions
    on rigid partners (shape (particle_count, rigid slots)) and their chunk sums.
    """

    def __init__(self, model: SoilModel, neighbours: NeighbourList, status: wp.array):
        self.model = model
        prec = model.precision
        self.kernels = contact_kernels(prec.hi, prec.mid, prec.lo, model.law, model.slot_major)
        self.neighbours = neighbours
        self.status = status
        """The step status array (soil.status), shared with the Simulation."""
        device = model.device
        self._partners = model.boundary_count + model.body_count
        width = model.walls_per_world + model.bodies_per_world
        self._moments = WorldTree(model.world_count, model.world_size, 2 * width, prec.vec_hi, device)
        """Force [N] (columns 0 .. width - 1) and torque [N m] on each of a world's partners."""
        self._contacts = WorldTree(model.world_count, model.world_size, width, wp.int32, device)
        """Grains touching each of a world's partners."""
        self._reaction_force = self._reaction_torque = None
        self._torque_sum = wp.zeros(model.particle_count, dtype=prec.vec_hi, device=device)
        """Each grain's torque from its grain contacts [N m], shape (particle_count,), in `hi`:
        grain_contacts' partial sum, which rigid_contacts finishes (stored rounded to `mid`)."""
        self._wall_reported = (
            model.boundary_column
            if model.boundary_column is not None
            else wp.zeros(model.boundary_count, dtype=wp.int32, device=device)
        )
        self.evaluations = 0
        """Number of force evaluations so far (the cost unit of integrators)."""

    def reserve(self, rigid_capacity: int):
        """The per-grain reaction scratch, sized for `rigid_capacity` slots (allocated here,
        before a step is captured)."""
        n = self.model.particle_count
        shape = (rigid_capacity, n) if self.model.slot_major else (n, rigid_capacity)
        if self._reaction_force is None or self._reaction_force.shape != shape:
            self._reaction_force = wp.zeros(shape, dtype=self.model.precision.vec_hi, device=self.model.device)
            self._reaction_torque = wp.zeros(shape, dtype=self.model.precision.vec_hi, device=self.model.device)
        return self._reaction_force, self._reaction_torque

    def device_arrays(self) -> list:
        """The scratch arrays a captured step uses (a graph stays valid while they do)."""
        return [
            self._reaction_force,
            self._reaction_torque,
            self._torque_sum,
            *self._moments.levels,
            *self._contacts.levels,
            *self.neighbours.device_arrays(),
        ]

    def bytes_per_grain(self) -> float:
        """Device memory of the solver's scratch per grain [B]."""
        n = max(self.model.particle_count, 1)
        scratch = self._moments.capacity + self._contacts.capacity + self._torque_sum.capacity
        if self._reaction_force is not None:
            scratch += self._reaction_force.capacity + self._reaction_torque.capacity
        return scratch / n

    # -- argument bundles ------------------------------------------------------------------
    def grains(self, state: SoilState):
        layout = state.layout
        bundle = self.kernels.Grains()
        bundle.order, bundle.radius, bundle.mass = layout.order, layout.radius, layout.mass
        bundle.inv_mass, bundle.material = layout.inv_mass, layout.material
        bundle.pair, bundle.material_count = self.model.pair, self.model.material_count
        bundle.world_size = max(self.model.world_size, 1)
        return bundle

    def walls(self, state: SoilState):
        model = self.model
        bundle = self.kernels.Walls()
        bundle.kind, bundle.geometry, bundle.material = (
            model.boundary_kind,
            model.boundary_geometry,
            model.boundary_material,
        )
        bundle.displacement, bundle.velocity = state.boundary_displacement, state.boundary_velocity
        bundle.per_world = model.walls_per_world
        return bundle

    def bodies(self, state: SoilState):
        model = self.model
        bundle = self.kernels.Bodies()
        bundle.kind, bundle.shape, bundle.mesh, bundle.material = (
            model.body_kind,
            model.body_shape,
            model.body_mesh,
            model.body_material,
        )
        bundle.mesh_points, bundle.mesh_indices = model.mesh_points, model.mesh_indices
        bundle.point_offset, bundle.index_offset = model.body_point_offset, model.body_index_offset
        bundle.position, bundle.rotation = state.body_position, state.body_rotation
        bundle.velocity, bundle.angular_velocity = state.body_velocity, state.body_angular_velocity
        bundle.posed = state.body_posed
        bundle.per_world = model.bodies_per_world
        return bundle

    def history(self, state: SoilState):
        bundle = self.kernels.History()
        bundle.touching, bundle.tangential, bundle.rolling = (
            state.pair_touching,
            state.pair_tangential,
            state.pair_rolling,
        )
        bundle.rigid_key, bundle.rigid_count = state.rigid_key, state.rigid_count
        bundle.rigid_tangential, bundle.rigid_rolling = state.rigid_tangential, state.rigid_rolling
        return bundle

    # -- evaluation --------------------------------------------------------------------------
    def compute(self, state_in: SoilState, state_out: SoilState, control: SoilControl, dt: wp.array) -> None:
        """Forces at state_out's positions/velocities (and boundary positions/velocities); history
        read from state_in, written to state_out (the neighbour list is checked and, when a grain
        has moved too far, rebuilt first). Then the wrenches on walls and wheels and the loaded
        walls' accelerations (soil.boundaries) of state_out. No host read: capturable.

        state_in and state_out must be different objects (history is double-buffered).
        """
        model = self.model
        self.neighbours.update(state_in, state_out, self.status)
        reaction_force, reaction_torque = self.reserve(state_out.rigid_capacity)
        layout = state_out.layout
        grains, history_in, history_out = self.grains(state_out), self.history(state_in), self.history(state_out)
        wp.launch(
            self.kernels.grain_contacts,
            dim=model.particle_count,
            inputs=[
                state_out.position,
                state_out.velocity,
                state_out.angular_velocity,
                grains,
                layout.neighbours,
                layout.neighbour_count,
                state_out.list_index,
                self.neighbours.rebuilt,
                history_in,
                control.external_force,
                int(control.external_force_used),
                dt,
                model.world_size,
            ],
            outputs=[state_out.force, self._torque_sum, state_out.contact_count, history_out],
            device=model.device,
            block_dim=CONTACT_BLOCK_DIM,
        )
        wp.launch(
            self.kernels.rigid_contacts,
            dim=model.particle_count,
            inputs=[
                state_out.position,
                state_out.velocity,
                state_out.angular_velocity,
                grains,
                self.walls(state_out),
                self.bodies(state_out),
                history_in,
                dt,
                model.world_size,
                self._torque_sum,
            ],
            outputs=[
                state_out.force,
                state_out.torque,
                state_out.contact_count,
                history_out,
                reaction_force,
                reaction_torque,
                self.status,
            ],
            device=model.device,
            block_dim=CONTACT_BLOCK_DIM,
        )
        if self._partners:
            self._sum(state_out, reaction_force, reaction_torque)
        if model.boundary_count:
            update_acceleration(model, state_out, control)
        self.evaluations += 1

    def _sum(self, state: SoilState, reaction_force, reaction_torque) -> None:
        """Wall and wheel totals: a fixed tree over each world's grains (soil.reduction)."""
        model = self.model
        moments, contacts = self._moments, self._contacts
        wp.launch(
            self.kernels.wrench_partial,
            dim=moments.leaves.shape[0],
            inputs=[
                state.layout.slot,
                state.rigid_key,
                state.rigid_count,
                reaction_force,
                reaction_torque,
                model.world_size,
                moments.rows[0],
                model.walls_per_world,
                model.bodies_per_world,
                model.boundary_count,
            ],
            outputs=[moments.leaves, contacts.leaves],
            device=model.device,
            block_dim=CONTACT_BLOCK_DIM,
        )
        moments.fold(summed_columns=moments.leaves.shape[1])
        contacts.fold(summed_columns=contacts.leaves.shape[1])
        wp.launch(
            self.kernels.wrench_total,
            dim=self._partners,
            inputs=[
                moments.last,
                contacts.last,
                moments.last_rows,
                self._wall_reported,
                model.walls_per_world,
                model.bodies_per_world,
            ],
            outputs=[
                state.boundary_force,
                state.boundary_torque,
                state.boundary_contacts,
                state.body_force,
                state.body_torque,
                state.body_contacts,
            ],
            device=model.device,
            block_dim=CONTACT_BLOCK_DIM,
        )

    def current_list(self, state: SoilState) -> int:
        """Index of a neighbour list valid for `state`'s positions (host read): its own, or the
        other one built afresh when a grain has moved too far (the state is not changed)."""
        row = int(state.list_index.numpy()[0])
        if not self.neighbours.stale(state):
            return row
        self.neighbours.build_other(state, self.status)
        return 1 - row

    def elastic_energy(self, state: SoilState) -> float:
        """Hertz strain energy stored in all grain-grain and grain-wall contacts [J]."""
        model = self.model
        row = self.current_list(state)
        energy = wp.zeros(model.particle_count, dtype=model.precision.hi, device=model.device)
        layout = state.layout
        wp.launch(
            self.kernels.elastic_energy,
            dim=model.particle_count,
            inputs=[
                state.position,
                self.grains(state),
                self.walls(state),
                layout.neighbours,
                layout.neighbour_count,
                row,
            ],
            outputs=[energy],
            device=model.device,
            block_dim=CONTACT_BLOCK_DIM,
        )
        per_grain = np.empty(model.particle_count)
        per_grain[layout.order.numpy()] = energy.numpy()
        return float(np.sum(per_grain, dtype=np.float64))
