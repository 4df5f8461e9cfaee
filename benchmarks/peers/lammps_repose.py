"""A heap formed by lifting a square tube, in LAMMPS: the peer of `cosim lab repose`.

The same scene as cosim.lab.repose, given as arrays (this module needs numpy and LAMMPS
only): fixed base grains, the grains in the tube, the tube's four wall boxes, smooth side
walls around the base, the same contact model as lammps_peer.run_bed (Hertz from E and nu,
Mindlin tangential spring with a Coulomb limit mu, restitution damping; no rolling
resistance) and the same phases, checked every `chunk_steps`:

    settle  until the grains' translational kinetic energy < settle_energy (and min_steps
            have passed; a grain spinning in place does not change the heap),
    lift    the tube's walls move up at lift_speed (`region ... move`, `fix wall/gran/region`)
            until their lower edge clears the highest grain by clearance,
    rest    the walls stop; until the translational kinetic energy < rest_energy (and min_steps).

Each phase ends after max_steps at the latest. One MPI rank, units SI.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np

from . import lammps_peer

_num = lammps_peer._num


def run_heap(
    base_positions,
    base_radius: float,
    positions,
    radii,
    density: float,
    youngs_modulus: float,
    poisson: float,
    friction_coefficient: float,
    restitution: float,
    tube_boxes,
    base_width: float,
    gravity: float,
    dt: float,
    lift_speed: float,
    clearance: float,
    chunk_steps: int,
    settle_energy: float,
    rest_energy: float,
    min_steps: int,
    max_steps: int,
) -> dict:
    """Settle the grains in the tube, lift it, let the heap come to rest.

    Args:
        base_positions: centres of the fixed base grains [m], shape (n_base, 3).
        base_radius: their radius [m].
        positions, radii: the grains in the tube [m], shapes (n, 3), (n,).
        density [kg/m^3], youngs_modulus [Pa], poisson [-], friction_coefficient [-] (grains and
            base; the walls are smooth), restitution [-] in (0, 1].
        tube_boxes: (lower, upper) corners [m] of the tube's wall boxes.
        base_width: side of the square box the side walls enclose (from 0) [m].
        gravity: |g| along -Z [m/s^2].
        dt: time step [s]; lift_speed [m/s]; clearance [m] above the highest grain.
        chunk_steps, min_steps, max_steps: steps between checks, before a phase may end, at most.
        settle_energy, rest_energy: thresholds of the grains' translational kinetic energy [J].

    Returns:
        dict with positions [m] (n, 3) and radii [m] (n,) of the grains at rest (input order),
        settle_time, lift_time, rest_time [s], settled, lifted, rested (phases ended by their
        criterion), lammps_version.
    """
    base_positions = np.asarray(base_positions, dtype=np.float64).reshape(-1, 3)
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    n_base = len(base_positions)
    every = np.concatenate([base_positions, positions])
    every_radius = np.concatenate([np.full(n_base, base_radius), radii])
    # limit_damping: the normal force never pulls (as ours: damping cannot make it attractive)
    grains = lammps_peer._granular_model(youngs_modulus, poisson, friction_coefficient, restitution) + " limit_damping"
    smooth = lammps_peer._granular_model(youngs_modulus, poisson, 0.0, restitution) + " limit_damping"
    top = max(float(np.max([upper[2] for _, upper in tube_boxes])), float(np.max(positions[:, 2] + radii)))
    skin = 0.3 * float(radii.max())
    lmp = lammps_peer._new_lammps()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            data = os.path.join(tmp, "heap.data")
            lammps_peer._write_data_file(
                data, every, every_radius, density, [0.0, 0.0, 0.0], [base_width, base_width, top + 2 * skin]
            )
            if n_base:  # fixed grains weigh as a wall in our contact law (m* = m of the moving grain)
                lines = open(data).read().splitlines()
                first = lines.index("Atoms # sphere") + 2
                for i in range(first, first + n_base):
                    fields = lines[i].split()
                    fields[3] = _num(1e9 * density)
                    lines[i] = " ".join(fields)
                with open(data, "w") as f:
                    f.write("\n".join(lines) + "\n")
            script = [
                "units si",
                "atom_style sphere",
                "atom_modify map array",
                "boundary f f fm",
                "newton off",
                "comm_modify vel yes",
                f"read_data {data}",
            ]
            script += (
                [f"group base id 1:{n_base}", "group mobile subtract all base"]
                if n_base
                else ["group mobile union all"]
            )
            script += [
                "pair_style granular",
                f"pair_coeff * * {grains}",
                f"neighbor {_num(skin)} bin",
                "neigh_modify delay 0 every 1 check yes" + (" exclude group base base" if n_base else ""),
                "fix integrate mobile nve/sphere",
                f"fix floor mobile wall/gran granular {grains} zplane 0.0 NULL",
                f"fix xwalls mobile wall/gran granular {smooth} xplane 0.0 {_num(base_width)}",
                f"fix ywalls mobile wall/gran granular {smooth} yplane 0.0 {_num(base_width)}",
                "variable lift equal 0.0",
            ]
            for k, (lower, upper) in enumerate(tube_boxes):
                # a union of regions cannot move in LAMMPS: one moving block (and one fix) per wall
                script.append(
                    f"region wall{k} block {_num(lower[0])} {_num(upper[0])} {_num(lower[1])} "
                    f"{_num(upper[1])} {_num(lower[2])} {_num(upper[2])} side out "
                    "move NULL NULL v_lift units box"
                )
                script.append(f"fix tube{k} mobile wall/gran/region granular {smooth} region wall{k}")
            script += [
                f"fix gravity mobile gravity {_num(gravity)} vector 0 0 -1",
                "compute translation mobile ke",
                f"timestep {_num(dt)}",
                "thermo 0",
                "run 0",
            ]
            for line in script:
                lmp.command(line)

        def energy():
            return lmp.extract_compute("translation", 0, 0)

        def state():
            nlocal = lmp.extract_global("nlocal")
            order = np.argsort(np.array(lmp.numpy.extract_atom("id")[:nlocal]))
            x = np.array(lmp.numpy.extract_atom("x")[:nlocal])[order]
            r = np.array(lmp.numpy.extract_atom("radius")[:nlocal])[order]
            return x[n_base:], r[n_base:]

        def phase(done, minimum):
            steps = 0
            while steps < max_steps:
                lmp.command(f"run {chunk_steps} pre no post no")
                steps += chunk_steps
                if steps >= minimum and done():
                    return steps, True
            return steps, False

        step = 0
        settle_steps, settled = phase(lambda: energy() < settle_energy, min_steps)
        step += settle_steps
        lmp.command(f'variable lift equal "{_num(lift_speed)}*(step-{step})*{_num(dt)}"')
        bottom = min(lower[2] for lower, _ in tube_boxes)

        def cleared():
            x, r = state()
            moved = lift_speed * (lmp.extract_global("ntimestep") - step) * dt
            return bottom + moved > np.max(x[:, 2] + r) + clearance

        lift_steps, lifted = phase(cleared, 0)
        lmp.command(f"variable lift equal {_num(lift_speed * lift_steps * dt)}")
        rest_steps, rested = phase(lambda: energy() < rest_energy, min_steps)
        x, r = state()
        version = int(lmp.version())
    finally:
        lmp.close()
    if not np.all(np.isfinite(x)):
        raise RuntimeError("LAMMPS heap went non-finite")
    return {
        "positions": x,
        "radii": r,
        "settle_time": settle_steps * dt,
        "lift_time": lift_steps * dt,
        "rest_time": rest_steps * dt,
        "settled": settled,
        "lifted": lifted,
        "rested": rested,
        "lammps_version": version,
    }


def run_lab_heap(plan, replica: int = 0) -> dict:
    """The heap of `cosim lab repose` for a lab plan (cosim.lab.scene.LabPlan) and replica, in LAMMPS:
    the same fill, base, tube, lift speed, time step and phase criteria. The plan's soil must
    be what LAMMPS models the same way: one friction angle (stick = slip, a stick speed far above
    any sliding speed), no rolling resistance, no cohesion, restitution given.
    Returns run_heap's dict plus the heap measured as cosim.lab.repose.measure_heap measures it."""
    import math

    from cosim.lab import common, repose

    soil = plan.soil
    if soil.stick_angle != soil.slip_angle or soil.rolling_friction or soil.cohesion or soil.restitution is None:
        raise ValueError(
            "the LAMMPS heap models one friction angle (stick = slip), no rolling resistance, no "
            "cohesion and a restitution"
        )
    geo = repose.geometry(plan, replica)
    chunk = int(round(common.chunk_steps(plan, plan.time_scale) / plan.dt))
    mass = soil.density * 4.0 / 3.0 * math.pi * geo.fill_radii**3
    scale = len(mass) * float(mass.mean()) * plan.g * float(geo.fill_radii.mean())  # as common.kinetic_threshold
    r_max = plan.radius_max
    result = run_heap(
        geo.base_positions,
        geo.base_radius,
        geo.fill_positions,
        geo.fill_radii,
        soil.density,
        soil.youngs_modulus,
        soil.poisson_ratio,
        math.tan(soil.stick_angle),
        soil.restitution,
        geo.tube_boxes(),
        geo.base_width,
        plan.g,
        plan.dt,
        geo.lift_speed,
        r_max,
        chunk,
        plan.scene.bed.settle_ke_ratio * scale,
        plan.scene.lab.rest_ke_ratio * scale,
        int(round(5 * plan.time_scale / plan.dt)),
        int(round(plan.max_phase_time(1.0) / plan.dt)),
    )
    section = plan.scene.repose
    heap = repose.measure_heap(
        result["positions"],
        result["radii"],
        geo.centre,
        geo.base_top,
        plan.diameter,
        section.sectors,
        section.fit_range,
    )
    return {**result, **heap}
