"""Angle of repose: a square tube of grains lifted off a rough base; the angle from the heap's surface.

    1. settle:  `grains_for(w^2 h)` grains fall into the tube (inner width w, settled height h)
                standing on the base, until their translational kinetic energy < bed.settle_ke_ratio N m g r;
    2. lift:    the four walls of the tube rise together at the lift speed v until their lower
                edge clears the highest grain; the grains flow out into a heap;
    3. rest:    until the translational kinetic energy < lab.rest_ke_ratio N m g r;
    4. measure: the heap's surface profile (`measure_heap`) and the flank's slope.

The base is a square layer of fixed grains (rough, like the sandpaper under a lab heap) or
the flat floor, inside smooth side walls far enough away that a heap down to 10 degrees
fits. The report states v / sqrt(g d) (the lift must be slow against the grains' own
fall speed) and p / E* (the grains must stay nearly rigid); docs/lab.md has the details.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass

import numpy as np

from soil import SoilBuilder

from ..plots import save_figure
from . import common
from .scene import PACKING_FRACTION, LabPlan, SceneError

log = logging.getLogger("cosim.lab")

SMALLEST_ANGLE_DEG = 10.0
"""The base is made wide enough for a heap this flat [deg]."""
BODY_FILL = 0.75
"""A radial bin belongs to the heap's body when this share of the sectors holds a grain there [-]."""


@dataclass(frozen=True)
class ReposeGeometry:
    """Where everything of one heap test is (plan units: metres, Z up; floor at z = 0)."""

    base_width: float
    """Side of the square base and of the side walls' box [m]."""
    base_positions: np.ndarray
    """Centres of the fixed base grains [m], shape (n_base, 3) (empty for a plane base)."""
    base_radius: float
    """Radius of the base grains [m]."""
    base_top: float
    """Height of the base's top (the heap's zero) [m]."""
    fill_positions: np.ndarray
    """Centres of the grains in the tube before settling [m], shape (n, 3)."""
    fill_radii: np.ndarray
    """Their radii [m], shape (n,)."""
    tube_lower: tuple[float, float]
    """Inner lower corner (x, y) of the tube [m]."""
    tube_width: float
    """Inner width of the tube [m]."""
    wall_thickness: float
    """Thickness of the tube's walls [m]."""
    tube_bottom: float
    """Lower edge of the tube's walls [m]."""
    tube_top: float
    """Upper edge of the tube's walls [m]."""
    lift_speed: float
    """[m/s]"""

    @property
    def centre(self) -> tuple[float, float]:
        """Axis of the tube and of the heap (x, y) [m]."""
        return (self.tube_lower[0] + 0.5 * self.tube_width, self.tube_lower[1] + 0.5 * self.tube_width)

    def tube_boxes(self) -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
        """(lower, upper) corners of the four wall boxes [m]: -x, +x, -y, +y."""
        (x0, y0), w, t = self.tube_lower, self.tube_width, self.wall_thickness
        x1, y1, z0, z1 = x0 + w, y0 + w, self.tube_bottom, self.tube_top
        return [
            ((x0 - t, y0 - t, z0), (x0, y1 + t, z1)),
            ((x1, y0 - t, z0), (x1 + t, y1 + t, z1)),
            ((x0, y0 - t, z0), (x1, y0, z1)),
            ((x0, y1, z0), (x1, y1 + t, z1)),
        ]


def lift_speed(plan: LabPlan) -> float:
    """The tube's lift speed [m/s]: repose.lift_speed, or lift_ratio (default 0.1) x sqrt(|g| d)."""
    section = plan.scene.repose
    if section.lift_speed is not None:
        return section.lift_speed
    return (section.lift_ratio if section.lift_ratio is not None else 0.1) * math.sqrt(plan.g * plan.diameter)


def geometry(plan: LabPlan, replica: int = 0, check_memory: bool = False) -> ReposeGeometry:
    """The heap test's geometry and its fill for replica k (fill seed bed.seed + k); with check_memory, one
    whose grains cannot fit this machine's free memory is refused before they are made."""
    section = plan.scene.repose
    d = plan.diameter
    r_max = plan.radius_max
    width = section.tube_width if section.tube_width is not None else 10 * d
    height = section.fill_height if section.fill_height is not None else 1.5 * width
    problems = []
    if width < 4 * r_max * 1.05:
        problems.append(
            f"repose.tube_width: ({width:.4g} m) must hold two of the largest grains (>= {4.2 * r_max:.4g} m)"
        )
    count = common.grains_for(
        plan, width * width * height, "repose.tube_width, repose.fill_height" if check_memory else None
    )
    volume = width * width * height  # the heap keeps the column's bulk volume
    footprint = (3 * volume / (math.pi * math.tan(math.radians(SMALLEST_ANGLE_DEG)))) ** (1 / 3)
    base_width = section.base_width if section.base_width is not None else 2 * (footprint + 3 * d)
    if base_width < width + 4 * d:
        problems.append(
            f"repose.base_width: ({base_width:.4g} m) must exceed the tube ({width:.4g} m) by 4 grain "
            f"diameters ({width + 4 * d:.4g} m)"
        )
    if problems:
        raise SceneError(problems)
    if section.base == "grains":
        radius = plan.radius_mean
        pitch = 2.1 * radius  # not touching each other; the pockets between them hold every grain (r >= 0.5 r_mean)
        n = int(base_width // pitch)
        centres = (np.arange(n) + 0.5) * pitch + 0.5 * (base_width - n * pitch)
        xx, yy = np.meshgrid(centres, centres, indexing="ij")
        base = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, radius)], axis=1)
        base_top = 2 * radius
    else:
        radius, base, base_top = 0.0, np.zeros((0, 3)), 0.0
    lower = (0.5 * (base_width - width), 0.5 * (base_width - width))
    seed, _ = common.replica_seeds(plan, replica)
    positions, radii = common.lattice_fill(
        plan, (lower[0], lower[1], base_top), (lower[0] + width, lower[1] + width), count, seed
    )
    top = float(np.max(positions[:, 2] + radii)) + d
    return ReposeGeometry(
        base_width=base_width,
        base_positions=base,
        base_radius=radius,
        base_top=base_top,
        fill_positions=positions,
        fill_radii=radii,
        tube_lower=lower,
        tube_width=width,
        wall_thickness=d,
        tube_bottom=base_top,
        tube_top=top,
        lift_speed=lift_speed(plan),
    )


def build(plan: LabPlan, geo: ReposeGeometry, order_seed: int | None):
    """(simulation, tube wall indices) of a heap test."""
    builder = SoilBuilder(gravity=np.asarray(plan.gravity))
    grain = builder.add_material(plan.soil)
    wall = builder.add_material(plan.wall_material(plan.scene.repose.wall_friction_deg))
    w = geo.base_width
    builder.add_plane((0, 0, 0), (0, 0, 1), grain)  # the floor: rough (the soil's own friction)
    for axis in range(2):
        inward = np.zeros(3)
        inward[axis] = 1.0
        builder.add_plane((0, 0, 0), inward, wall)
        builder.add_plane((w, w, 0), -inward, wall)
    tube = [builder.add_box(lower, upper, wall) for lower, upper in geo.tube_boxes()]
    if len(geo.base_positions):
        builder.add_particles(geo.base_positions, geo.base_radius, grain, fixed=True)
    builder.add_particles(geo.fill_positions, geo.fill_radii, grain)
    return common.finalize(plan, builder, order_seed), tube


def measure_heap(
    positions, radii, centre, base_top: float, bin_width: float, sectors: int = 16, fit_range=(0.1, 0.9)
) -> dict:
    """The angle of repose of a heap from its surface profile.

    The heap is cut into `sectors` equal angular sectors about its axis `centre` (x, y) [m]
    and radial bins of `bin_width` [m]; the surface of each cell is the top (z + r) of its
    highest grain above `base_top` [m]. The profile is the median over the sectors. Its
    body runs from the peak outwards while at least 75 % of the sectors hold a grain (a
    few grains rolled further do not count); the toe is the body's last bin. The flank is
    the part of the body between the toe + fit_range[0] H and the toe + fit_range[1] H,
    H = peak - toe. A straight line fitted to each sector's flank gives its slope; the
    angle of repose is the mean of the sectors' angles, its uncertainty their standard
    error. The line through the median profile's flank is reported as a cross-check.

    Returns angle, angle_sem, angle_std, angle_profile [deg], sectors_fitted, height
    (H + toe above the base), toe [m], footprint (outer radius of the body) [m], window
    (first, last bin of the flank), radius (bin centres) [m], profile (median) [m], filled
    (share of sectors per bin), tops (sectors, bins) [m]; angle is NaN when the flank has
    fewer than three bins (too small a heap: more grains or a wider tube).
    """
    x = np.asarray(positions, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    dx, dy = x[:, 0] - centre[0], x[:, 1] - centre[1]
    rho = np.hypot(dx, dy)
    top = x[:, 2] + r - base_top
    sector = np.minimum(((np.arctan2(dy, dx) + math.pi) / (2 * math.pi / sectors)).astype(int), sectors - 1)
    radial = (rho // bin_width).astype(int)
    bins = int(radial.max()) + 1
    tops = np.full((sectors, bins), np.nan)
    np.fmax.at(tops, (sector, radial), top)
    filled = np.isfinite(tops).mean(axis=0)
    profile = np.full(bins, np.nan)
    has = filled > 0
    profile[has] = np.nanmedian(tops[:, has], axis=0)
    centres = (np.arange(bins) + 0.5) * bin_width
    peak_bin = int(np.nanargmax(profile))
    end = peak_bin
    while end + 1 < bins and filled[end + 1] >= BODY_FILL:
        end += 1
    peak, toe = float(profile[peak_bin]), float(profile[end])
    rise = peak - toe
    k = np.arange(bins)
    low, high = toe + fit_range[0] * rise, toe + fit_range[1] * rise
    flank = (k >= peak_bin) & (k <= end) & (profile >= low) & (profile <= high)
    result = {
        "height": peak,
        "toe": toe,
        "footprint": float((end + 1) * bin_width),
        "window": [int(k[flank].min()), int(k[flank].max())] if flank.any() else [peak_bin, end],
        "radius": centres,
        "profile": profile,
        "filled": filled,
        "tops": tops,
        "angle": math.nan,
        "angle_sem": math.nan,
        "angle_std": math.nan,
        "angle_profile": math.nan,
        "sectors_fitted": 0,
    }
    if flank.sum() < 3:
        return result
    slope = np.polyfit(centres[flank], profile[flank], 1)[0]
    fitted = []
    for s in range(sectors):
        use = flank & np.isfinite(tops[s])
        if use.sum() >= 3:
            fitted.append(math.degrees(math.atan(-np.polyfit(centres[use], tops[s, use], 1)[0])))
    angles = np.asarray(fitted)
    result.update(angle_profile=math.degrees(math.atan(-slope)), sectors_fitted=len(angles))
    if len(angles):
        result.update(
            angle=float(angles.mean()),
            angle_std=float(angles.std(ddof=1)) if len(angles) > 1 else math.nan,
            angle_sem=float(angles.std(ddof=1) / math.sqrt(len(angles))) if len(angles) > 1 else math.nan,
        )
    return result


def run_replica(plan: LabPlan, replica: int = 0) -> dict:
    """One heap: settle in the tube, lift, rest, measure. Returns the measurement (measure_heap),
    the phases' times [s] and whether each ended by its criterion, the free grains' final
    positions [m] (n, 3) and radii [m], the geometry's numbers and the history (time [s], translational
    kinetic energy [J], tube lift [m] per check)."""
    geo = geometry(plan, replica)
    _, order_seed = common.replica_seeds(plan, replica)
    sim, tube = build(plan, geo, order_seed)
    chunk = common.chunk_steps(plan, plan.time_scale)
    longest = plan.max_phase_time(1.0)
    free = sim.free_grains()
    history: list[tuple[float, float, float]] = []

    def record(s):
        history.append((s.time, common.moving_energy(s), float(s.boundary_displacements()[tube[0], 2])))

    def still(ratio):
        threshold = common.kinetic_threshold(sim, ratio, plan.g)
        return lambda s: (record(s), common.moving_energy(s) < threshold)[1]

    min_time = 5 * plan.time_scale
    settle_time, settled = common.run_until(
        sim, plan.dt, still(plan.scene.bed.settle_ke_ratio), longest, chunk, min_time
    )
    column = float(np.max(sim.positions()[free, 2] + sim.radii()[free]))
    sim.control.set_boundary_velocity(tube, (0.0, 0.0, geo.lift_speed))
    r_max = plan.radius_max

    def cleared(s):
        record(s)
        bottom = geo.tube_bottom + s.boundary_displacements()[tube[0], 2]
        return bottom > np.max(s.positions()[free, 2] + s.model.radius_numpy()[free]) + r_max

    lift_time, lifted = common.run_until(sim, plan.dt, cleared, longest, chunk)
    sim.control.set_boundary_velocity(tube, (0.0, 0.0, 0.0))
    rest_time, rested = common.run_until(sim, plan.dt, still(plan.scene.lab.rest_ke_ratio), longest, chunk, min_time)
    x, r = sim.positions()[free], sim.radii()[free]
    section = plan.scene.repose
    heap = measure_heap(x, r, geo.centre, geo.base_top, plan.diameter, section.sectors, section.fit_range)
    near_wall = np.min(np.stack([x[:, 0], x[:, 1], geo.base_width - x[:, 0], geo.base_width - x[:, 1]]), axis=0)
    history_array = np.asarray(history) if history else np.zeros((0, 3))
    return {
        **heap,
        "replica": replica,
        "grains": int(free.sum()),
        "base_grains": int(len(geo.base_positions)),
        "positions": x,
        "radii": r,
        "centre": geo.centre,
        "base_top": geo.base_top,
        "base_width": geo.base_width,
        "tube_width": geo.tube_width,
        "column_height": column - geo.base_top,
        "lift_speed": geo.lift_speed,
        "settle_time": settle_time,
        "settled": settled,
        "lift_time": lift_time,
        "lifted": lifted,
        "rest_time": rest_time,
        "rested": rested,
        "at_walls": int(np.sum(near_wall < 2 * plan.diameter)),
        "history": history_array,
        "steps": int(sim.steps),
        "particles": int(sim.particle_count),
    }


def quasi_static_numbers(plan: LabPlan, column_height: float, lift_speed_value: float) -> list[dict]:
    """The dimensionless numbers of a heap test (docs/lab.md)."""
    pressure = PACKING_FRACTION * plan.soil.density * plan.g * column_height
    return [
        common.quasi_static(
            "lift speed v / sqrt(g d)",
            lift_speed_value / math.sqrt(plan.g * plan.diameter),
            0.3,
            "the tube rises slowly against the grains' own fall speed over one diameter",
        ),
        common.stiffness_number(plan, pressure),
    ]


def repose_test(
    plan: LabPlan,
    out_dir: str,
    overwrite: bool = False,
    executor: str = "serial",
    scheduler: str | None = None,
    workers: int | None = None,
) -> dict:
    """Run lab.replicas heaps (through cosim.study.Executor), write the report into out_dir
    (repose.csv: the surface profiles; repose_grains.csv: the heaps' grains, to measure again;
    repose_history.csv; summary.json; repose.png) and return the summary."""
    geo = geometry(plan, 0, check_memory=True)  # a geometry that cannot work is refused before the folder is touched
    with common.prepare_folder(plan, out_dir, overwrite, executor, scheduler):
        replicas = plan.scene.lab.replicas
        log.info(
            "repose: %d grains in a %.3g m tube on a %.3g m base, lifted at %.3g m/s; %d replica(s)",
            len(geo.fill_radii),
            geo.tube_width,
            geo.base_width,
            geo.lift_speed,
            replicas,
        )
        results, stopped = common.map_until_stopped(
            plan,
            run_replica,
            [{"replica": k} for k in range(replicas)],
            [f"replica {k}" for k in range(replicas)],
            executor,
            scheduler,
            workers,
        )
        done = common.successful(results, "repose")
        angles = [r["angle"] for r in done]
        numbers = quasi_static_numbers(plan, max(r["column_height"] for r in done), geo.lift_speed)
        notes = _notes(plan, done) + common.interrupted_notes(stopped, len(results), replicas, "replicas")
        summary = {
            "test": "repose",
            "name": plan.name,
            "gravity": plan.g,
            "units": {"gravity": "m/s^2"},  # the other numbers: counts, or a unit in their key
            "soil": common.soil_summary(plan),
            "repose_angle_deg": common.statistics(angles),
            "repose_angle_profile_deg": common.statistics([r["angle_profile"] for r in done]),
            "replicas": [
                {
                    "replica": r["replica"],
                    "angle_deg": r["angle"],
                    "angle_sem_deg": r["angle_sem"],
                    "angle_profile_deg": r["angle_profile"],
                    "height_m": r["height"],
                    "toe_m": r["toe"],
                    "footprint_m": r["footprint"],
                    "grains": r["grains"],
                    "settled": r["settled"],
                    "lifted": r["lifted"],
                    "rested": r["rested"],
                    "settle_time_s": r["settle_time"],
                    "lift_time_s": r["lift_time"],
                    "rest_time_s": r["rest_time"],
                    "grains_at_walls": r["at_walls"],
                    "steps": r["steps"],
                }
                for r in done
            ],
            "failed": [{"label": r.get("label"), "error": r.get("error")} for r in results if not r.get("ok")],
            "geometry": {
                "tube_width_m": geo.tube_width,
                "column_height_m": float(np.mean([r["column_height"] for r in done])),
                "base": plan.scene.repose.base,
                "base_width_m": geo.base_width,
                "grains": len(geo.fill_radii),
                "base_grains": len(geo.base_positions),
                "lift_speed_m_s": geo.lift_speed,
                "grain_diameter_m": plan.diameter,
                "dt_s": plan.dt,
            },
            "quasi_static": numbers,
            "notes": notes,
        }
        rows = [(r["replica"], c, p, f) for r in done for c, p, f in zip(r["radius"], r["profile"], r["filled"])]
        common.write_csv(
            os.path.join(out_dir, "repose.csv"),
            [
                ("replica", "1", [row[0] for row in rows]),
                ("radius", "m", [row[1] for row in rows]),
                ("surface_height", "m", [row[2] for row in rows]),
                ("sectors_filled", "1", [row[3] for row in rows]),
            ],
        )
        grains = [(r["replica"], *x, radius) for r in done for x, radius in zip(r["positions"], r["radii"])]
        common.write_csv(
            os.path.join(out_dir, "repose_grains.csv"),
            [
                (name, unit, [g[i] for g in grains])
                for i, (name, unit) in enumerate(
                    (("replica", "1"), ("x", "m"), ("y", "m"), ("z", "m"), ("radius", "m"))
                )
            ],
        )
        history = [(r["replica"], *h) for r in done for h in r["history"]]
        common.write_csv(
            os.path.join(out_dir, "repose_history.csv"),
            [
                ("replica", "1", [h[0] for h in history]),
                ("time", "s", [h[1] for h in history]),
                ("translational_kinetic_energy", "J", [h[2] for h in history]),
                ("tube_lift", "m", [h[3] for h in history]),
            ],
        )
        summary["figure"] = _figure(out_dir, done, summary)
        common.write_summary(out_dir, summary)
        if stopped is not None:  # the finished replicas' report is written: now stop as asked
            raise stopped
        return summary


def _notes(plan: LabPlan, done: list[dict]) -> list[str]:
    notes = []
    for r in done:
        k = r["replica"]
        if not (r["settled"] and r["lifted"] and r["rested"]):
            phase = "settle" if not r["settled"] else "lift" if not r["lifted"] else "rest"
            notes.append(f"replica {k}: the {phase} phase hit lab.max_time_factor x sqrt(d/g) before its criterion")
        if r["at_walls"]:
            notes.append(f"replica {k}: {r['at_walls']} grain(s) reached the side walls: widen repose.base_width")
        if not np.isfinite(r["angle"]):
            notes.append(
                f"replica {k}: the flank is shorter than three bins: more grains (repose.fill_height) or "
                "a wider tube (repose.tube_width)"
            )
        elif r["height"] - r["toe"] < 2 * plan.diameter:
            notes.append(
                f"replica {k}: the heap rises only {(r['height'] - r['toe']) / plan.diameter:.2g} grain "
                "diameters above its toe: its angle is coarse (more grains)"
            )
    return notes


def _figure(out_dir: str, done: list[dict], summary: dict) -> str | None:
    plt = common.pyplot()
    if plt is None:
        return None
    first = done[0]
    fig, (side, prof) = plt.subplots(1, 2, figsize=(12, 4.5))
    d = summary["geometry"]["grain_diameter_m"]
    x = first["positions"]
    slab = np.abs(x[:, 1] - first["centre"][1]) < d
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    grains = [
        Circle(((px - first["centre"][0]) * 1e3, (pz - first["base_top"]) * 1e3), pr * 1e3)
        for (px, _, pz), pr in zip(x[slab], first["radii"][slab])
    ]
    side.add_collection(PatchCollection(grains, facecolor="tan", edgecolor="saddlebrown", lw=0.5))
    side.autoscale_view()
    side.set_aspect("equal")
    side.set_xlabel("x from the heap's axis [mm]")
    side.set_ylabel("height above the base [mm]")
    side.set_title(f"replica {first['replica']}: grains within one diameter of the axis plane")
    for r in done:
        (line,) = prof.plot(
            r["radius"] * 1e3, r["profile"] * 1e3, ".-", label=f"replica {r['replica']}: {r['angle']:.1f} deg"
        )
        if np.isfinite(r["angle"]):
            lo, hi = r["window"]
            radius = r["radius"][lo : hi + 1]
            fit = np.polyfit(radius, r["profile"][lo : hi + 1], 1)
            prof.plot(radius * 1e3, np.polyval(fit, radius) * 1e3, "-", color=line.get_color(), lw=3, alpha=0.4)
    stats = summary["repose_angle_deg"]
    title = f"angle of repose {stats.get('mean', math.nan):.1f} deg"
    if stats.get("n", 0) > 1:
        title += f" +- {stats['ci95']:.1f} (95 %, {stats['n']} replicas)"
    prof.set_title(title)
    prof.set_xlabel("distance from the axis [mm]")
    prof.set_ylabel("surface height (median over sectors) [mm]")
    prof.legend(fontsize=8)
    fig.tight_layout()
    path = os.path.join(out_dir, "repose.png")
    save_figure(fig, path, 120)
    plt.close(fig)
    return path
