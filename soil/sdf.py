"""Signed distances of the rigid partners of a grain: walls (planes, boxes) and wheels
(a parametric grousered wheel, closed triangle meshes), as Warp functions generic in `hi`.

Each returns the distance [m] (negative inside) and the outward unit normal. The contact
kernels (soil.solver) turn them into overlaps; the divergence check (soil.stability) and
the energy diagnostics use the same functions.
"""

import numpy as np
import warp as wp

from .precision import kernel_factory

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


def displaced_geometry(kinds, initial, displacement) -> np.ndarray:
    """Geometry rows [m], shape (count, 6), float64, of boundaries of `kinds` (count,) whose initial rows
    are `initial` (count, 6), moved by `displacement` [m] (count, 3): a plane's point moves, a box's two
    corners move."""
    rows = np.array(initial, dtype=np.float64, copy=True)
    shift = np.asarray(displacement, dtype=np.float64).reshape(-1, 3)
    rows[:, :3] += shift
    box = np.asarray(kinds) == BOUNDARY_BOX
    rows[box, 3:] += shift[box]
    return rows


@kernel_factory
def sdf_functions(hi):
    """The signed-distance functions for the precision type `hi`."""
    vec_hi = wp.types.vector(3, hi)

    @wp.func
    def boundary_contact(kind: int, geometry: wp.array2d(dtype=hi), b: int, x: vec_hi, radius: hi):
        """Overlap [m] of a sphere (centre x, radius) with boundary b, and the unit normal from
        the sphere towards the boundary."""
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
        return hi(0.5) * vec_hi(
            geometry[b, 0] + geometry[b, 3], geometry[b, 1] + geometry[b, 4], geometry[b, 2] + geometry[b, 5]
        )

    @wp.func
    def box_distance(q: vec_hi, half: vec_hi):
        """Signed distance of q from a centred box and the outward normal at the closest point."""
        d = vec_hi(wp.abs(q[0]) - half[0], wp.abs(q[1]) - half[1], wp.abs(q[2]) - half[2])
        if wp.max(d) > hi(0.0):
            gap = q - wp.min(wp.max(q, -half), half)
            distance = wp.length(gap)
            return distance, gap / distance
        axis = int(0)  # noqa: UP018 (a Warp variable the kernel changes: not a constant)
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
    def mesh_distance(
        mesh: wp.uint64,
        points: wp.array(dtype=vec_hi),
        indices: wp.array(dtype=wp.int32),
        point_offset: int,
        index_offset: int,
        p: vec_hi,
        max_distance: hi,
    ):
        """Signed distance of p from a closed mesh and the outward normal; (max_distance, 0) if far.

        Warp's mesh query (float32) finds the closest triangle and the inside/outside
        sign; the closest point is then recomputed in `hi` from the triangle's `hi`
        vertices, so tiny overlaps stay resolved in double and mixed precision.
        """
        query = wp.mesh_query_point_sign_normal(
            mesh, wp.vec3(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2])), wp.float32(max_distance)
        )
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

    return dict(
        boundary_contact=boundary_contact,
        boundary_reference=boundary_reference,
        box_distance=box_distance,
        wheel_distance=wheel_distance,
        closest_on_triangle=closest_on_triangle,
        mesh_distance=mesh_distance,
    )
