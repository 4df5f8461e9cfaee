"""Direct shear: a split box sheared at several normal stresses; peak and residual strength,
and the Mohr-Coulomb friction angle and cohesion from a straight-line fit.

    box:     inner length L (shear direction X) x width W; the floor (rough) and two frames of
             four smooth walls each, split at mid height by a gap smaller than any grain;
    sample:  `grains_for(L W H)` grains settle into the box (each replica a new specimen,
             settled once for all its normal stresses);
    consolidate: a rough lid plane on the grains, dead-loaded with sigma L W (a rigid body
             free along -Z, its mass the sample's, critically damped against the sample's
             stiffness) until it stops moving;
    shear:   the upper frame and the lid move along +X at the shear speed v (reached linearly over
             the first 2 % of the samples); the lid keeps its load (it rises and falls with
             the sample's dilation).

Measured (every recorded step, from the boundary wrenches):
    tau     = -(F_x on the upper frame + F_x on the lid) / (L W)         [Pa]
    sigma_n = (F_z on the lid + weight of the grains above the shear plane) / (L W)   [Pa]
Peak: the largest tau of the curve smoothed over 1/20 of the displacement; residual: the
mean over the second half of the displacement. tau = c + sigma_n tan(phi) fitted (scipy.stats.linregress) to
every (sigma_n, tau) pair of every replica, for the peak and for the residual state; and
tau = sigma_n tan(phi_0) through the origin (a cohesionless soil's angle).
Quasi-static when the inertial number I = (v / 10 d) d / sqrt(sigma / rho) <= 1e-3.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass

import numpy as np

from soil import SoilBuilder
from soil.bed import read_bed, save_bed

from ..plots import save_figure
from . import common
from .scene import LabPlan, SceneError

log = logging.getLogger("cosim.lab")

BAND_DIAMETERS = 10.0
"""Width of a shear band in grain diameters (GDR MiDi 2004): the shear rate is v / (10 d) [-]."""
RECORDS = 400
"""Samples of a shear curve [-]."""
RAMP = 0.02
"""Share of the samples over which the shear speed rises linearly to its value [-] (no impulsive start)."""


@dataclass(frozen=True)
class ShearBox:
    """The box of a direct shear test (floor at z = 0, box from x = y = 0)."""

    length: float
    """Inner length along the shear direction X [m]."""
    width: float
    """Inner width [m]."""
    height: float
    """Settled sample height [m] (its middle is the shear plane)."""
    gap: float
    """Gap between the halves [m]."""
    wall: float
    """Wall thickness [m] (more than the shear displacement: grains carried over a lower wall rest on it)."""
    top: float
    """Upper edge of the upper frame [m]."""
    displacement: float
    """Shear displacement [m]."""
    speed: float
    """Shear speed [m/s]."""
    stresses: tuple[float, ...]
    """Nominal normal stresses [Pa]."""
    count: int
    """Grains [-]."""

    @property
    def area(self) -> float:
        """L W [m^2]."""
        return self.length * self.width

    @property
    def plane(self) -> float:
        """Height of the shear plane [m]."""
        return 0.5 * self.height

    def frames(self) -> tuple[list, list]:
        """(lower, upper) frames: four (lower corner, upper corner) boxes each [m]."""
        length, width, t = self.length, self.width, self.wall

        def frame(z0, z1):
            return [
                ((-t, -t, z0), (0.0, width + t, z1)),
                ((length, -t, z0), (length + t, width + t, z1)),
                ((0.0, -t, z0), (length, 0.0, z1)),
                ((0.0, width, z0), (length, width + t, z1)),
            ]

        return frame(0.0, self.plane - 0.5 * self.gap), frame(self.plane + 0.5 * self.gap, self.top)


def normal_stresses(plan: LabPlan) -> tuple[float, ...]:
    """shear.normal_stresses, or Young's modulus x (2.5e-5, 5e-5, 1e-4) (overlaps up to about 1 % of r)."""
    given = plan.scene.shear.normal_stresses
    return tuple(given) if given is not None else tuple(plan.soil.youngs_modulus * f for f in (2.5e-5, 5e-5, 1e-4))


def shear_speed(plan: LabPlan, stresses) -> float:
    """shear.speed, or the speed of inertial number shear.inertial_number (default 1e-3) at the lowest stress [m/s]."""
    section = plan.scene.shear
    if section.speed is not None:
        return section.speed
    number = section.inertial_number if section.inertial_number is not None else 1e-3
    return number * BAND_DIAMETERS * math.sqrt(min(stresses) / plan.soil.density)


def inertial_number(plan: LabPlan, speed: float, stress: float) -> float:
    """I = gamma_dot d / sqrt(sigma / rho), gamma_dot = v / (10 d) [-]."""
    return speed / BAND_DIAMETERS / math.sqrt(stress / plan.soil.density)


def box(plan: LabPlan, check_memory: bool = False) -> ShearBox:
    """The shear box of a plan; SceneError names a box that cannot work (and, with check_memory, one whose
    grains cannot fit this machine's free memory, before they are made)."""
    section = plan.scene.shear
    d = plan.diameter
    r_min = plan.radius_min
    length = section.length if section.length is not None else 12 * d
    width = section.width if section.width is not None else 12 * d
    height = section.height if section.height is not None else 8 * d
    gap = section.gap if section.gap is not None else 1.5 * r_min
    displacement = section.displacement if section.displacement is not None else 0.2 * length
    problems = []
    for name, value in (("length", length), ("width", width), ("height", height)):
        if value < 4 * d:
            problems.append(f"shear.{name}: ({value:.4g} m) must hold at least four grain diameters ({4 * d:.4g} m)")
    if gap >= 2 * r_min:
        problems.append(
            f"shear.gap: ({gap:.4g} m) must be smaller than the smallest grain ({2 * r_min:.4g} m) or "
            "grains leak out between the halves"
        )
    if displacement >= 0.5 * length:
        problems.append(
            f"shear.displacement: ({displacement:.4g} m) must be less than half the box length ({0.5 * length:.4g} m)"
        )
    if problems:
        raise SceneError(problems)
    stresses = normal_stresses(plan)
    keys = "shear.length, shear.width, shear.height" if check_memory else None  # before the folder, not per replica
    count = common.grains_for(plan, length * width * height, keys)
    # the loose lattice stands about twice as high as the settled sample: frames high enough to hold it
    r_max = plan.radius_max
    nx, ny = (int((s - 2 * r_max) // (2.04 * r_max)) + 1 for s in (length, width))
    loose = (-(-count // (nx * ny)) + 1) * 2.04 * r_max
    return ShearBox(
        length,
        width,
        height,
        gap,
        max(d, displacement + d),
        max(loose, height) + 2 * d,
        displacement,
        shear_speed(plan, stresses),
        stresses,
        count,
    )


def _specimen(plan: LabPlan, geometry: ShearBox, replica: int, path: str) -> dict:
    """Fill and settle a specimen in the box (gravity permitting) and save it to `path`."""
    builder = SoilBuilder(gravity=np.asarray(plan.gravity))
    grain = builder.add_material(plan.soil)
    wall = builder.add_material(plan.wall_material(plan.scene.shear.wall_friction_deg))
    builder.add_plane((0, 0, 0), (0, 0, 1), grain)
    lower, upper = geometry.frames()
    for low, high in lower + upper:
        builder.add_box(low, high, wall)
    seed, order_seed = common.replica_seeds(plan, replica)
    positions, radii = common.lattice_fill(plan, (0, 0, 0), (geometry.length, geometry.width), geometry.count, seed)
    builder.add_particles(positions, radii, grain)
    sim = common.finalize(plan, builder, order_seed)
    settled, time_taken = True, 0.0
    if plan.g > 0:
        threshold = common.kinetic_threshold(sim, plan.scene.bed.settle_ke_ratio, plan.g)
        time_taken, settled = common.run_until(
            sim,
            plan.dt,
            lambda s: common.moving_energy(s) < threshold,
            plan.max_phase_time(1.0),
            common.chunk_steps(plan, plan.time_scale),
            5 * plan.time_scale,
        )
    save_bed(path, sim)
    top = float(np.max(sim.positions()[:, 2] + sim.radii()))
    return {"replica": replica, "path": path, "settled": settled, "settle_time": time_taken, "top": top}


def _lid_dynamics(plan: LabPlan, geometry: ShearBox, stress: float, mass: float) -> tuple[float, float]:
    """(damping [N s/m], natural period [s]) of the lid on the sample: the sample's stiffness
    k = A M / H with the Hertz-packing modulus M ~ (E*^2 sigma)^(1/3); damping 2 sqrt(k m) (critical)."""
    e_star = plan.soil.youngs_modulus / (2 * (1 - plan.soil.poisson_ratio**2))
    stiffness = geometry.area * (e_star**2 * stress) ** (1 / 3) / geometry.height
    return 2 * math.sqrt(stiffness * mass), 2 * math.pi * math.sqrt(mass / stiffness)


def _shear(plan: LabPlan, geometry: ShearBox, replica: int, path: str, stress: float, top: float) -> dict:
    """Consolidate the saved specimen (its highest grain reaching `top` [m]) under `stress` [Pa] and shear it."""
    builder = read_bed(path).builder()
    grain = 0  # the specimen's first material is the soil
    lid = builder.add_plane((0, 0, top + 0.1 * plan.radius_mean), (0, 0, -1), grain)
    _, order_seed = common.replica_seeds(plan, replica)
    sim = common.finalize(plan, builder, order_seed)
    control = sim.control
    sample_mass = float(sim.masses().sum())
    damping, period = _lid_dynamics(plan, geometry, stress, sample_mass)
    load = stress * geometry.area
    control.set_boundary_load(lid, load, direction=(0, 0, -1), mass=sample_mass, damping=damping)
    lower = [1, 2, 3, 4]
    upper = [5, 6, 7, 8]
    chunk = common.chunk_steps(plan, 0.5 * period)
    longest = min(plan.max_phase_time(period), 100 * period)  # the lid settles within tens of its periods
    last = [sim.boundary_displacements()[lid, 2]]

    def consolidated(s):
        # the grains carry the lid's load and it has stopped sinking
        z = s.boundary_displacements()[lid, 2]
        still = abs(z - last[0]) < 5e-3 * plan.radius_mean
        last[0] = z
        return still and abs(s.boundary_wrenches()[0][lid, 2] - load) < 0.05 * load

    consolidate_time, consolidated_ok = common.run_until(sim, plan.dt, consolidated, longest, chunk, 3 * period)
    weight_above = float(np.sum(sim.masses()[sim.positions()[:, 2] > geometry.plane])) * plan.g
    duration = geometry.displacement / geometry.speed
    steps = int(round(duration / plan.dt))
    every = max(1, steps // RECORDS)
    ramp = RAMP * RECORDS  # records over which the frame speeds up: no impulsive start
    z0 = sim.boundary_displacements()[lid, 2]
    rows = []
    k = 0
    while True:
        u = sim.boundary_displacements()[upper[0], 0]
        if u >= geometry.displacement:
            break
        control.set_boundary_velocity(upper + [lid], (geometry.speed * min(1.0, (k + 1) / ramp), 0.0, 0.0))
        sim.run(every * plan.dt, plan.dt)
        k += 1
        force = sim.boundary_wrenches()[0]
        shift = sim.boundary_displacements()
        rows.append(
            (
                shift[upper[0], 0],
                -(force[upper, 0].sum() + force[lid, 0]) / geometry.area,
                (force[lid, 2] + weight_above) / geometry.area,
                force[[0] + lower, 0].sum() / geometry.area,
                shift[lid, 2] - z0,
            )
        )
        if k > 2 * RECORDS + ramp:
            break
    sim.check_finite()
    u, tau, sigma, tau_lower, rise = (np.array(c) for c in zip(*rows))
    return {
        "replica": replica,
        "stress": stress,
        "displacement": u,
        "tau": tau,
        "sigma": sigma,
        "tau_lower": tau_lower,
        "rise": rise,
        **strength(u, tau, sigma),
        "consolidated": consolidated_ok,
        "consolidate_time": consolidate_time,
        "lid_damping": damping,
        "weight_above": weight_above,
        "steps": int(sim.steps),
        "particles": int(sim.particle_count),
    }


RISING_BLOCKS = 5
"""Blocks of equal travel over the second half of a shear, whose means tell a curve still rising from a
plateau."""
RISING_GAIN = 0.05
"""What a curve still rising gains over the second half, as a fraction of its peak (a plateau: nothing)."""


def strength(u, tau, sigma) -> dict:
    """Peak and residual of a shear curve (displacement u [m], tau and sigma_n [Pa] per record):
    the peak is the largest tau smoothed over 1/20 of the records, with the mean sigma_n around
    it; the residual the means over the second half of the displacement. `rising_at_end`: tau still
    climbs at the end (_still_rising): a curve still rising (its peak may lie beyond the travel, and the
    second half is no residual), not one levelled off at a plateau that wobbles (a small box's, whose
    largest value may fall anywhere in it)."""
    u, tau, sigma = (np.asarray(c, dtype=float) for c in (u, tau, sigma))
    window = max(1, len(u) // 20)
    smooth = np.convolve(tau, np.ones(window) / window, mode="same")
    edge = window // 2  # the running mean is biased where it runs off the ends
    inner = slice(edge, len(u) - edge) if len(u) > 2 * edge + 1 else slice(None)
    peak = int(np.argmax(smooth[inner])) + (inner.start or 0)
    near = slice(max(0, peak - window // 2), peak + window // 2 + 1)
    residual = u >= 0.5 * u[-1]
    return {
        "peak_tau": float(smooth[peak]),
        "peak_sigma": float(sigma[near].mean()),
        "peak_displacement": float(u[peak]),
        "residual_tau": float(tau[residual].mean()),
        "residual_sigma": float(sigma[residual].mean()),
        "rising_at_end": _still_rising(u, tau, float(smooth[peak])),
    }


def _still_rising(u, tau, peak: float) -> bool:
    """Whether tau still climbs at the end of the travel u (strength's `rising_at_end`): over the second
    half in RISING_BLOCKS blocks of equal travel, the last block's mean is the highest (within the
    blocks' scatter) and near the curve's peak (within twice RISING_GAIN of it: a curve that peaked
    earlier and recovers a little is not still rising to its peak), and above the first block's by more
    than RISING_GAIN of the peak and by more than twice the blocks' scatter (the spread of their
    successive differences: a steady climb has little, a wobbling plateau much)."""
    edges = np.linspace(0.5 * u[-1], u[-1], RISING_BLOCKS + 1)
    means = []
    for low, high in zip(edges[:-1], edges[1:]):
        inside = (u >= low) & (u <= high)
        if not inside.any():
            return False
        means.append(float(tau[inside].mean()))
    climb = means[-1] - means[0]
    scatter = float(np.std(np.diff(means), ddof=1))
    highest = means[-1] >= max(means) - scatter and means[-1] >= (1.0 - 2.0 * RISING_GAIN) * peak
    return bool(highest and climb > RISING_GAIN * abs(peak) and climb > 2.0 * scatter)


def run_replica(
    plan: LabPlan, replica: int = 0, stage: str = "shear", specimen: str = "", stress: float = 0.0, top: float = 0.0
) -> dict:
    """One task of the test: stage 'specimen' settles replica k into the file `specimen`;
    stage 'shear' consolidates that specimen (grains up to `top` [m]) under `stress` [Pa] and shears it."""
    geometry = box(plan)
    if stage == "specimen":
        return _specimen(plan, geometry, replica, specimen)
    return _shear(plan, geometry, replica, specimen, stress, top)


def mohr_coulomb(sigma, tau) -> dict:
    """tau = c + sigma tan(phi) by least squares (scipy.stats.linregress): friction angle phi [deg],
    cohesion c [Pa] and their standard errors (NaN with two points or one stress); and the
    line through the origin tau = sigma tan(phi_0) (c = 0, a cohesionless soil's angle, from
    a single stress on): friction_angle_origin_deg."""
    from scipy import stats

    sigma, tau = np.asarray(sigma, dtype=float), np.asarray(tau, dtype=float)
    origin = math.degrees(math.atan(float(np.sum(sigma * tau) / np.sum(sigma**2)))) if len(sigma) else math.nan
    if len(np.unique(sigma)) < 2:
        return {
            "friction_angle_deg": math.nan,
            "cohesion_pa": math.nan,
            "friction_angle_origin_deg": origin,
            "points": int(len(sigma)),
        }
    fit = stats.linregress(sigma, tau)
    enough = len(sigma) > 2
    slope_error = fit.stderr if enough else math.nan
    return {
        "friction_angle_deg": math.degrees(math.atan(fit.slope)),
        "friction_angle_se_deg": math.degrees(slope_error / (1 + fit.slope**2)) if enough else math.nan,
        "cohesion_pa": float(fit.intercept),
        "cohesion_se_pa": float(fit.intercept_stderr) if enough else math.nan,
        "tan_phi": float(fit.slope),
        "r_squared": float(fit.rvalue**2),
        "friction_angle_origin_deg": origin,
        "points": int(len(sigma)),
    }


def quasi_static_numbers(plan: LabPlan, geometry: ShearBox) -> list[dict]:
    """The dimensionless numbers of a shear test (docs/lab.md)."""
    return [
        common.quasi_static(
            "inertial number I",
            inertial_number(plan, geometry.speed, min(geometry.stresses)),
            1e-3,
            "(v / 10 d) d / sqrt(sigma / rho) at the lowest stress: quasi-static shear",
        ),
        common.stiffness_number(plan, max(geometry.stresses)),
    ]


def shear_test(
    plan: LabPlan,
    out_dir: str,
    overwrite: bool = False,
    executor: str = "serial",
    scheduler: str | None = None,
    workers: int | None = None,
) -> dict:
    """Settle lab.replicas specimens, shear each at every normal stress (through
    cosim.study.Executor), fit Mohr-Coulomb and write the report into out_dir (shear.csv,
    shear_points.csv, summary.json, shear.png). Returns the summary."""
    geometry = box(plan, check_memory=True)  # a box that cannot work is refused before the folder is touched
    with common.prepare_folder(plan, out_dir, overwrite, executor, scheduler):
        replicas = plan.scene.lab.replicas
        log.info(
            "shear: %d grains in a %.3g x %.3g m box, %.3g m high; normal stresses %s Pa; shear at %.3g m/s "
            "to %.3g m; %d replica(s)",
            geometry.count,
            geometry.length,
            geometry.width,
            geometry.height,
            ", ".join(f"{s:.4g}" for s in geometry.stresses),
            geometry.speed,
            geometry.displacement,
            replicas,
        )
        folder = os.path.join(out_dir, "specimens")
        os.makedirs(folder, exist_ok=True)
        paths = [os.path.join(folder, f"replica_{k}.h5") for k in range(replicas)]
        specimens = common.map_tasks(
            plan,
            run_replica,
            [{"replica": k, "stage": "specimen", "specimen": p} for k, p in enumerate(paths)],
            [f"specimen {k}" for k in range(replicas)],
            executor,
            scheduler,
            workers,
        )
        ready = common.successful(specimens, "shear specimen")
        jobs = [
            {"replica": s["replica"], "stage": "shear", "specimen": s["path"], "stress": sigma, "top": s["top"]}
            for s in ready
            for sigma in geometry.stresses
        ]
        results, stopped = common.map_until_stopped(
            plan,
            run_replica,
            jobs,
            [f"replica {j['replica']}, sigma {j['stress']:.4g} Pa" for j in jobs],
            executor,
            scheduler,
            workers,
        )
        done = common.successful(results, "shear")
        peak = mohr_coulomb([r["peak_sigma"] for r in done], [r["peak_tau"] for r in done])
        residual = mohr_coulomb([r["residual_sigma"] for r in done], [r["residual_tau"] for r in done])
        numbers = quasi_static_numbers(plan, geometry)
        notes = [
            f"replica {s['replica']}: the specimen had not settled within lab.max_time_factor"
            for s in ready
            if not s["settled"]
        ]
        notes += [
            f"replica {r['replica']}, sigma {r['stress']:.4g} Pa: the lid was still moving after consolidation"
            for r in done
            if not r["consolidated"]
        ]
        notes += [
            f"replica {r['replica']}, sigma {r['stress']:.4g} Pa: tau was still rising at the end of the travel (its "
            f"largest at {r['peak_displacement'] / r['displacement'][-1]:.0%} of it): the peak may lie beyond, and the "
            "second half is no residual; lengthen shear.displacement"
            for r in done
            if r["rising_at_end"]
        ]
        notes += common.interrupted_notes(stopped, len(results), len(jobs), "shear tests")
        if len({r["stress"] for r in done}) < 2:
            notes.append(
                "one normal stress sheared: no Mohr-Coulomb line (its friction angle and cohesion need two or more "
                "shear.normal_stresses); the angle with c = 0 assumes a cohesionless soil"
            )
        summary = {
            "test": "shear",
            "name": plan.name,
            "gravity": plan.g,
            "units": {"gravity": "m/s^2"},  # the other numbers: counts, or a unit in their key
            "soil": common.soil_summary(plan),
            "peak": peak,
            "residual": residual,
            "points": [
                {
                    "replica": r["replica"],
                    "normal_stress_nominal_pa": r["stress"],
                    "peak_sigma_pa": r["peak_sigma"],
                    "peak_tau_pa": r["peak_tau"],
                    "peak_displacement_m": r["peak_displacement"],
                    "residual_sigma_pa": r["residual_sigma"],
                    "residual_tau_pa": r["residual_tau"],
                    "consolidated": r["consolidated"],
                    "steps": r["steps"],
                }
                for r in done
            ],
            "failed": [
                {"label": r.get("label"), "error": r.get("error")} for r in specimens + results if not r.get("ok")
            ],
            "geometry": {
                "length_m": geometry.length,
                "width_m": geometry.width,
                "height_m": geometry.height,
                "gap_m": geometry.gap,
                "grains": geometry.count,
                "displacement_m": geometry.displacement,
                "speed_m_s": geometry.speed,
                "normal_stresses_pa": list(geometry.stresses),
                "grain_diameter_m": plan.diameter,
                "dt_s": plan.dt,
            },
            "quasi_static": numbers,
            "notes": notes,
        }
        curves = [
            (r["replica"], r["stress"], *row)
            for r in done
            for row in zip(r["displacement"], r["tau"], r["sigma"], r["tau_lower"], r["rise"])
        ]
        names = [
            ("replica", "1"),
            ("normal_stress_nominal", "Pa"),
            ("displacement", "m"),
            ("shear_stress", "Pa"),
            ("normal_stress", "Pa"),
            ("shear_stress_lower_half", "Pa"),
            ("lid_rise", "m"),
        ]
        columns = list(zip(*curves)) if curves else [() for _ in names]
        common.write_csv(
            os.path.join(out_dir, "shear.csv"), [(n, unit, column) for (n, unit), column in zip(names, columns)]
        )
        points: list[dict] = summary["points"]  # type: ignore[assignment]
        common.write_csv(
            os.path.join(out_dir, "shear_points.csv"),
            [
                ("replica", "1", [p["replica"] for p in points]),
                ("normal_stress_nominal", "Pa", [p["normal_stress_nominal_pa"] for p in points]),
                ("peak_normal_stress", "Pa", [p["peak_sigma_pa"] for p in points]),
                ("peak_shear_stress", "Pa", [p["peak_tau_pa"] for p in points]),
                ("residual_normal_stress", "Pa", [p["residual_sigma_pa"] for p in points]),
                ("residual_shear_stress", "Pa", [p["residual_tau_pa"] for p in points]),
            ],
        )
        summary["figure"] = _figure(out_dir, done, summary)
        common.write_summary(out_dir, summary)
        if stopped is not None:  # the finished tests' report is written: now stop as asked
            raise stopped
        return summary


def _figure(out_dir: str, done: list[dict], summary: dict) -> str | None:
    plt = common.pyplot()
    if plt is None:
        return None
    fig, (curves, mohr, rise) = plt.subplots(1, 3, figsize=(16, 4.5))
    stresses = sorted({r["stress"] for r in done})
    colours = {s: plt.cm.viridis(i / max(1, len(stresses) - 1)) for i, s in enumerate(stresses)}
    for r in done:
        label = f"{r['stress']:.3g} Pa" if r["replica"] == done[0]["replica"] else None
        curves.plot(r["displacement"] * 1e3, r["tau"], color=colours[r["stress"]], lw=1, label=label)
        curves.plot(r["peak_displacement"] * 1e3, r["peak_tau"], "v", color=colours[r["stress"]])
        rise.plot(r["displacement"] * 1e3, r["rise"] * 1e3, color=colours[r["stress"]], lw=1, label=label)
    curves.set_xlabel("shear displacement [mm]")
    curves.set_ylabel("shear stress [Pa]")
    curves.legend(title="normal stress", fontsize=8)
    rise.set_xlabel("shear displacement [mm]")
    rise.set_ylabel("lid rise (dilation) [mm]")
    top = max(r["peak_sigma"] for r in done) * 1.1
    for key, marker, style in (("peak", "o", "-"), ("residual", "s", "--")):
        fit = summary[key]
        mohr.plot(
            [r[f"{key}_sigma"] for r in done],
            [r[f"{key}_tau"] for r in done],
            marker,
            ls="none",
            label=f"{key}: phi {fit['friction_angle_deg']:.1f} deg, c {fit['cohesion_pa']:.3g} Pa",
        )
        if np.isfinite(fit["friction_angle_deg"]):
            s = np.array([0.0, top])
            mohr.plot(s, fit["cohesion_pa"] + s * fit["tan_phi"], style, color="grey")
    mohr.set_xlim(0, top)
    mohr.set_ylim(bottom=min(0.0, mohr.get_ylim()[0]))
    mohr.set_xlabel("normal stress [Pa]")
    mohr.set_ylabel("shear stress [Pa]")
    mohr.set_title("Mohr-Coulomb")
    mohr.legend(fontsize=8)
    fig.tight_layout()
    path = os.path.join(out_dir, "shear.png")
    save_figure(fig, path, 120)
    plt.close(fig)
    return path
