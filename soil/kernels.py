"""Warp kernels of the soil: contact forces and time integration.

One generic set of kernels serves every precision: `make_kernels(hi, lo, law)` closes
over the types and the contact-law switches and is cached per combination. Kernel
parameters come as inputs first, then outputs (suffix _out).

Particle-particle forces are gathered: each particle sums the forces of its own
contacts, in its own thread, with no atomics. Both particles of a pair evaluate the
same contact with mirrored inputs and keep their own (mirrored) history. The sums are
therefore independent of thread scheduling and runs repeat bit for bit.

Boundaries (planes, boxes) translate: a boundary's geometry row is its initial
geometry, and the state carries its displacement and velocity (soil.boundaries moves
them on the device). A wall displaced by d meets a grain at x as the initial wall
meets x - d. The reaction of every grain-wall and grain-body contact is written per
particle into a scratch column and summed per wall/body in a fixed order
(`wrench_partial`, `wrench_total`): no atomics, so the totals repeat bit for bit.
"""


import warp as wp

from .contact import ContactLaw, make_contact_law

BOUNDARY_PLANE = 0
"""Half-space: geometry row (point xyz, unit normal xyz); particles live on the normal's side.
Its torque is reported about the point."""
BOUNDARY_BOX = 1
"""Solid axis-aligned box: geometry row (lower corner xyz, upper corner xyz); particles stay outside.
Its torque is reported about its centre."""

BODY_WHEEL = 0
"""Parametric grousered wheel: shape row (radius, half width, grousers, grouser height, thickness, bounding radius)."""
BODY_MESH = 1
"""Closed triangle mesh: shape row (0, 0, 0, 0, 0, bounding radius)."""

_cache: dict = {}


def make_kernels(hi, lo, law: ContactLaw):
    """The soil kernels for precision types (hi, lo) and the contact-law switches."""
    key = (hi, lo, law)
    if key in _cache:
        return _cache[key]
    vec_hi = wp.types.vector(3, hi)
    mat_hi = wp.types.matrix((3, 3), hi)
    contact_law, _ = make_contact_law(hi, lo, law)

    @wp.func
    def boundary_contact(kind: int, geometry: wp.array2d(dtype=hi), b: int, x: vec_hi, radius: hi):
        """Overlap [m] and unit normal (from the particle towards the boundary)."""
        if kind == BOUNDARY_PLANE:
            point = vec_hi(geometry[b, 0], geometry[b, 1], geometry[b, 2])
            outward = vec_hi(geometry[b, 3], geometry[b, 4], geometry[b, 5])
            return radius - wp.dot(x - point, outward), -outward
        lower = vec_hi(geometry[b, 0], geometry[b, 1], geometry[b, 2])
        upper = vec_hi(geometry[b, 3], geometry[b, 4], geometry[b, 5])
        closest = wp.min(wp.max(x, lower), upper)
        gap = x - closest
        distance = wp.length(gap)
        if distance > hi(0.0):
            return radius - distance, -gap / distance
        # centre inside the box: push out through the nearest face
        best = upper[0] - x[0]
        normal = vec_hi(hi(-1.0), hi(0.0), hi(0.0))
        for axis in range(3):
            to_upper = upper[axis] - x[axis]
            to_lower = x[axis] - lower[axis]
            if to_upper < best:
                best = to_upper
                normal = vec_hi()
                normal[axis] = hi(-1.0)
            if to_lower < best:
                best = to_lower
                normal = vec_hi()
                normal[axis] = hi(1.0)
        return radius + best, normal

    @wp.func
    def boundary_reference(kind: int, geometry: wp.array2d(dtype=hi), b: int):
        """Reference point of a boundary's torque [m], undisplaced: a plane's point, a box's centre."""
        if kind == BOUNDARY_PLANE:
            return vec_hi(geometry[b, 0], geometry[b, 1], geometry[b, 2])
        return hi(0.5) * vec_hi(geometry[b, 0] + geometry[b, 3], geometry[b, 1] + geometry[b, 4],
                                geometry[b, 2] + geometry[b, 5])

    @wp.func
    def find_history(partner: wp.array2d(dtype=wp.int32), count: wp.array(dtype=wp.int32), i: int, key: int):
        for k in range(count[i]):
            if partner[i, k] == key:
                return k
        return -1

    @wp.func
    def box_distance(q: vec_hi, half: vec_hi):
        """Signed distance of q from a centred box and the outward normal at the closest point."""
        d = vec_hi(wp.abs(q[0]) - half[0], wp.abs(q[1]) - half[1], wp.abs(q[2]) - half[2])
        if wp.max(d) > hi(0.0):
            gap = q - wp.min(wp.max(q, -half), half)
            distance = wp.length(gap)
            return distance, gap / distance
        axis = int(0)
        if d[1] > d[axis]:
            axis = 1
        if d[2] > d[axis]:
            axis = 2
        normal = vec_hi()
        normal[axis] = wp.sign(q[axis])
        return d[axis], normal

    @wp.func
    def wheel_distance(shape: wp.array2d(dtype=hi), b: int, p: vec_hi):
        """Signed distance [m] of p (wheel frame) from a grousered wheel, and the outward normal.

        The wheel is the union of a solid cylinder (axle = Y) and box-shaped grousers,
        so its signed distance is the minimum over the parts.
        """
        radius = shape[b, 0]
        half_width = shape[b, 1]
        grousers = int(shape[b, 2])
        rho = wp.sqrt(p[0] * p[0] + p[2] * p[2])
        radial = vec_hi(hi(0.0), hi(0.0), hi(1.0))
        if rho > hi(0.0):
            radial = vec_hi(p[0] / rho, hi(0.0), p[2] / rho)
        axial = vec_hi(hi(0.0), wp.sign(p[1]), hi(0.0))
        d_r = rho - radius
        d_y = wp.abs(p[1]) - half_width
        best = wp.max(d_r, d_y)
        normal = radial
        if d_y > d_r:
            normal = axial
        if d_r > hi(0.0) and d_y > hi(0.0):
            best = wp.sqrt(d_r * d_r + d_y * d_y)
            normal = (d_r * radial + d_y * axial) / best
        if grousers > 0:
            height = shape[b, 3]
            thickness = shape[b, 4]
            pitch = hi(2.0 * 3.141592653589793) / hi(grousers)
            nearest = int(wp.round(wp.atan2(p[0], p[2]) / pitch))
            # plates run from inside the rim (one thickness deep) to the tip
            inner = radius - thickness
            centre = hi(0.5) * (inner + radius + height)
            half = vec_hi(hi(0.5) * (radius + height - inner), hi(0.5) * thickness, half_width)
            for offset in range(-1, 2):
                theta = hi(nearest + offset) * pitch
                e_r = vec_hi(wp.sin(theta), hi(0.0), wp.cos(theta))
                e_t = vec_hi(wp.cos(theta), hi(0.0), -wp.sin(theta))
                q = vec_hi(wp.dot(p, e_r) - centre, wp.dot(p, e_t), p[1])
                distance, n_box = box_distance(q, half)
                if distance < best:
                    best = distance
                    normal = n_box[0] * e_r + n_box[1] * e_t + vec_hi(hi(0.0), n_box[2], hi(0.0))
        return best, normal

    @wp.func
    def closest_on_triangle(p: vec_hi, a: vec_hi, b: vec_hi, c: vec_hi):
        """Closest point to p on triangle abc (Ericson, Real-Time Collision Detection 5.1.5)."""
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = wp.dot(ab, ap)
        d2 = wp.dot(ac, ap)
        if d1 <= hi(0.0) and d2 <= hi(0.0):
            return a
        bp = p - b
        d3 = wp.dot(ab, bp)
        d4 = wp.dot(ac, bp)
        if d3 >= hi(0.0) and d4 <= d3:
            return b
        vc = d1 * d4 - d3 * d2
        if vc <= hi(0.0) and d1 >= hi(0.0) and d3 <= hi(0.0):
            return a + (d1 / (d1 - d3)) * ab
        cp = p - c
        d5 = wp.dot(ab, cp)
        d6 = wp.dot(ac, cp)
        if d6 >= hi(0.0) and d5 <= d6:
            return c
        vb = d5 * d2 - d1 * d6
        if vb <= hi(0.0) and d2 >= hi(0.0) and d6 <= hi(0.0):
            return a + (d2 / (d2 - d6)) * ac
        va = d3 * d6 - d5 * d4
        if va <= hi(0.0) and (d4 - d3) >= hi(0.0) and (d5 - d6) >= hi(0.0):
            return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b)
        denominator = hi(1.0) / (va + vb + vc)
        return a + ab * (vb * denominator) + ac * (vc * denominator)

    @wp.func
    def mesh_distance(mesh: wp.uint64, points: wp.array(dtype=vec_hi), indices: wp.array(dtype=wp.int32),
                      point_offset: int, index_offset: int, p: vec_hi, max_distance: hi):
        """Signed distance of p from a closed mesh and the outward normal; (max_distance, 0) if far.

        Warp's mesh query (float32) finds the closest triangle and the inside/outside
        sign; the closest point is then recomputed in `hi` from the triangle's `hi`
        vertices, so tiny overlaps stay resolved in double and mixed precision.
        """
        query = wp.mesh_query_point_sign_normal(mesh, wp.vec3(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2])),
                                                wp.float32(max_distance))
        if not query.result:
            return max_distance, vec_hi()
        base = index_offset + 3 * query.face
        a = points[point_offset + indices[base + 0]]
        b = points[point_offset + indices[base + 1]]
        c = points[point_offset + indices[base + 2]]
        gap = p - closest_on_triangle(p, a, b, c)
        distance = wp.length(gap)
        side = hi(query.sign)
        if distance > hi(0.0):
            return side * distance, side * gap / distance
        return hi(0.0), wp.normalize(wp.cross(b - a, c - a))

    @wp.kernel(module="unique")
    def contact_forces(
        grid: wp.uint64,
        x_in: wp.array(dtype=vec_hi),
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_hi),
        radius: wp.array(dtype=lo),
        mass: wp.array(dtype=lo),
        inv_mass: wp.array(dtype=lo),
        material: wp.array(dtype=wp.int32),
        pair: wp.array2d(dtype=lo),
        material_count: int,
        boundary_kind: wp.array(dtype=wp.int32),
        boundary_geometry: wp.array2d(dtype=hi),
        boundary_material: wp.array(dtype=wp.int32),
        boundary_column: wp.array(dtype=wp.int32),
        boundary_displacement: wp.array(dtype=vec_hi),
        boundary_velocity: wp.array(dtype=vec_hi),
        external_force: wp.array(dtype=vec_hi),
        body_kind: wp.array(dtype=wp.int32),
        body_shape: wp.array2d(dtype=hi),
        body_mesh: wp.array(dtype=wp.uint64),
        body_material: wp.array(dtype=wp.int32),
        mesh_points: wp.array(dtype=vec_hi),
        mesh_indices: wp.array(dtype=wp.int32),
        body_point_offset: wp.array(dtype=wp.int32),
        body_index_offset: wp.array(dtype=wp.int32),
        body_position: wp.array(dtype=vec_hi),
        body_rotation: wp.array(dtype=mat_hi),
        body_velocity: wp.array(dtype=vec_hi),
        body_angular_velocity: wp.array(dtype=vec_hi),
        search_radius: hi,
        dt: hi,
        partner_in: wp.array2d(dtype=wp.int32),
        tangential_in: wp.array2d(dtype=vec_hi),
        rolling_in: wp.array2d(dtype=vec_hi),
        count_in: wp.array(dtype=wp.int32),
        # outputs
        force_out: wp.array(dtype=vec_hi),
        torque_out: wp.array(dtype=vec_hi),
        partner_out: wp.array2d(dtype=wp.int32),
        tangential_out: wp.array2d(dtype=vec_hi),
        rolling_out: wp.array2d(dtype=vec_hi),
        count_out: wp.array(dtype=wp.int32),
        overflow_out: wp.array(dtype=wp.int32),
        body_force_out: wp.array2d(dtype=vec_hi),
        body_torque_out: wp.array2d(dtype=vec_hi),
        body_contact_out: wp.array2d(dtype=wp.int32),
        boundary_force_out: wp.array2d(dtype=vec_hi),
        boundary_torque_out: wp.array2d(dtype=vec_hi),
        boundary_contact_out: wp.array2d(dtype=wp.int32),
    ):
        i = wp.tid()
        particle_count = x_in.shape[0]
        capacity = partner_out.shape[1]
        xi = x_in[i]
        ri = radius[i]
        total_force = external_force[i]
        total_torque = vec_hi()
        stored = int(0)

        neighbours = wp.hash_grid_query(grid, xi, search_radius)
        for j in neighbours:
            if j != i:
                gap = x_in[j] - xi
                distance = wp.length(gap)
                rj = radius[j]
                overlap = hi(ri + rj) - distance
                inv_sum = inv_mass[i] + inv_mass[j]
                if overlap > hi(0.0) and distance > hi(0.0) and inv_sum > lo(0.0):
                    n = gap / distance
                    lever_i = hi(ri) - hi(0.5) * overlap
                    lever_j = hi(rj) - hi(0.5) * overlap
                    v_rel = (v_in[i] + wp.cross(w_in[i], lever_i * n)) - (v_in[j] - wp.cross(w_in[j], lever_j * n))
                    slot = find_history(partner_in, count_in, i, j)
                    t_hist = vec_hi()
                    r_hist = vec_hi()
                    if slot >= 0:
                        t_hist = tangential_in[i, slot]
                        r_hist = rolling_in[i, slot]
                    row = material[i] * material_count + material[j]
                    f, m_roll, t_new, r_new = contact_law(
                        n, overlap, v_rel, w_in[i] - w_in[j], ri * rj / (ri + rj), lo(1.0) / inv_sum,
                        pair, row, t_hist, r_hist, dt)
                    total_force = total_force + f
                    total_torque = total_torque + wp.cross(lever_i * n, f) + m_roll
                    if stored < capacity:
                        partner_out[i, stored] = j
                        tangential_out[i, stored] = t_new
                        rolling_out[i, stored] = r_new
                        stored += 1
                    else:
                        overflow_out[0] = 1

        # walls: fixed grains do not touch them; reporting walls get this grain's reaction
        free = inv_mass[i] > lo(0.0)
        for b in range(boundary_kind.shape[0]):
            column = boundary_column[b]
            if column >= 0:
                boundary_force_out[i, column] = vec_hi()
                boundary_torque_out[i, column] = vec_hi()
                boundary_contact_out[i, column] = 0
            if free:
                shift = boundary_displacement[b]
                overlap, n = boundary_contact(boundary_kind[b], boundary_geometry, b, xi - shift, hi(ri))
                if overlap > hi(0.0):
                    lever_i = hi(ri) - overlap
                    # a translating wall: its contact point moves with the wall's velocity
                    v_rel = v_in[i] + wp.cross(w_in[i], lever_i * n) - boundary_velocity[b]
                    key = particle_count + b
                    slot = find_history(partner_in, count_in, i, key)
                    t_hist = vec_hi()
                    r_hist = vec_hi()
                    if slot >= 0:
                        t_hist = tangential_in[i, slot]
                        r_hist = rolling_in[i, slot]
                    row = material[i] * material_count + boundary_material[b]
                    f, m_roll, t_new, r_new = contact_law(
                        n, overlap, v_rel, w_in[i], ri, lo(1.0) / inv_mass[i], pair, row, t_hist, r_hist, dt)
                    total_force = total_force + f
                    total_torque = total_torque + wp.cross(lever_i * n, f) + m_roll
                    if column >= 0:
                        reference = boundary_reference(boundary_kind[b], boundary_geometry, b) + shift
                        boundary_force_out[i, column] = -f
                        boundary_torque_out[i, column] = wp.cross(xi + lever_i * n - reference, -f) - m_roll
                        boundary_contact_out[i, column] = 1
                    if stored < capacity:
                        partner_out[i, stored] = key
                        tangential_out[i, stored] = t_new
                        rolling_out[i, stored] = r_new
                        stored += 1
                    else:
                        overflow_out[0] = 1

        # wheels and other rigid bodies moved by the control
        for b in range(body_kind.shape[0]):
            body_force_out[i, b] = vec_hi()
            body_torque_out[i, b] = vec_hi()
            body_contact_out[i, b] = 0
            hub = body_position[b]
            rotation = body_rotation[b]
            local = wp.transpose(rotation) * (xi - hub)
            reach = body_shape[b, 5] + hi(ri)
            if wp.length(local) < reach:  # fixed grains too: they push on the wheel
                distance = reach
                n_out = vec_hi()
                if body_kind[b] == BODY_WHEEL:
                    distance, n_out = wheel_distance(body_shape, b, local)
                else:
                    distance, n_out = mesh_distance(body_mesh[b], mesh_points, mesh_indices, body_point_offset[b],
                                                    body_index_offset[b], local, hi(2.0) * reach)
                overlap = hi(ri) - distance
                if overlap > hi(0.0):
                    n = -(rotation * n_out)  # from the particle towards the body
                    lever_i = hi(ri) - overlap
                    contact_point = xi + lever_i * n
                    v_body = body_velocity[b] + wp.cross(body_angular_velocity[b], contact_point - hub)
                    v_rel = v_in[i] + wp.cross(w_in[i], lever_i * n) - v_body
                    key = particle_count + boundary_kind.shape[0] + b
                    slot = find_history(partner_in, count_in, i, key)
                    t_hist = vec_hi()
                    r_hist = vec_hi()
                    if slot >= 0:
                        t_hist = tangential_in[i, slot]
                        r_hist = rolling_in[i, slot]
                    row = material[i] * material_count + body_material[b]
                    f, m_roll, t_new, r_new = contact_law(
                        n, overlap, v_rel, w_in[i] - body_angular_velocity[b], ri, mass[i],
                        pair, row, t_hist, r_hist, dt)
                    total_force = total_force + f
                    total_torque = total_torque + wp.cross(lever_i * n, f) + m_roll
                    body_force_out[i, b] = -f
                    body_torque_out[i, b] = wp.cross(contact_point - hub, -f) - m_roll
                    body_contact_out[i, b] = 1
                    if stored < capacity:
                        partner_out[i, stored] = key
                        tangential_out[i, stored] = t_new
                        rolling_out[i, stored] = r_new
                        stored += 1
                    else:
                        overflow_out[0] = 1

        force_out[i] = total_force
        torque_out[i] = total_torque
        count_out[i] = stored

    @wp.func
    def acceleration_of(force: vec_hi, inv_mass: lo, gravity: vec_hi):
        """Acceleration [m/s^2] of a grain under `force`; fixed grains (inv_mass 0) feel no gravity."""
        inv_m = hi(inv_mass)
        acceleration = force * inv_m
        if inv_m > hi(0.0):
            acceleration = acceleration + gravity
        return acceleration

    @wp.kernel(module="unique")
    def kick_drift(
        x_in: wp.array(dtype=vec_hi),
        v_in: wp.array(dtype=vec_hi),
        w_in: wp.array(dtype=vec_hi),
        force_in: wp.array(dtype=vec_hi),
        torque_in: wp.array(dtype=vec_hi),
        inv_mass: wp.array(dtype=lo),
        inv_inertia: wp.array(dtype=lo),
        gravity: vec_hi,
        dt: hi,
        # outputs
        x_out: wp.array(dtype=vec_hi),
        v_out: wp.array(dtype=vec_hi),
        w_out: wp.array(dtype=vec_hi),
    ):
        """Velocity Verlet, first half: half kick with the old forces, then a full drift."""
        i = wp.tid()
        v_half = v_in[i] + hi(0.5) * dt * acceleration_of(force_in[i], inv_mass[i], gravity)
        v_out[i] = v_half
        w_out[i] = w_in[i] + hi(0.5) * dt * hi(inv_inertia[i]) * torque_in[i]
        x_out[i] = x_in[i] + dt * v_half

    @wp.kernel(module="unique")
    def kick(
        force_in: wp.array(dtype=vec_hi),
        torque_in: wp.array(dtype=vec_hi),
        inv_mass: wp.array(dtype=lo),
        inv_inertia: wp.array(dtype=lo),
        gravity: vec_hi,
        dt: hi,
        # in/out
        v_io: wp.array(dtype=vec_hi),
        w_io: wp.array(dtype=vec_hi),
    ):
        """Velocity Verlet, second half kick with the new forces."""
        i = wp.tid()
        v_io[i] = v_io[i] + hi(0.5) * dt * acceleration_of(force_in[i], inv_mass[i], gravity)
        w_io[i] = w_io[i] + hi(0.5) * dt * hi(inv_inertia[i]) * torque_in[i]

    @wp.kernel(module="unique")
    def elastic_energy(
        grid: wp.uint64,
        x_in: wp.array(dtype=vec_hi),
        radius: wp.array(dtype=lo),
        material: wp.array(dtype=wp.int32),
        pair: wp.array2d(dtype=lo),
        material_count: int,
        boundary_kind: wp.array(dtype=wp.int32),
        boundary_geometry: wp.array2d(dtype=hi),
        boundary_material: wp.array(dtype=wp.int32),
        boundary_displacement: wp.array(dtype=vec_hi),
        search_radius: hi,
        # outputs
        energy_out: wp.array(dtype=hi),
    ):
        """Hertz strain energy (8/15) E* sqrt(R*) delta^2.5 per particle [J]; pairs split half-half."""
        i = wp.tid()
        xi = x_in[i]
        ri = radius[i]
        total = hi(0.0)
        for j in wp.hash_grid_query(grid, xi, search_radius):
            if j != i:
                overlap = hi(ri + radius[j]) - wp.length(x_in[j] - xi)
                if overlap > hi(0.0):
                    r_eff = hi(ri * radius[j] / (ri + radius[j]))
                    e_star = hi(pair[material[i] * material_count + material[j], 0])
                    total += hi(0.5 * 8.0 / 15.0) * e_star * wp.sqrt(r_eff) * wp.pow(overlap, hi(2.5))
        for b in range(boundary_kind.shape[0]):
            overlap, n = boundary_contact(boundary_kind[b], boundary_geometry, b, xi - boundary_displacement[b], hi(ri))
            if overlap > hi(0.0):
                e_star = hi(pair[material[i] * material_count + boundary_material[b], 0])
                total += hi(8.0 / 15.0) * e_star * wp.sqrt(hi(ri)) * wp.pow(overlap, hi(2.5))
        energy_out[i] = total

    @wp.kernel(module="unique")
    def wrench_partial(
        force: wp.array2d(dtype=vec_hi),
        torque: wp.array2d(dtype=vec_hi),
        contact: wp.array2d(dtype=wp.int32),
        chunk: int,
        # outputs
        force_out: wp.array2d(dtype=vec_hi),
        torque_out: wp.array2d(dtype=vec_hi),
        contact_out: wp.array2d(dtype=wp.int32),
    ):
        """Sum each scratch column's per-particle wrench over fixed chunks of particles, in
        index order: the sum does not depend on thread scheduling (deterministic)."""
        c, k = wp.tid()
        start = c * chunk
        stop = wp.min(start + chunk, force.shape[0])
        total_force = vec_hi()
        total_torque = vec_hi()
        contacts = int(0)
        for i in range(start, stop):
            total_force = total_force + force[i, k]
            total_torque = total_torque + torque[i, k]
            contacts += contact[i, k]
        force_out[c, k] = total_force
        torque_out[c, k] = total_torque
        contact_out[c, k] = contacts

    @wp.kernel(module="unique")
    def wrench_total(
        force_in: wp.array2d(dtype=vec_hi),
        torque_in: wp.array2d(dtype=vec_hi),
        contact_in: wp.array2d(dtype=wp.int32),
        column: wp.array(dtype=wp.int32),
        # outputs
        force_out: wp.array(dtype=vec_hi),
        torque_out: wp.array(dtype=vec_hi),
        contact_out: wp.array(dtype=wp.int32),
    ):
        """Total of the chunk sums for item b from its scratch column (-1: not summed, zero)."""
        b = wp.tid()
        k = column[b]
        total_force = vec_hi()
        total_torque = vec_hi()
        contacts = int(0)
        if k >= 0:
            for c in range(force_in.shape[0]):
                total_force = total_force + force_in[c, k]
                total_torque = total_torque + torque_in[c, k]
                contacts += contact_in[c, k]
        force_out[b] = total_force
        torque_out[b] = total_torque
        contact_out[b] = contacts

    kernels = dict(
        wrench_partial=wrench_partial,
        wrench_total=wrench_total,
        contact_forces=contact_forces,
        kick_drift=kick_drift,
        kick=kick,
        elastic_energy=elastic_energy,
        contact_law=contact_law,
        boundary_contact=boundary_contact,
        boundary_reference=boundary_reference,
        acceleration_of=acceleration_of,
        find_history=find_history,
    )
    _cache[key] = kernels
    return kernels
