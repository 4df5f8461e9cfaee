# mypy: ignore-errors
# (Warp kernel code: annotated with Warp's types, which mypy cannot read; the host code is in terrain.py)
"""The SCM's kernels (see soil.scm): one generic source per precision type `hi`, launched by
soil.scm.terrain.ScmTerrain. No atomics; each sum over nodes runs in a fixed order."""

import warp as wp

from ..control import path_kernels
from ..precision import kernel_factory, kernel_module, soil_kernel

MIN_NORMAL_Z = 0.2
"""Smallest |n_z| of the wheel surface used for a node's contact area h^2 / |n_z|: a near-vertical
face (a grouser's flank) above a node would otherwise get an unbounded area."""

GROUSER_WHEEL = 0
"""Wheel kind of a GrouserWheel (its soil.sdf shape row); MESH_WHEEL: a closed mesh."""
MESH_WHEEL = 1


@kernel_factory
def scm_kernels(hi):
    """The SCM kernels for the precision type `hi`."""
    kernel = soil_kernel(kernel_module("scm", hi))
    vec_hi = wp.types.vector(3, hi)
    vec4_hi = wp.types.vector(4, hi)
    mat_hi = wp.types.matrix((3, 3), hi)
    huge = 1.0e30

    @wp.struct
    class Soil:
        """The soil's parameters and the grid's layout; `box`: the most nodes along x or y of a wheel's
        box (the launch size of the kernels that work the boxes)."""

        k_c: hi
        k_phi: hi
        n: hi
        cohesion: hi
        tan_phi: hi
        janosi_k: hi
        elastic_stiffness: hi
        damping: hi
        spacing: hi
        surface: hi
        nx: int
        ny: int
        box: int

    @wp.struct
    class Wheels:
        """Shapes (soil.sdf's rows) [m], meshes, the cylinder about each axle that holds the wheel (radius,
        half width) [m] and the current poses and velocities, shape (wheels,): kind, mesh and the mesh indices
        and offsets [-]; mesh_points [m]; position [m], rotation body -> world [-], velocity [m/s],
        angular_velocity [rad/s]."""

        kind: wp.array(dtype=wp.int32)
        shape: wp.array2d(dtype=hi)
        mesh: wp.array(dtype=wp.uint64)
        mesh_points: wp.array(dtype=vec_hi)
        mesh_indices: wp.array(dtype=wp.int32)
        point_offset: wp.array(dtype=wp.int32)
        index_offset: wp.array(dtype=wp.int32)
        cylinder: wp.array2d(dtype=hi)
        position: wp.array(dtype=vec_hi)
        rotation: wp.array(dtype=mat_hi)
        velocity: wp.array(dtype=vec_hi)
        angular_velocity: wp.array(dtype=vec_hi)

    @wp.struct
    class Nodes:
        """Per-node state (kept) and the step's contact: `wheel` at every node (-1: none; written in the
        wheels' boxes, cleared where a box left), the other arrays rewritten, and valid, at the contact
        nodes only. Shape (node_count,): key_i, key_j, wheel, rim [-]; reference (undisturbed height),
        plastic (sinkage), shear (Janosi-Hanamoto displacement), hit (point), flow [m]; normal [-];
        pressure [Pa]; force [N]; torque about the hub [N m]."""

        key_i: wp.array(dtype=wp.int32)
        key_j: wp.array(dtype=wp.int32)
        reference: wp.array(dtype=hi)
        plastic: wp.array(dtype=hi)
        shear: wp.array(dtype=hi)
        wheel: wp.array(dtype=wp.int32)
        rim: wp.array(dtype=wp.int32)
        hit: wp.array(dtype=vec_hi)
        normal: wp.array(dtype=vec_hi)
        pressure: wp.array(dtype=hi)
        flow: wp.array(dtype=hi)
        force: wp.array(dtype=vec_hi)
        torque: wp.array(dtype=vec_hi)

    @wp.func
    def slab(o: hi, d: hi, low: hi, high: hi, t_in: hi, t_out: hi):
        """Clip the ray interval (t_in, t_out) to low <= o + t d <= high; also whether the entry moved."""
        if wp.abs(d) < hi(1.0e-12):
            if o < low or o > high:
                return hi(1.0), hi(-1.0), False
            return t_in, t_out, False
        t0 = (low - o) / d
        t1 = (high - o) / d
        if t0 > t1:
            swap = t0
            t0 = t1
            t1 = swap
        entered = False
        if t0 > t_in:
            t_in = t0
            entered = True
        t_out = wp.min(t_out, t1)
        return t_in, t_out, entered

    @wp.func
    def cylinder_interval(o: vec_hi, d: vec_hi, radius: hi, half_width: hi):
        """The interval of t where o + t d (wheel frame) is inside the solid cylinder (axle Y, |y| <= half
        width): (t_in, t_out; empty if t_in > t_out) and whether it enters through a side face."""
        a = d[0] * d[0] + d[2] * d[2]
        b = hi(2.0) * (o[0] * d[0] + o[2] * d[2])
        c = o[0] * o[0] + o[2] * o[2] - radius * radius
        t_in = hi(-huge)
        t_out = hi(huge)
        if a > hi(1.0e-12):
            disc = b * b - hi(4.0) * a * c
            if disc >= hi(0.0):
                root = wp.sqrt(disc)
                t_in = (-b - root) / (hi(2.0) * a)
                t_out = (-b + root) / (hi(2.0) * a)
            else:
                t_out = hi(-huge)
        elif c > hi(0.0):
            t_out = hi(-huge)
        t_in, t_out, side_entry = slab(o[1], d[1], -half_width, half_width, t_in, t_out)
        return t_in, t_out, side_entry

    @wp.func
    def grouser_wheel_ray(shape: wp.array2d(dtype=hi), w: int, o: vec_hi, d: vec_hi):
        """First hit t along o + t d (wheel frame, o outside the wheel) with a grousered wheel (the solid
        of soil.sdf wheel_distance: a cylinder and box grousers), and the outward normal; t = huge if none.

        Only the grousers that the ray can meet are tested: those at the angles (about the axle) that
        the ray sweeps between entering the cylinder over the grouser tips and meeting the rim."""
        radius = shape[w, 0]
        half_width = shape[w, 1]
        grousers = int(shape[w, 2])
        height = shape[w, 3]
        thickness = shape[w, 4]
        best = hi(huge)
        best_normal = vec_hi()
        outer = wp.sqrt((radius + height) * (radius + height) + hi(0.25) * thickness * thickness)
        a_in, a_out, a_side = cylinder_interval(o, d, outer, half_width)
        if a_in > a_out or a_out < hi(0.0):
            return best, best_normal  # the ray misses the cylinder that holds the whole wheel
        t_in, t_out, side_entry = cylinder_interval(o, d, radius, half_width)
        t_end = a_out
        if t_in <= t_out and t_in >= hi(0.0):
            best = t_in
            t_end = t_in
            p = o + t_in * d
            if side_entry:
                best_normal = vec_hi(hi(0.0), -wp.sign(d[1]), hi(0.0))
            else:
                best_normal = vec_hi(p[0], hi(0.0), p[2]) / radius
        if grousers > 0:
            pitch = hi(2.0 * 3.141592653589793) / hi(grousers)
            inner = radius - thickness
            centre = hi(0.5) * (inner + radius + height)
            half_r = hi(0.5) * (radius + height - inner)
            half_t = hi(0.5) * thickness
            # the swept angles: a grouser reaches less than half a pitch to each side of its angle
            p_a = o + wp.max(a_in, hi(0.0)) * d
            p_b = o + t_end * d
            angle = wp.atan2(p_a[0], p_a[2])
            span = wp.atan2(p_b[0], p_b[2]) - angle
            if span > hi(3.141592653589793):
                span -= hi(2.0 * 3.141592653589793)
            if span < hi(-3.141592653589793):
                span += hi(2.0 * 3.141592653589793)
            step = int(1)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
            if span < hi(0.0):
                step = -1
            count = int(wp.abs(span) / pitch) + 4
            first = int(wp.round(angle / pitch)) - step
            if count >= grousers:
                count = grousers
                first = 0
                step = 1
            for s in range(count):
                index = ((first + step * s) % grousers + grousers) % grousers  # one angle per grouser
                theta = hi(index) * pitch
                e_r = vec_hi(wp.sin(theta), hi(0.0), wp.cos(theta))
                e_t = vec_hi(wp.cos(theta), hi(0.0), -wp.sin(theta))
                q = o - centre * e_r
                qr = wp.dot(q, e_r)
                qt = wp.dot(q, e_t)
                dr = wp.dot(d, e_r)
                dt = wp.dot(d, e_t)
                g_in = hi(-huge)
                g_out = hi(huge)
                g_in, g_out, enter_r = slab(qr, dr, -half_r, half_r, g_in, g_out)
                g_in, g_out, enter_t = slab(qt, dt, -half_t, half_t, g_in, g_out)
                g_in, g_out, enter_y = slab(o[1], d[1], -half_width, half_width, g_in, g_out)
                if g_in <= g_out and g_in >= hi(0.0) and g_in < best:
                    best = g_in
                    if enter_y:
                        best_normal = vec_hi(hi(0.0), -wp.sign(d[1]), hi(0.0))
                    elif enter_t:
                        best_normal = -wp.sign(dt) * e_t
                    else:
                        best_normal = -wp.sign(dr) * e_r
        return best, best_normal

    @wp.func
    def mesh_ray(wheels: Wheels, w: int, o: vec_hi, d: vec_hi, max_t: hi):
        """First hit t along o + t d (wheel frame) with a closed mesh and its outward normal; t = huge if
        none. Warp's query (float32) finds the triangle; t is recomputed in `hi` from its vertices."""
        query = wp.mesh_query_ray(
            wheels.mesh[w],
            wp.vec3(wp.float32(o[0]), wp.float32(o[1]), wp.float32(o[2])),
            wp.vec3(wp.float32(d[0]), wp.float32(d[1]), wp.float32(d[2])),
            wp.float32(max_t),
        )
        if not query.result:
            return hi(huge), vec_hi()
        base = wheels.index_offset[w] + 3 * query.face
        offset = wheels.point_offset[w]
        a = wheels.mesh_points[offset + wheels.mesh_indices[base + 0]]
        b = wheels.mesh_points[offset + wheels.mesh_indices[base + 1]]
        c = wheels.mesh_points[offset + wheels.mesh_indices[base + 2]]
        normal = wp.normalize(wp.cross(b - a, c - a))
        along = wp.dot(d, normal)
        t = hi(query.t)
        if wp.abs(along) > hi(1.0e-12):
            t = wp.dot(a - o, normal) / along
        return t, normal

    @wp.func
    def grid_index(slot: int, origin: int, count: int):
        """The grid index (I or J) that a slot holds while the window starts at `origin`."""
        return origin + ((slot - origin) % count + count) % count

    @wp.func
    def slot_of(i: int, j: int, soil: Soil):
        """The storage slot of grid node (I, J) (the ring buffer: (I mod nx, J mod ny))."""
        return ((i % soil.nx + soil.nx) % soil.nx) * soil.ny + ((j % soil.ny + soil.ny) % soil.ny)

    @wp.func
    def in_window(i: int, j: int, soil: Soil, origin: wp.array(dtype=wp.int32)):
        """Whether grid node (I, J) is in the window (it has a slot)."""
        return i >= origin[0] and i < origin[0] + soil.nx and j >= origin[1] and j < origin[1] + soil.ny

    @wp.func
    def first_box(i: int, j: int, boxes: wp.array2d(dtype=wp.int32), count: int):
        """The lowest of the first `count` wheels whose box holds grid node (I, J), -1 if none: where boxes
        overlap, one wheel's thread works a node (each node once per kernel)."""
        for w in range(count):
            a = i - boxes[w, 0]
            b = j - boxes[w, 1]
            if a >= 0 and a < boxes[w, 2] and b >= 0 and b < boxes[w, 3]:
                return w
        return -1

    @wp.func
    def box_slot(
        w: int, a: int, b: int, soil: Soil, origin: wp.array(dtype=wp.int32), boxes: wp.array2d(dtype=wp.int32)
    ):
        """Node (a, b) of wheel w's box: its slot and grid indices (I, J); slot -1 when the node is outside
        the box or the window, or another (lower) wheel's box works it."""
        i = boxes[w, 0] + a
        j = boxes[w, 1] + b
        k = int(-1)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        if a < boxes[w, 2] and b < boxes[w, 3] and in_window(i, j, soil, origin) and first_box(i, j, boxes, w) < 0:
            k = slot_of(i, j, soil)
        return k, i, j

    @wp.func
    def box_span(centre: hi, reach: hi, spacing: hi, most: int):
        """The first grid index and the count (at most `most`) of the nodes within reach of centre plus
        one spacing (a node beyond it is farther than a spacing from the wheel: no rounding reaches it)."""
        first = int(wp.floor((centre - reach) / spacing)) - 1
        last = int(wp.floor((centre + reach) / spacing)) + 1
        return first, wp.min(last - first + 1, most)

    @kernel
    def place_window(
        wheels: Wheels,
        follow: int,
        centre: wp.array(dtype=hi),
        soil: Soil,
        origin: wp.array(dtype=wp.int32),
        boxes: wp.array2d(dtype=wp.int32),
        boxes_before: wp.array2d(dtype=wp.int32),
    ):
        """The window's first node (I0, J0): centred on the wheels' mean hub (follow != 0) or on `centre`;
        each wheel's box (first node I, J, and its nodes along x, y): the nodes under the footprint of the
        cylinder that holds the wheel (radius r, half width w about its axle a: it reaches
        w |a_x| + r sqrt(1 - a_x^2) along x), the only nodes it can touch; the last step's in `boxes_before`."""
        cx = centre[0]
        cy = centre[1]
        count = wheels.position.shape[0]
        if follow != 0:
            sx = hi(0.0)
            sy = hi(0.0)
            for w in range(count):
                sx += wheels.position[w][0]
                sy += wheels.position[w][1]
            cx = sx / hi(count)
            cy = sy / hi(count)
        origin[0] = int(wp.floor(cx / soil.spacing)) - soil.nx // 2
        origin[1] = int(wp.floor(cy / soil.spacing)) - soil.ny // 2
        for w in range(count):
            for e in range(4):
                boxes_before[w, e] = boxes[w, e]
            axle = wheels.rotation[w] * vec_hi(hi(0.0), hi(1.0), hi(0.0))
            radius = wheels.cylinder[w, 0]
            half_width = wheels.cylinder[w, 1]
            reach_x = half_width * wp.abs(axle[0]) + radius * wp.sqrt(wp.max(hi(0.0), hi(1.0) - axle[0] * axle[0]))
            reach_y = half_width * wp.abs(axle[1]) + radius * wp.sqrt(wp.max(hi(0.0), hi(1.0) - axle[1] * axle[1]))
            hub = wheels.position[w]
            first_i, count_i = box_span(hub[0], reach_x, soil.spacing, soil.box)
            first_j, count_j = box_span(hub[1], reach_y, soil.spacing, soil.box)
            boxes[w, 0] = first_i
            boxes[w, 1] = first_j
            boxes[w, 2] = count_i
            boxes[w, 3] = count_j

    @wp.func
    def reset_slot(k: int, i: int, j: int, soil: Soil, nodes: Nodes):
        """Slot k to grid node (I, J) if a new node entered it: the undisturbed soil, no contact."""
        if nodes.key_i[k] != i or nodes.key_j[k] != j:
            nodes.key_i[k] = i
            nodes.key_j[k] = j
            nodes.reference[k] = soil.surface
            nodes.plastic[k] = hi(0.0)
            nodes.shear[k] = hi(0.0)
            nodes.wheel[k] = -1

    @kernel
    def enter_window(soil: Soil, origin: wp.array(dtype=wp.int32), nodes: Nodes):
        """Per node of the window: reset a slot that a new grid node entered (before the steps that read
        every node: bulldozing; otherwise a slot is reset when a wheel's box first reaches it)."""
        k = wp.tid()
        i = grid_index(k // soil.ny, origin[0], soil.nx)
        j = grid_index(k % soil.ny, origin[1], soil.ny)
        reset_slot(k, i, j, soil, nodes)

    @kernel
    def release(
        soil: Soil,
        origin: wp.array(dtype=wp.int32),
        boxes: wp.array2d(dtype=wp.int32),
        boxes_before: wp.array2d(dtype=wp.int32),
        nodes: Nodes,
    ):
        """Per node of the last step's boxes that no box holds now: no contact, no shear displacement (a
        node out of every box is out of every wheel's reach; its state stays as the wheel left it)."""
        w, a, b = wp.tid()
        count = boxes.shape[0]
        i = boxes_before[w, 0] + a
        j = boxes_before[w, 1] + b
        if a >= boxes_before[w, 2] or b >= boxes_before[w, 3] or first_box(i, j, boxes_before, w) >= 0:
            return  # outside the old box, or a lower wheel's old box holds it
        if in_window(i, j, soil, origin) and first_box(i, j, boxes, count) >= 0:
            return  # find_contacts works it
        k = slot_of(i, j, soil)
        if nodes.key_i[k] == i and nodes.key_j[k] == j:
            nodes.wheel[k] = -1
            nodes.shear[k] = hi(0.0)

    @kernel
    def find_contacts(
        wheels: Wheels,
        soil: Soil,
        origin: wp.array(dtype=wp.int32),
        boxes: wp.array2d(dtype=wp.int32),
        nodes: Nodes,
    ):
        """Per node of the wheels' boxes: reset a slot that a new grid node entered; cast the vertical ray
        onto the wheels and keep the lowest hit below the soil's plastic surface (wheel -1: no contact)."""
        box_w, a, b = wp.tid()
        k, i, j = box_slot(box_w, a, b, soil, origin, boxes)
        if k < 0:
            return
        reset_slot(k, i, j, soil, nodes)
        x = hi(i) * soil.spacing
        y = hi(j) * soil.spacing
        top = nodes.reference[k] - nodes.plastic[k]
        best_wheel = int(-1)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        best_z = top
        best_normal = vec_hi()
        up = vec_hi(hi(0.0), hi(0.0), hi(1.0))
        for w in range(wheels.position.shape[0]):
            hub = wheels.position[w]
            reach = wheels.shape[w, 5]
            dx = x - hub[0]
            dy = y - hub[1]
            bottom = hub[2] - reach - soil.spacing
            if dx * dx + dy * dy > reach * reach or bottom >= best_z:
                continue
            rotation = wheels.rotation[w]
            start = vec_hi(x, y, bottom)
            o = wp.transpose(rotation) * (start - hub)
            d = wp.transpose(rotation) * up
            t = hi(huge)
            n_local = vec_hi()
            if wheels.kind[w] == GROUSER_WHEEL:
                t, n_local = grouser_wheel_ray(wheels.shape, w, o, d)
            else:
                t, n_local = mesh_ray(wheels, w, o, d, best_z - bottom)
            z = bottom + t
            if z < best_z:
                best_z = z
                best_wheel = w
                best_normal = rotation * n_local
        nodes.wheel[k] = best_wheel
        if best_wheel >= 0:  # the step's other arrays are read at contact nodes only
            nodes.hit[k] = vec_hi(x, y, best_z)
            nodes.normal[k] = best_normal

    @wp.func
    def box_row(row: int, w: int, boxes: wp.array2d(dtype=wp.int32), soil: Soil):
        """Whether slot row `row` (I mod nx) holds a row of wheel w's box."""
        return grid_index(row, boxes[w, 0], soil.nx) - boxes[w, 0] < boxes[w, 2]

    @wp.func
    def box_columns(part: int, w: int, boxes: wp.array2d(dtype=wp.int32), soil: Soil):
        """Part 0 or 1 of the slot columns (J mod ny) of wheel w's box, [first, end), the parts in
        ascending order (a box across the ring buffer's seam has two, one of them empty otherwise)."""
        first = ((boxes[w, 1] % soil.ny) + soil.ny) % soil.ny
        end = first + boxes[w, 3]
        low = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        high = int(0)  # noqa: UP018
        if boxes[w, 3] >= soil.ny:
            if part == 0:
                high = soil.ny
        elif end <= soil.ny:
            if part == 0:
                low = first
                high = end
        elif part == 0:
            high = end - soil.ny
        else:
            low = first
            high = soil.ny
        return low, high

    @wp.func
    def chunk_box_slots(
        row: int, part: int, w: int, chunk_start: int, chunk_end: int, boxes: wp.array2d(dtype=wp.int32), soil: Soil
    ):
        """The slots [start, stop) of slot row `row`, part `part` (box_columns) of wheel w's box that lie
        in the chunk [chunk_start, chunk_end) of the storage order (empty where the row is not the box's)."""
        start = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        stop = int(0)  # noqa: UP018
        if box_row(row, w, boxes, soil):
            first, end = box_columns(part, w, boxes, soil)
            start = wp.max(chunk_start, row * soil.ny + first)
            stop = wp.min(chunk_end, row * soil.ny + end)
        return start, stop

    @kernel
    def patch_partial(
        wheels: Wheels,
        nodes: Nodes,
        soil: Soil,
        boxes: wp.array2d(dtype=wp.int32),
        node_count: int,
        chunk: int,
        low: wp.array2d(dtype=hi),
        high: wp.array2d(dtype=hi),
    ):
        """Per (wheel, chunk of nodes): the contact nodes' extents across and along the axle
        (min/max of the horizontal coordinates along the wheel's heading and its axle)."""
        w, c = wp.tid()
        axle = wheels.rotation[w] * vec_hi(hi(0.0), hi(1.0), hi(0.0))
        a = vec_hi(axle[0], axle[1], hi(0.0))
        if wp.length(a) > hi(1.0e-9):
            a = wp.normalize(a)
        else:
            a = vec_hi(hi(0.0), hi(1.0), hi(0.0))
        heading = vec_hi(a[1], -a[0], hi(0.0))
        l0 = hi(huge)
        l1 = hi(huge)
        h0 = hi(-huge)
        h1 = hi(-huge)
        chunk_start = c * chunk
        chunk_end = wp.min(chunk_start + chunk, node_count)
        # the chunk's slots in storage order, only those of the wheel's box (no others hold its contacts)
        for row in range(chunk_start // soil.ny, (chunk_end - 1) // soil.ny + 1):
            for part in range(2):
                start, stop = chunk_box_slots(row, part, w, chunk_start, chunk_end, boxes, soil)
                for k in range(start, stop):
                    if nodes.wheel[k] == w:
                        u = wp.dot(nodes.hit[k], heading)
                        v = wp.dot(nodes.hit[k], a)
                        l0 = wp.min(l0, u)
                        h0 = wp.max(h0, u)
                        l1 = wp.min(l1, v)
                        h1 = wp.max(h1, v)
        low[w, 2 * c + 0] = l0
        low[w, 2 * c + 1] = l1
        high[w, 2 * c + 0] = h0
        high[w, 2 * c + 1] = h1

    @kernel
    def patch_width(
        low: wp.array2d(dtype=hi), high: wp.array2d(dtype=hi), chunks: int, soil: Soil, width: wp.array(dtype=hi)
    ):
        """Per wheel: the Bekker width b = the smaller patch extent (node span plus one spacing) [m]."""
        w = wp.tid()
        l0 = hi(huge)
        l1 = hi(huge)
        h0 = hi(-huge)
        h1 = hi(-huge)
        for c in range(chunks):
            l0 = wp.min(l0, low[w, 2 * c + 0])
            l1 = wp.min(l1, low[w, 2 * c + 1])
            h0 = wp.max(h0, high[w, 2 * c + 0])
            h1 = wp.max(h1, high[w, 2 * c + 1])
        b = hi(huge)
        if h0 >= l0:
            b = wp.min(h0 - l0, h1 - l1) + soil.spacing
        width[w] = b

    @kernel
    def contact_stress(
        wheels: Wheels,
        soil: Soil,
        origin: wp.array(dtype=wp.int32),
        boxes: wp.array2d(dtype=wp.int32),
        width: wp.array(dtype=hi),
        dt: hi,
        nodes: Nodes,
    ):
        """Per node of the wheels' boxes: the elastic-plastic pressure, the shear displacement and stress,
        the node's force on its wheel and torque about the hub; the plastic flow (height) for bulldozing."""
        box_w, a, b = wp.tid()
        k, _i, _j = box_slot(box_w, a, b, soil, origin, boxes)
        if k < 0:
            return
        w = nodes.wheel[k]
        if w < 0:  # the wheel left (or never reached) the node; its other arrays are read at contacts only
            if nodes.shear[k] != hi(0.0):
                nodes.shear[k] = hi(0.0)
            return
        nodes.flow[k] = hi(0.0)
        p = nodes.hit[k]
        n = nodes.normal[k]
        sinkage = nodes.reference[k] - p[2]
        plastic = nodes.plastic[k]
        sigma = soil.elastic_stiffness * (sinkage - plastic)
        bekker = (soil.k_c / width[w] + soil.k_phi) * wp.pow(sinkage, soil.n)
        if sigma > bekker:
            sigma = bekker
            nodes.plastic[k] = sinkage - sigma / soil.elastic_stiffness
            nodes.flow[k] = nodes.plastic[k] - plastic
        hub = wheels.position[w]
        arm = p - hub
        v = wheels.velocity[w] + wp.cross(wheels.angular_velocity[w], arm)
        sigma = wp.max(hi(0.0), sigma - soil.damping * v[2])
        v_t = v - wp.dot(v, n) * n
        speed = wp.length(v_t)
        j = nodes.shear[k] + speed * dt
        nodes.shear[k] = j
        tau = (soil.cohesion + sigma * soil.tan_phi) * (hi(1.0) - wp.exp(-j / soil.janosi_k))
        area = soil.spacing * soil.spacing / wp.max(-n[2], hi(MIN_NORMAL_Z))
        force = -(sigma * area) * n
        if speed > hi(0.0):
            force = force - (tau * area / speed) * v_t
        nodes.pressure[k] = sigma
        nodes.force[k] = force
        nodes.torque[k] = wp.cross(arm, force)

    @wp.func
    def side_offset(side: int):
        """The grid offset (di, dj) of side 0..3 of a node: +x, -x, +y, -y."""
        if side == 0:
            return 1, 0
        if side == 1:
            return -1, 0
        if side == 2:
            return 0, 1
        return 0, -1

    @wp.func
    def neighbour(k: int, di: int, dj: int, soil: Soil, origin: wp.array(dtype=wp.int32), nodes: Nodes):
        """The slot of the grid node (I + di, J + dj) next to slot k, -1 outside the window."""
        i = nodes.key_i[k] + di
        j = nodes.key_j[k] + dj
        if i < origin[0] or i >= origin[0] + soil.nx or j < origin[1] or j >= origin[1] + soil.ny:
            return -1
        return ((i % soil.nx + soil.nx) % soil.nx) * soil.ny + ((j % soil.ny + soil.ny) % soil.ny)

    @kernel
    def mark_rim(soil: Soil, origin: wp.array(dtype=wp.int32), nodes: Nodes):
        """Per node out of contact: the wheel of its first neighbour in contact (sides in a fixed order),
        -1 if none. These nodes are the rims of the contact patches."""
        k = wp.tid()
        rim = int(-1)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        if nodes.wheel[k] < 0:
            for side in range(4):
                di, dj = side_offset(side)
                m = neighbour(k, di, dj, soil, origin, nodes)
                if m >= 0 and rim < 0:
                    rim = nodes.wheel[m]
        nodes.rim[k] = rim

    @kernel
    def flow_partial(
        nodes: Nodes, node_count: int, chunk: int, flow: wp.array2d(dtype=hi), rims: wp.array2d(dtype=wp.int32)
    ):
        """Per (wheel, chunk): the plastic flow (a height, summed over the wheel's contact nodes in storage
        order) and the number of the wheel's rim nodes."""
        w, c = wp.tid()
        total = hi(0.0)
        count = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        for k in range(c * chunk, wp.min((c + 1) * chunk, node_count)):
            if nodes.wheel[k] == w:
                total += nodes.flow[k]
            if nodes.rim[k] == w:
                count += 1
        flow[w, c] = total
        rims[w, c] = count

    @kernel
    def flow_total(
        flow: wp.array2d(dtype=hi),
        rims: wp.array2d(dtype=wp.int32),
        chunks: int,
        fraction: hi,
        raise_by: wp.array(dtype=hi),
    ):
        """Per wheel: how much each of its rim nodes rises [m]: the moved fraction of the patch's plastic
        flow shared equally among the rim nodes (the chunks in order)."""
        w = wp.tid()
        total = hi(0.0)
        count = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        for c in range(chunks):
            total += flow[w, c]
            count += rims[w, c]
        share = hi(0.0)
        if count > 0:
            share = fraction * total / hi(count)
        raise_by[w] = share

    @kernel
    def bulldoze(raise_by: wp.array(dtype=hi), nodes: Nodes):
        """Per rim node: rise by its wheel's share of the patch's displaced soil."""
        k = wp.tid()
        w = nodes.rim[k]
        if w >= 0:
            nodes.reference[k] = nodes.reference[k] + raise_by[w]

    @kernel
    def erode(
        soil: Soil,
        origin: wp.array(dtype=wp.int32),
        limit: hi,
        nodes: Nodes,
        reference_out: wp.array(dtype=hi),
    ):
        """One slope-limiting pass between free nodes: a pair steeper than `limit` (a height difference)
        exchanges an eighth of the excess; each pair's exchange is computed alike on both sides."""
        k = wp.tid()
        level = nodes.reference[k]
        if nodes.wheel[k] < 0:
            surface = level - nodes.plastic[k]
            for side in range(4):
                di, dj = side_offset(side)
                m = neighbour(k, di, dj, soil, origin, nodes)
                if m >= 0:
                    if nodes.wheel[m] < 0:
                        other = nodes.reference[m] - nodes.plastic[m]
                        drop = surface - other
                        if drop > limit:
                            level -= hi(0.125) * (drop - limit)
                        elif -drop > limit:
                            level += hi(0.125) * (-drop - limit)
        reference_out[k] = level

    @kernel
    def wrench_partial(
        nodes: Nodes,
        soil: Soil,
        boxes: wp.array2d(dtype=wp.int32),
        node_count: int,
        chunk: int,
        force: wp.array2d(dtype=vec_hi),
        torque: wp.array2d(dtype=vec_hi),
        count: wp.array2d(dtype=wp.int32),
        deepest: wp.array2d(dtype=hi),
    ):
        """Per (wheel, chunk): the chunk's nodes' force and torque sums in storage order, count, deepest sinkage."""
        w, c = wp.tid()
        f = vec_hi()
        t = vec_hi()
        n = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        z = hi(0.0)
        chunk_start = c * chunk
        chunk_end = wp.min(chunk_start + chunk, node_count)
        # the chunk's slots in storage order, only those of the wheel's box (no others hold its contacts)
        for row in range(chunk_start // soil.ny, (chunk_end - 1) // soil.ny + 1):
            for part in range(2):
                start, stop = chunk_box_slots(row, part, w, chunk_start, chunk_end, boxes, soil)
                for k in range(start, stop):
                    if nodes.wheel[k] == w:
                        f += nodes.force[k]
                        t += nodes.torque[k]
                        n += 1
                        z = wp.max(z, nodes.reference[k] - nodes.hit[k][2])
        force[w, c] = f
        torque[w, c] = t
        count[w, c] = n
        deepest[w, c] = z

    @kernel
    def wrench_total(
        force_part: wp.array2d(dtype=vec_hi),
        torque_part: wp.array2d(dtype=vec_hi),
        count_part: wp.array2d(dtype=wp.int32),
        deepest_part: wp.array2d(dtype=hi),
        chunks: int,
        totals: wp.array2d(dtype=hi),
        sums: wp.array2d(dtype=hi),
    ):
        """Per wheel: the chunks in order; the step's totals (force 3, torque 3, count, sinkage) and their
        running sums over the advance (for the means)."""
        w = wp.tid()
        f = vec_hi()
        t = vec_hi()
        n = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
        z = hi(0.0)
        for c in range(chunks):
            f += force_part[w, c]
            t += torque_part[w, c]
            n += count_part[w, c]
            z = wp.max(z, deepest_part[w, c])
        for a in range(3):
            totals[w, a] = f[a]
            totals[w, 3 + a] = t[a]
        totals[w, 6] = hi(n)
        totals[w, 7] = z
        for a in range(8):
            sums[w, a] = sums[w, a] + totals[w, a]

    rotation_of = path_kernels(hi).rotation_of  # the bodies' rotation, written once (soil.control)

    @kernel
    def follow_path(
        path: wp.array2d(dtype=hi),
        clock: wp.array(dtype=hi),
        dt: hi,
        position: wp.array(dtype=vec_hi),
        rotation: wp.array(dtype=mat_hi),
        velocity: wp.array(dtype=vec_hi),
        angular_velocity: wp.array(dtype=vec_hi),
    ):
        """Pose of wheel w at time tau = clock + dt after the path's start (constant velocities: the start
        position plus v tau, the start orientation turned by omega tau), as soil.control's body paths.
        The clock (the time since the path's start, on the device) moves on in `tick`."""
        w = wp.tid()
        tau = clock[0] + dt
        p0 = vec_hi(path[w, 0], path[w, 1], path[w, 2])
        q0 = vec4_hi(path[w, 3], path[w, 4], path[w, 5], path[w, 6])
        v0 = vec_hi(path[w, 7], path[w, 8], path[w, 9])
        w0 = vec_hi(path[w, 10], path[w, 11], path[w, 12])
        orientation = q0
        angle = wp.length(w0) * tau
        if angle >= hi(1.0e-15):
            axis = w0 / wp.length(w0)
            half = hi(0.5) * angle
            s = wp.sin(half)
            turn = vec4_hi(wp.cos(half), s * axis[0], s * axis[1], s * axis[2])
            orientation = vec4_hi(
                turn[0] * q0[0] - turn[1] * q0[1] - turn[2] * q0[2] - turn[3] * q0[3],
                turn[0] * q0[1] + turn[1] * q0[0] + turn[2] * q0[3] - turn[3] * q0[2],
                turn[0] * q0[2] - turn[1] * q0[3] + turn[2] * q0[0] + turn[3] * q0[1],
                turn[0] * q0[3] + turn[1] * q0[2] - turn[2] * q0[1] + turn[3] * q0[0],
            )
        position[w] = p0 + v0 * tau
        rotation[w] = rotation_of(orientation)
        velocity[w] = v0
        angular_velocity[w] = w0

    @kernel
    def tick(clock: wp.array(dtype=hi), dt: hi):
        """Move the path's clock on by dt (after the wheels were posed at clock + dt)."""
        clock[0] = clock[0] + dt

    return dict(
        Soil=Soil,
        Wheels=Wheels,
        Nodes=Nodes,
        place_window=place_window,
        enter_window=enter_window,
        release=release,
        find_contacts=find_contacts,
        patch_partial=patch_partial,
        patch_width=patch_width,
        contact_stress=contact_stress,
        mark_rim=mark_rim,
        flow_partial=flow_partial,
        flow_total=flow_total,
        bulldoze=bulldoze,
        erode=erode,
        wrench_partial=wrench_partial,
        wrench_total=wrench_total,
        follow_path=follow_path,
        tick=tick,
    )
