"""A direct shear box in LAMMPS: the peer of `cosim lab shear`.

The same test as cosim.lab.shear, given as numbers (`shear` needs numpy and LAMMPS only):
the same lattice fill, a rough floor plane at z = 0, two frames of four box walls each split
by the gap at the shear plane (`fix wall/gran/region` on blocks, side out), the same contact
model as lammps_peer.run_bed (Hertz from E and nu, Mindlin tangential spring with a Coulomb
limit mu = tan(phi), restitution damping, `limit_damping`; no rolling resistance) and the same
phases, checked every chunk as ours checks them:

    settle       the grains fall into the box until their translational kinetic energy
                 < settle_energy (after min_steps);
    consolidate  a rough lid plane, 0.1 r above the highest grain, carries the dead load
                 sigma L W until it has stopped sinking and carries its load within 5 %;
    shear        the upper frame and the lid move along +X at the shear speed (set once per record,
                 reached linearly over the first RAMP of the records) until the frame has moved
                 the displacement.

The loaded lid: a plane region whose height follows one extra atom (the lid atom: its own
type, excluded from every pair and wall, parked above the frames while the grains settle)
that carries the lid's mass and is pushed by `fix addforce` with the load + the grains' force
on the lid plane (the wall fix's `contacts` array, summed) - c v_z: the rigid body free along
-Z of soil.boundaries (mass the sample's, damper c critical against the sample's stiffness),
integrated by the same velocity Verlet as the grains, its force from the same step.

Measured from the wall fixes' contact forces at the end of every record, as ours:
tau = -(F_x on the upper frame + F_x on the lid) / (L W), sigma_n = (F_z on the lid + weight
of the grains above the shear plane) / (L W); peak and residual by cosim.lab.shear.strength,
the Mohr-Coulomb fits by cosim.lab.shear.mohr_coulomb.

Differences from ours:
- Ours settles a specimen once and restores it for every normal stress; here every normal
  stress settles the fill again in a fresh LAMMPS run (one rank: the same specimen each time,
  contact springs included).
- The lid's velocity in its contacts is the finite difference of the region's displacement
  over the step (ours carries the lid's velocity in the state); both integrate by velocity
  Verlet at the plan's step.
- LAMMPS has one friction coefficient (no separate stick and slip angles, no stick speed), so
  the comparison's soil has stick = slip angle and a stick speed far above any sliding speed.
  A sliding contact differs in a detail: LAMMPS's force follows the trial spring-dashpot force,
  its spring cut back to the Coulomb limit (dashpot included); ours is the spring's force, the
  spring cut along itself to the limit, no dashpot while cut (docs/physics.md section 1.3).
One MPI rank, units SI.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass

import numpy as np

from . import lammps_peer

_num = lammps_peer._num


@dataclass(frozen=True)
class ShearSetup:
    """A direct shear test in SI units (cosim.lab.shear.ShearBox and the plan's grains, as numbers)."""

    density: float
    youngs_modulus: float
    poisson: float
    friction: float
    """Coulomb coefficient of grains, floor and lid [-]."""
    wall_friction: float
    """Coulomb coefficient of the frames [-] (0: smooth)."""
    restitution: float
    length: float
    width: float
    plane: float
    """Height of the shear plane [m]."""
    gap: float
    wall: float
    """Frame wall thickness [m]."""
    top: float
    """Upper edge of the upper frame [m]."""
    displacement: float
    speed: float
    gravity: float
    """|g| along -Z [m/s^2]."""
    dt: float
    radius_mean: float
    records: int
    """Samples of a shear curve [-]."""
    ramp: float
    """Share of the records over which the shear speed rises linearly [-]."""
    chunk_steps: int
    """Steps between the settling checks [-]."""
    settle_energy: float
    """Settled when the grains' translational kinetic energy is below it [J]."""
    min_settle_steps: int
    max_settle_steps: int
    max_consolidate_time: float
    """Longest consolidation before the lid's own period caps it [s] (our max_phase_time)."""

    @property
    def area(self) -> float:
        return self.length * self.width

    def frames(self) -> list[tuple[tuple, tuple]]:
        """The eight frame boxes (lower corner, upper corner) [m], lower frame first (as ShearBox.frames)."""
        length, width, t = self.length, self.width, self.wall

        def frame(z0, z1):
            return [
                ((-t, -t, z0), (0.0, width + t, z1)),
                ((length, -t, z0), (length + t, width + t, z1)),
                ((0.0, -t, z0), (length, 0.0, z1)),
                ((0.0, width, z0), (length, width + t, z1)),
            ]

        return frame(0.0, self.plane - 0.5 * self.gap) + frame(self.plane + 0.5 * self.gap, self.top)


def _write_data(path, positions, radii, densities, types, lo, hi) -> None:
    """LAMMPS data file, atom_style sphere: id type diameter density x y z."""
    lines = ["regolith-cosim shear peer (SI units)", "", f"{len(radii)} atoms", "2 atom types", ""]
    lines += [f"{_num(lo[k])} {_num(hi[k])} {axis}lo {axis}hi" for k, axis in enumerate("xyz")]
    lines += ["", "Atoms # sphere", ""]
    for i, (p, r, rho, kind) in enumerate(zip(positions, radii, densities, types)):
        lines.append(f"{i + 1} {kind} {_num(2 * r)} {_num(rho)} {_num(p[0])} {_num(p[1])} {_num(p[2])}")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


class _Box:
    """A LAMMPS instance holding the shear box, its grains and the lid atom (idle until arm_lid)."""

    def __init__(self, setup: ShearSetup, positions, radii):
        s = setup
        n = len(radii)
        positions = np.asarray(positions, dtype=np.float64).reshape(n, 3)
        radii = np.asarray(radii, dtype=np.float64)
        self.setup, self.n, self.lid_id = s, n, n + 1
        self.sample_mass = float(np.sum(s.density * 4.0 / 3.0 * math.pi * radii**3))
        skin = 0.3 * float(radii.max())
        # the lid atom, parked above the frames until the lid is armed: as small as the smallest grain (the
        # neighbour cutoff follows the largest radius), as heavy as the sample (our lid's mass)
        lid_radius = float(radii.min())
        park = max(s.top, float(np.max(positions[:, 2] + radii))) + skin
        every = np.vstack([positions, [0.5 * s.length, 0.5 * s.width, park]])
        densities = np.append(np.full(n, s.density), self.sample_mass / (4.0 / 3.0 * math.pi * lid_radius**3))
        types = np.append(np.ones(n, dtype=int), 2)
        lo = [-s.wall - skin, -s.wall - skin, -skin]
        hi = [s.length + s.wall + s.displacement + skin, s.width + s.wall + skin, park + 2 * skin]  # frame moved
        grains = lammps_peer._granular_model(s.youngs_modulus, s.poisson, s.friction, s.restitution) + " limit_damping"
        walls = (
            lammps_peer._granular_model(s.youngs_modulus, s.poisson, s.wall_friction, s.restitution) + " limit_damping"
        )
        self.grains_model = grains
        self.lmp = lammps_peer._new_lammps()
        with tempfile.TemporaryDirectory() as tmp:
            data = os.path.join(tmp, "shear.data")
            _write_data(data, every, np.append(radii, lid_radius), densities, types, lo, hi)
            script = [
                "units si",
                "atom_style sphere",
                "atom_modify map array",
                "boundary f f fm",
                "newton off",
                "comm_modify vel yes",
                f"read_data {data}",
                "group grains type 1",
                "group lid type 2",
                "pair_style granular",
                f"pair_coeff * * {grains}",
                f"neighbor {_num(skin)} bin",
                "neigh_modify delay 0 every 1 check yes exclude type 1 2",
                "fix integrate all nve/sphere",
                f"fix floor grains wall/gran granular {grains} zplane 0.0 NULL contacts",
                "compute floor grains reduce sum f_floor[2] f_floor[4]",
                "variable shift equal 0.0",
            ]
            for k, (lower, upper) in enumerate(s.frames()):
                moving = " move v_shift NULL NULL units box" if k >= 4 else ""
                script.append(
                    f"region frame{k} block {_num(lower[0])} {_num(upper[0])} {_num(lower[1])} {_num(upper[1])} "
                    f"{_num(lower[2])} {_num(upper[2])} side out{moving}"
                )
                script.append(f"fix frame{k} grains wall/gran/region granular {walls} region frame{k} contacts")
                script.append(f"compute frame{k} grains reduce sum f_frame{k}[2] f_frame{k}[4]")
            script += [
                f"fix gravity grains gravity {_num(s.gravity)} vector 0 0 -1",
                "compute translation grains ke",
                f"timestep {_num(s.dt)}",
                "thermo 0",
                "run 0",
            ]
            for line in script:
                self.lmp.command(line)

    def run(self, steps: int) -> None:
        self.lmp.command(f"run {int(steps)} pre no post no")

    @property
    def step(self) -> int:
        return int(self.lmp.extract_global("ntimestep"))

    def energy(self) -> float:
        """Translational kinetic energy of the grains [J]."""
        return float(self.lmp.extract_compute("translation", 0, 0))

    def settle(self) -> tuple[int, bool]:
        """Run until the grains' translational kinetic energy < settle_energy (after min_settle_steps):
        (steps, whether the criterion ended it)."""
        s = self.setup
        steps = 0
        while steps < s.max_settle_steps:
            self.run(s.chunk_steps)
            steps += s.chunk_steps
            if steps >= s.min_settle_steps and self.energy() < s.settle_energy:
                return steps, True
        return steps, False

    def arm_lid(self, height: float, load: float, damping: float) -> None:
        """Put the lid plane at `height` [m], loaded with `load` [N] along -Z, its damper `damping` [N s/m]."""
        i = self.lid_id
        for line in (
            f"set atom {i} z {_num(height)} vx 0.0 vy 0.0 vz 0.0",
            f"variable sink equal z[{i}]-{_num(height)}",
            f"region lid plane 0 0 {_num(height)} 0 0 -1 side in move v_shift NULL v_sink units box",
            f"fix lid grains wall/gran/region granular {self.grains_model} region lid contacts",
            "compute lid grains reduce sum f_lid[2] f_lid[4]",
            # m a_z = -load + (grains' force on the lid)_z - c v_z; the wall fix gives the force on the grains
            f"variable lid_force equal -{_num(load)}-c_lid[2]-{_num(damping)}*vz[{i}]",
            "fix lid_load lid addforce 0.0 0.0 v_lid_force",
            "run 0",  # set the new fixes up (a run with pre no would not)
        ):
            self.lmp.command(line)

    def force(self, wall: str) -> np.ndarray:
        """(F_x, F_z) of the grains on a wall fix ('floor', 'frame0'..'frame7', 'lid') [N]."""
        on_grains = [self.lmp.extract_compute(wall, 0, 1)[k] for k in range(2)]
        return -np.array(on_grains)

    def lid_rise(self) -> float:
        """The lid's displacement along Z since it was armed [m]."""
        return float(self.lmp.extract_variable("sink"))

    def state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, radii, masses of the grains, in input order."""
        nlocal = self.lmp.extract_global("nlocal")
        order = np.argsort(np.array(self.lmp.numpy.extract_atom("id")[:nlocal]))[: self.n]

        def atoms(name):
            return np.array(self.lmp.numpy.extract_atom(name)[:nlocal])[order]

        return atoms("x"), atoms("radius"), atoms("rmass")

    def close(self) -> None:
        self.lmp.close()


def lid_dynamics(setup: ShearSetup, stress: float, mass: float, height: float) -> tuple[float, float]:
    """(damping [N s/m], period [s]) of the lid on a sample of `height` [m]: as cosim.lab.shear._lid_dynamics."""
    e_star = setup.youngs_modulus / (2 * (1 - setup.poisson**2))
    stiffness = setup.area * (e_star**2 * stress) ** (1 / 3) / height
    return 2 * math.sqrt(stiffness * mass), 2 * math.pi * math.sqrt(mass / stiffness)


def shear(setup: ShearSetup, positions, radii, stress: float, sample_height: float) -> dict:
    """Settle a fill (positions, radii [m]) into the box, consolidate it under `stress` [Pa] and shear it.

    sample_height: the nominal settled height H [m] (the lid's damper, as ours).
    Returns the curve (displacement [m], tau, sigma [Pa], tau_lower [Pa] the shear force on the
    lower frame and floor, rise [m]), settled, settle_time [s], consolidated, consolidate_time [s],
    weight_above [N], steps."""
    s = setup
    box = _Box(s, positions, radii)
    try:
        settle_steps, settled = box.settle()
        x, r, masses = box.state()
        load = stress * s.area
        damping, period = lid_dynamics(s, stress, box.sample_mass, sample_height)
        box.arm_lid(float(np.max(x[:, 2] + r)) + 0.1 * s.radius_mean, load, damping)
        chunk = max(1, round(0.5 * period / s.dt))
        longest = min(s.max_consolidate_time, 100 * period)
        max_steps, min_steps = round(longest / s.dt), 3 * period / s.dt
        steps, consolidated, last = 0, False, box.lid_rise()
        while steps < max_steps:
            box.run(min(chunk, max_steps - steps))
            steps += chunk
            if steps >= min_steps:
                # the grains carry the lid's load and it has stopped sinking (as ours)
                z = box.lid_rise()
                still = abs(z - last) < 5e-3 * s.radius_mean
                last = z
                if still and abs(box.force("lid")[1] - load) < 0.05 * load:
                    consolidated = True
                    break
        consolidate_time = steps * s.dt
        x, _, masses = box.state()
        weight_above = float(np.sum(masses[x[:, 2] > s.plane])) * s.gravity
        every = max(1, round(s.displacement / s.speed / s.dt) // s.records)
        ramp = s.ramp * s.records
        z0 = box.lid_rise()
        shift, rows, k = 0.0, [], 0
        while shift < s.displacement and k <= 2 * s.records + ramp:
            # as ours: the speed set once per record, reached linearly over the first records
            speed = s.speed * min(1.0, (k + 1) / ramp)
            box.lmp.command(f'variable shift equal "{_num(shift)}+{_num(speed * s.dt)}*(step-{box.step})"')
            box.run(every)
            shift += speed * every * s.dt
            k += 1
            upper = sum(box.force(f"frame{j}")[0] for j in range(4, 8))
            lower = sum(box.force(f"frame{j}")[0] for j in range(4))
            lid = box.force("lid")
            rows.append(
                (
                    shift,
                    -(upper + lid[0]) / s.area,
                    (lid[1] + weight_above) / s.area,
                    (lower + box.force("floor")[0]) / s.area,
                    box.lid_rise() - z0,
                )
            )
        x, _, _ = box.state()
        total_steps = box.step
    finally:
        box.close()
    if not np.all(np.isfinite(x)):
        raise RuntimeError("LAMMPS shear went non-finite")
    u, tau, sigma, tau_lower, rise = (np.array(c) for c in zip(*rows))
    return {
        "stress": stress,
        "displacement": u,
        "tau": tau,
        "sigma": sigma,
        "tau_lower": tau_lower,
        "rise": rise,
        "settled": settled,
        "settle_time": settle_steps * s.dt,
        "consolidated": consolidated,
        "consolidate_time": consolidate_time,
        "lid_damping": damping,
        "weight_above": weight_above,
        "steps": total_steps,
        "particles": len(radii),
    }


def lab_setup(plan, radii) -> ShearSetup:
    """The ShearSetup of a lab plan (cosim.lab.scene.LabPlan) for a fill of `radii` [m]: its box,
    grains, speed and phases. The plan's soil must be what LAMMPS models the same way: one friction
    angle (stick = slip, a stick speed far above any sliding speed), no rolling resistance, no
    cohesion, restitution given."""
    from cosim.lab import common
    from cosim.lab import shear as lab_shear

    soil = plan.soil
    if soil.stick_angle != soil.slip_angle or soil.rolling_friction or soil.cohesion or soil.restitution is None:
        raise ValueError(
            "the LAMMPS shear box models one friction angle (stick = slip), no rolling resistance, no "
            "cohesion and a restitution"
        )
    if plan.g <= 0:
        raise ValueError("the LAMMPS shear box settles its specimen under gravity (scene.gravity > 0)")
    geometry = lab_shear.box(plan)
    wall = plan.wall_material(plan.scene.shear.wall_friction_deg)
    mass = soil.density * 4.0 / 3.0 * math.pi * np.asarray(radii) ** 3
    energy_scale = len(mass) * float(mass.mean()) * plan.g * float(np.mean(radii))  # as common.kinetic_threshold
    return ShearSetup(
        density=soil.density,
        youngs_modulus=soil.youngs_modulus,
        poisson=soil.poisson_ratio,
        friction=math.tan(soil.stick_angle),
        wall_friction=math.tan(wall.stick_angle),
        restitution=soil.restitution,
        length=geometry.length,
        width=geometry.width,
        plane=geometry.plane,
        gap=geometry.gap,
        wall=geometry.wall,
        top=geometry.top,
        displacement=geometry.displacement,
        speed=geometry.speed,
        gravity=plan.g,
        dt=plan.dt,
        radius_mean=plan.radius_mean,
        records=lab_shear.RECORDS,
        ramp=lab_shear.RAMP,
        chunk_steps=int(round(common.chunk_steps(plan, plan.time_scale) / plan.dt)),
        settle_energy=plan.scene.bed.settle_ke_ratio * energy_scale,
        min_settle_steps=int(round(5 * plan.time_scale / plan.dt)),
        max_settle_steps=int(round(plan.max_phase_time(1.0) / plan.dt)),
        max_consolidate_time=plan.max_phase_time(1.0),
    )


def run_lab_shear(plan, replica: int = 0) -> dict:
    """The direct shear test of `cosim lab shear` for a lab plan and replica, in LAMMPS: the same
    fill, box, lid, shear speed, time step and phase criteria; one specimen sheared at each of the
    plan's normal stresses.

    Returns a dict with ``points`` (one per normal stress: stress, the curve displacement [m],
    tau, sigma, tau_lower [Pa], rise [m], peak_tau, peak_sigma, peak_displacement, residual_tau,
    residual_sigma as cosim.lab.shear.strength measures them, consolidated, ...), ``peak`` and
    ``residual`` (cosim.lab.shear.mohr_coulomb over this specimen's stresses), ``settled``,
    ``settle_time`` [s], ``replica`` and ``lammps_version``."""
    from cosim.lab import common
    from cosim.lab import shear as lab_shear

    geometry = lab_shear.box(plan)
    seed, _ = common.replica_seeds(plan, replica)
    positions, radii = common.lattice_fill(plan, (0, 0, 0), (geometry.length, geometry.width), geometry.count, seed)
    setup = lab_setup(plan, radii)
    points = []
    for stress in geometry.stresses:
        point = shear(setup, positions, radii, stress, geometry.height)
        points.append({**point, **lab_shear.strength(point["displacement"], point["tau"], point["sigma"])})
    fits = {
        state: lab_shear.mohr_coulomb([p[f"{state}_sigma"] for p in points], [p[f"{state}_tau"] for p in points])
        for state in ("peak", "residual")
    }
    return {
        "replica": replica,
        "points": points,
        **fits,
        "settled": all(p["settled"] for p in points),
        "settle_time": points[0]["settle_time"],
        "lammps_version": lammps_peer.lammps_version(),
    }


# 270 grains of 4 mm (+- 20 %) in a box 7 x 7 grains wide and 5 high (tests/test_lab.py's shear box), Earth
# gravity, normal stresses 1 and 2 kPa, inertial number 0.01. One friction coefficient (stick = slip angle,
# atan 0.5) and a stick speed far above any sliding speed: the Hertz-Mindlin-Coulomb model with restitution
# damping that LAMMPS runs; no rolling resistance; smooth frames, rough floor and lid.
COMPARISON_SCENE = """
[scene]
name = "shear_lammps"
gravity = "earth"
precision = "double"
device = "cpu"
[soil]
youngs_modulus = 5.0e6
poisson_ratio = 0.3
restitution = 0.3
stick_angle_deg = 26.565051177077986
slip_angle_deg = 26.565051177077986
stick_speed = 1000.0
rolling_friction = 0.0
[bed]
radius_mean = 0.002
settle_ke_ratio = 3e-3
[shear]
length = 0.028
width = 0.028
height = 0.02
displacement = 0.006
normal_stresses = [1000.0, 2000.0]
inertial_number = 0.01
"""


def specimen_angles(points) -> dict:
    """One specimen's friction angles through the origin [deg] (cosim.lab.shear.mohr_coulomb over its
    normal stresses): {'peak': ..., 'residual': ...}; points carry peak/residual _sigma and _tau."""
    from cosim.lab import shear as lab_shear

    return {
        state: lab_shear.mohr_coulomb([p[f"{state}_sigma"] for p in points], [p[f"{state}_tau"] for p in points])[
            "friction_angle_origin_deg"
        ]
        for state in ("peak", "residual")
    }


def compare(plan, replicas: int, out_dir: str, executor: str = "serial", workers: int | None = None) -> dict:
    """`replicas` specimens of ours (cosim.lab.shear.shear_test into out_dir) and of LAMMPS from the same
    fills (replica k: fill seed bed.seed + k). Returns, for 'ours' and 'lammps', the per-specimen peak and
    residual angles through the origin [deg] ('peak', 'residual': lists), their replica statistics
    ('peak_stats', 'residual_stats': cosim.lab.common.statistics) and the Mohr-Coulomb fits over every point
    ('peak_fit', 'residual_fit'), the statistics of the lid's rise at the end of every curve [m]
    ('rise_stats': dilation > 0) and each side's wall time [s]."""
    import time

    from cosim.lab import common
    from cosim.lab import shear as lab_shear

    plan = plan.with_changes({"lab.replicas": replicas})
    started = time.perf_counter()
    summary = lab_shear.shear_test(plan, out_dir, overwrite=True, executor=executor, workers=workers)
    ours_time = time.perf_counter() - started
    ours_points = [
        {
            "replica": p["replica"],
            "peak_sigma": p["peak_sigma_pa"],
            "peak_tau": p["peak_tau_pa"],
            "residual_sigma": p["residual_sigma_pa"],
            "residual_tau": p["residual_tau_pa"],
        }
        for p in summary["points"]
    ]
    ours = [specimen_angles([p for p in ours_points if p["replica"] == k]) for k in range(replicas)]
    curves = np.genfromtxt(os.path.join(out_dir, "shear.csv"), delimiter=",", names=True)
    ours_rise = []  # the lid's rise at the end of each curve (dilation > 0, compaction < 0)
    for p in summary["points"]:
        curve = (curves["replica_1"] == p["replica"]) & (
            curves["normal_stress_nominal_Pa"] == p["normal_stress_nominal_pa"]
        )
        ours_rise.append(float(curves["lid_rise_m"][curve][-1]))
    started = time.perf_counter()
    peer = [run_lab_shear(plan, k) for k in range(replicas)]
    lammps_time = time.perf_counter() - started
    lammps = [specimen_angles(r["points"]) for r in peer]
    lammps_points = [p for r in peer for p in r["points"]]

    def side(angles, points, rise, seconds, consolidated):
        out: dict = {"seconds": seconds, "consolidated": consolidated, "rise_stats": common.statistics(rise)}
        for state in ("peak", "residual"):
            out[state] = [a[state] for a in angles]
            out[f"{state}_stats"] = common.statistics(out[state])
            out[f"{state}_fit"] = lab_shear.mohr_coulomb(
                [p[f"{state}_sigma"] for p in points], [p[f"{state}_tau"] for p in points]
            )
        return out

    return {
        "replicas": replicas,
        "grains": lab_shear.box(plan).count,
        "ours": side(ours, ours_points, ours_rise, ours_time, all(p["consolidated"] for p in summary["points"])),
        "lammps": side(
            lammps,
            lammps_points,
            [float(p["rise"][-1]) for p in lammps_points],
            lammps_time,
            all(r["settled"] for r in peer) and all(p["consolidated"] for p in lammps_points),
        ),
        "lammps_version": peer[0]["lammps_version"] if peer else None,
    }
