"""Wheel geometry: a parametric grousered wheel and triangle meshes (OBJ, STL).

Wheel frame: the hub is the origin, the axle is the local Y axis, the wheel rolls in
the local X-Z plane. A wheel's pose (body -> world) comes from the control.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from typing import cast

import numpy as np

from .errors import DamagedFileError, RegolithWarning, SoilInputError

GROUSER_WHEEL_UNITS = {
    "radius": "m",
    "width": "m",
    "grouser_count": "count",
    "grouser_height": "m",
    "grouser_thickness": "m",
}
"""The unit of each GrouserWheel field."""


@dataclass(frozen=True)
class GrouserWheel:
    """A rigid cylinder with `grouser_count` flat plates (grousers) across its width."""

    radius: float
    """Rim radius [m] (without grousers)."""
    width: float
    """Wheel width along the axle [m]."""
    grouser_count: int = 0
    """Number of grousers, equally spaced [-]; 0 = smooth wheel."""
    grouser_height: float = 0.0
    """How far a grouser stands out of the rim [m]."""
    grouser_thickness: float = 0.0
    """Grouser plate thickness along the rim [m]."""

    def __post_init__(self):
        def check(name, ok, allowed):
            if not ok:
                raise SoilInputError(f"wheel.{name} must be {allowed}, got {getattr(self, name)!r}")

        check("radius", _positive(self.radius), "> 0 [m]")
        check("width", _positive(self.width), "> 0 [m]")
        check(
            "grouser_count",
            isinstance(self.grouser_count, (int, np.integer)) and 0 <= self.grouser_count <= 360,
            "an integer in [0, 360]",
        )
        if self.grouser_count:
            check("grouser_height", _positive(self.grouser_height), "> 0 [m] when grouser_count > 0")
            check(
                "grouser_thickness",
                _positive(self.grouser_thickness) and self.grouser_thickness < self.radius,
                "> 0 [m] and < radius when grouser_count > 0",
            )
            spacing = 2 * math.pi * self.radius / self.grouser_count
            check("grouser_thickness", self.grouser_thickness < spacing, f"< the grouser spacing {spacing:.4g} m")

    @property
    def outer_radius(self) -> float:
        """Radius over the grouser tips [m]."""
        if not self.grouser_count:
            return self.radius
        half = 0.5 * self.grouser_thickness
        return math.hypot(self.radius + self.grouser_height, half)

    @property
    def bounding_radius(self) -> float:
        """Radius of a sphere around the hub that contains the wheel [m]."""
        return math.hypot(self.outer_radius, 0.5 * self.width)

    def shape_row(self) -> list[float]:
        """The kernel's geometry row (see soil.sdf wheel_distance)."""
        return [
            self.radius,
            0.5 * self.width,
            float(self.grouser_count),
            self.grouser_height,
            self.grouser_thickness,
            self.bounding_radius,
        ]

    def profile(self, arc_segments: int = 720) -> np.ndarray:
        """Outline of the wheel in the X-Z plane, counter-clockwise about +Y [m], shape (k, 2)."""
        r = self.radius
        points = []
        if not self.grouser_count:
            angles = np.linspace(0, 2 * math.pi, arc_segments, endpoint=False)
            return np.stack([r * np.sin(angles), r * np.cos(angles)], axis=1)
        half = 0.5 * self.grouser_thickness
        # angle subtended on the rim by half a grouser
        half_angle = math.asin(half / r)
        pitch = 2 * math.pi / self.grouser_count
        per_arc = max(2, int(arc_segments / self.grouser_count))
        for k in range(self.grouser_count):
            theta = k * pitch
            er = np.array([math.sin(theta), math.cos(theta)])
            et = np.array([math.cos(theta), -math.sin(theta)])
            root = math.sqrt(r * r - half * half)
            tip = r + self.grouser_height
            points += [root * er - half * et, tip * er - half * et, tip * er + half * et, root * er + half * et]
            # the rim between this grouser and the next
            start = theta + half_angle
            stop = theta + pitch - half_angle
            for a in np.linspace(start, stop, per_arc + 1)[1:-1]:
                points.append(r * np.array([math.sin(a), math.cos(a)]))
        # sin/cos of the angle from +Z towards +X: going round with increasing theta
        # turns from +Z to +X, i.e. about -Y; reverse so the outline turns about +Y
        return np.array(points)[::-1]

    def to_mesh(self, arc_segments: int = 720) -> tuple[np.ndarray, np.ndarray]:
        """A closed triangle mesh of the wheel: (vertices [m] (v, 3), triangles (t, 3) int)."""
        return extrude_profile(self.profile(arc_segments), self.width)


class MeshOrientationWarning(RegolithWarning):
    """A wheel mesh was wound inside out (inward normals) and was turned over."""


def extrude_profile(profile: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Extrude a star-shaped X-Z outline (about the origin) along Y into a closed mesh."""
    k = len(profile)
    half = 0.5 * width
    ring = lambda y: np.column_stack([profile[:, 0], np.full(k, y), profile[:, 1]])  # noqa: E731
    vertices = np.vstack([ring(-half), ring(half), [[0, -half, 0], [0, half, 0]]])
    centre_lo, centre_hi = 2 * k, 2 * k + 1
    triangles = []
    for i in range(k):
        j = (i + 1) % k
        a, b, c, d = i, j, k + i, k + j
        # outward-facing side quads (outline turns about +Y)
        triangles += [(a, c, b), (b, c, d)]
        triangles += [(centre_lo, a, b), (centre_hi, d, c)]
    faces = np.array(triangles, dtype=np.int32)
    # orient all faces outward: flip if the signed volume is negative
    v = vertices[faces]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
    if volume < 0:
        faces = faces[:, ::-1].copy()
    return vertices.astype(np.float64), faces


MESH_OFF_AXLE = 0.25
"""How far a wheel mesh's bounding-box centre may lie from the axle, in outer radii [-]: a wheel's
grousers and treads move it a little; a mesh far off its axle (exported about another origin) would
sweep a circle its own size away and size every grid and bed check by it."""


@dataclass(frozen=True)
class MeshWheel:
    """A wheel given as a closed triangle mesh in the wheel frame."""

    vertices: np.ndarray
    """Vertex positions in the wheel frame [m], shape (v, 3)."""
    triangles: np.ndarray
    """Vertex indices of each triangle (outward counter-clockwise) [-], shape (t, 3), int."""
    name: str = "mesh"

    def __post_init__(self):
        vertices = np.asarray(self.vertices, dtype=np.float64)
        triangles = np.asarray(self.triangles)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 4 or not np.all(np.isfinite(vertices)):
            raise SoilInputError(
                f"mesh {self.name!r}: vertices must be finite, shape (v >= 4, 3), got {vertices.shape}"
            )
        if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) < 4:
            raise SoilInputError(f"mesh {self.name!r}: triangles must have shape (t >= 4, 3), got {triangles.shape}")
        if triangles.min() < 0 or triangles.max() >= len(vertices):
            raise SoilInputError(f"mesh {self.name!r}: triangle indices must be in [0, {len(vertices)})")
        edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        if np.any(counts != 2):
            raise SoilInputError(
                f"mesh {self.name!r} is not closed (watertight): {int(np.sum(counts != 2))} edges are not "
                "shared by exactly two triangles; inside/outside needs a closed surface"
            )
        low, high = vertices.min(axis=0), vertices.max(axis=0)
        centre = 0.5 * (low + high)
        off_axle = float(np.hypot(centre[0], centre[2]))
        outer = float(np.hypot(vertices[:, 0], vertices[:, 2]).max())
        if off_axle > MESH_OFF_AXLE * outer:
            raise SoilInputError(
                f"mesh {self.name!r}: its centre lies {off_axle:.4g} m from the axle (the wheel frame's y axis), "
                f"more than {MESH_OFF_AXLE:g} of its outer radius {outer:.4g} m: a wheel turns about its axle; "
                "centre the mesh on it (its file's origin must be the hub)"
            )
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "triangles", triangles.astype(np.int32))

    @property
    def bounding_radius(self) -> float:
        return float(np.linalg.norm(self.vertices, axis=1).max())

    @property
    def outer_radius(self) -> float:
        """Largest distance of a vertex from the axle [m]."""
        return float(np.hypot(self.vertices[:, 0], self.vertices[:, 2]).max())

    @classmethod
    def load(cls, path: str | os.PathLike, scale: float = 1.0) -> MeshWheel:
        """Load an OBJ or STL file (units: metres times `scale`), axle along the file's Y axis."""
        path = os.fspath(path)
        extension = os.path.splitext(path)[1].lower()
        if extension not in (".obj", ".stl"):
            raise SoilInputError(f"wheel mesh file must be .obj or .stl, got {path!r}")
        if not os.path.isfile(path):
            raise FileNotFoundError(f"wheel mesh file not found: {path!r}")
        if not (_positive(scale)):
            raise SoilInputError(f"mesh scale must be > 0, got {scale!r}")
        try:
            import trimesh
        except ImportError as error:  # pragma: no cover - depends on the install
            raise ImportError("loading OBJ/STL wheels needs trimesh: pip install 'regolith-cosim[mesh]'") from error
        kind = "STL (binary or ASCII)" if extension == ".stl" else "Wavefront OBJ"
        try:
            # force="mesh": a Trimesh whatever the file holds
            mesh = cast("trimesh.Trimesh", trimesh.load(path, force="mesh", process=False))
        except Exception:
            # trimesh's own message names what failed inside it (a text decoder, a struct), not the file
            raise DamagedFileError(
                f"cannot read wheel mesh {path!r}: not a readable {kind} file (damaged or another format)"
            ) from None
        if len(getattr(mesh, "faces", ())) == 0:
            raise DamagedFileError(f"wheel mesh {path!r} has no triangles: not a readable {kind} file")
        bad = int(np.sum(~np.isfinite(np.asarray(mesh.vertices)).all(axis=1)))
        if bad:  # (processed, trimesh would drop them and their triangles: the mesh would only look open)
            raise DamagedFileError(f"wheel mesh {path!r}: {bad} vertices are not finite numbers (nan or inf)")
        mesh.process()  # duplicate vertices merged, as trimesh does on load
        # degenerate and repeated triangles dropped (process() keeps them: a closed surface read as open),
        # then the vertices no triangle uses (a stray one would size the wheel)
        mesh.update_faces(mesh.unique_faces() & mesh.nondegenerate_faces())
        mesh.remove_unreferenced_vertices()
        if not mesh.is_watertight:
            raise SoilInputError(
                f"wheel mesh {path!r} is not closed (watertight): inside and outside of the wheel need a closed "
                "surface; close its holes (e.g. trimesh.repair.fill_holes) and export it again"
            )
        if not mesh.is_winding_consistent:
            raise SoilInputError(
                f"wheel mesh {path!r} has inconsistent winding (neighbouring triangles face opposite ways): "
                "its normals cannot all point outward; fix the mesh (e.g. trimesh.repair.fix_winding)"
            )
        if mesh.volume < 0:  # closed and consistent, but every normal points inward
            warnings.warn(
                f"wheel mesh {path!r} is wound inside out (normals inward, volume {mesh.volume:.4g} m^3): "
                "its triangles were turned over so that the normals point outward",
                MeshOrientationWarning,
                stacklevel=2,
            )
            trimesh.repair.fix_inversion(mesh)
        wheel = cls(np.asarray(mesh.vertices) * scale, np.asarray(mesh.faces), name=os.path.basename(path))
        wheel.check_wheel_shape()
        return wheel

    def check_wheel_shape(self) -> None:
        """Refuse a mesh read as a wheel that is not one about its hub (SoilInputError naming it): centred
        along the axle within MESH_OFF_AXLE of its width (the walls' clearance and the hub's track assume
        it), and round about the axle (its extents along x and z within MESH_OFF_AXLE of each other: a file
        whose axle is its X axis is a paddle). Other bodies given as meshes (a plate) are not judged."""
        low, high = self.vertices.min(axis=0), self.vertices.max(axis=0)
        centre, span = 0.5 * (low + high), high - low
        if abs(centre[1]) > MESH_OFF_AXLE * span[1]:
            raise SoilInputError(
                f"mesh {self.name!r}: its centre lies {abs(centre[1]):.4g} m along the axle from the hub, more than "
                f"{MESH_OFF_AXLE:g} of its width {span[1]:.4g} m: the wheel would run beside its hub's track and "
                "nearer one wall than the checks judge; centre the mesh on it (its file's origin must be the hub)"
            )
        if abs(span[0] - span[2]) > MESH_OFF_AXLE * max(span[0], span[2]):
            raise SoilInputError(
                f"mesh {self.name!r} is not round about the axle (the wheel frame's y axis): it spans "
                f"{span[0]:.4g} m along x and {span[2]:.4g} m along z (its width along y: {span[1]:.4g} m); "
                "a wheel's axle must be its file's Y axis: rotate the mesh"
            )

    @property
    def volume(self) -> float:
        """Enclosed volume [m^3] (positive: the normals point outward, as the SDF needs)."""
        v = self.vertices[self.triangles]
        return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)

    def save(self, path: str | os.PathLike) -> None:
        """Write the mesh as OBJ or STL (by extension)."""
        import trimesh

        trimesh.Trimesh(self.vertices, self.triangles, process=False).export(os.fspath(path))


def _positive(x) -> bool:
    return isinstance(x, (int, float, np.floating, np.integer)) and math.isfinite(x) and bool(x > 0)
