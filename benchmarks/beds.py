"""Beds for the benchmarks: jittered lattices (no settling), settled random fills (settled once,
cached under benchmarks/cache), and wide beds tiled from a settled one.

Tiling: a settled bed's grains all lie inside its walls, so copies of it side by side, with
the inner walls removed, overlap at the seams by at most the grains' wall overlaps (nm):
a wide settled bed without settling it whole.
"""

from __future__ import annotations

import math
import os
import time
import warnings

import numpy as np

from soil import ContactLaw, Material, NeighbourSettings, Simulation, SoilBuilder

HERE = os.path.dirname(os.path.abspath(__file__))
CACHE = os.path.join(HERE, "cache")
DENSITY, YOUNGS, POISSON, MU, RESTITUTION = 2600.0, 1e7, 0.3, 0.5, 0.5
RADIUS = 2.5e-3
"""Mean grain radius of the benchmark beds [m]."""


def material() -> Material:
    """The benchmark grains: E = 10 MPa, e = 0.5, Coulomb friction mu = 0.5 (stick = slip angle, no
    stick speed: the model LAMMPS has)."""
    angle = math.atan(MU)
    return Material(
        youngs_modulus=YOUNGS,
        poisson_ratio=POISSON,
        density=DENSITY,
        restitution=RESTITUTION,
        stick_angle=angle,
        slip_angle=angle,
        stick_speed=1e9,
    )


def build(
    positions,
    radii,
    box_hi,
    device,
    precision,
    gravity=9.81,
    grains: Material | None = None,
    neighbours: NeighbourSettings | None = None,
    capture: bool = True,
    wheels=(),
    storage: str = "grain",
) -> Simulation:
    """A Simulation of the grains in an open-top box from the origin to box_hi [m]."""
    builder = SoilBuilder(gravity=gravity)
    mat = builder.add_material(grains or material())
    builder.add_container((0, 0, 0), box_hi, mat)
    builder.add_particles(positions, radii, mat)
    for wheel in wheels:
        builder.add_wheel(wheel, mat)
    law = ContactLaw(damping=True, friction=True, rolling=(grains or material()).rolling_friction > 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # lattice and tiled beds start with nm overlaps at most
        model, state, control = builder.finalize(device=device, precision=precision, law=law, storage=storage)
    return Simulation(model, state, control, neighbours=neighbours, capture=capture)


def lattice_bed(n: int, shape: str = "deep", radius: float = RADIUS, squeeze: float = 1e-3):
    """About n equal grains on a simple cubic lattice whose pitch is (1 - squeeze) diameters: every
    grain touches its six lattice neighbours (and the walls) from the first step, lightly
    pressed (the overlap, 2 r squeeze, carries a few grain weights at E = 10 MPa), so the bed
    stands still. shape 'deep': a cube of grains; 'shallow': 4 grains deep on a 2.5:1
    footprint (a rover bed). Returns positions [m] (n, 3), radii [m] (n,), box upper corner [m] (3,)."""
    pitch = 2.0 * radius * (1.0 - squeeze)
    if shape == "deep":
        nx = ny = nz = max(1, round(n ** (1 / 3)))
    elif shape == "shallow":
        nz = 4
        ny = max(1, round(math.sqrt(n / nz / 2.5)))
        nx = max(1, round(n / nz / ny))
    else:
        raise ValueError(f"shape must be 'deep' or 'shallow', got {shape!r}")
    grid = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    positions = radius * (1.0 - squeeze) + grid * pitch
    radii = np.full(len(grid), radius)
    box_hi = np.array(
        [
            (nx - 1) * pitch + 2 * radius * (1.0 - squeeze),
            (ny - 1) * pitch + 2 * radius * (1.0 - squeeze),
            max(1.0, 4 * nz * pitch),
        ]
    )
    return positions, radii, box_hi


def random_fill(n: int, side: float, seed: int = 0):
    """n grains (radius RADIUS +- 20 %) placed at random without overlap in a box side x side x 1 m."""
    from benchmarks.peers import lammps_peer

    box_hi = np.array([side, side, 1.0])
    positions, radii = lammps_peer.make_random_fill(n, RADIUS, 0.2, (0, 0, 0), box_hi, seed)
    return positions, radii, box_hi


def settled_bed(n: int, device: str = "cpu", seed: int = 0, settle_time: float = 0.15, log=print):
    """A random fill of n grains settled under Earth gravity with this code (double), cached.

    Beds above 50,000 grains are tiles of the settled 50,000-grain bed (n rounded to whole tiles).
    Returns positions [m], radii [m], box upper corner [m], dt [s] (0.2 Rayleigh steps)."""
    from benchmarks.peers import lammps_peer

    if n > 50000:
        tiles = max(1, round(n / 50000))
        tx = int(math.sqrt(tiles))
        while tiles % tx:
            tx -= 1
        positions, radii, box_hi, dt = settled_bed(50000, device, seed, settle_time, log)
        positions, radii, box_hi = tile(positions, radii, box_hi, tx, tiles // tx)
        return positions, radii, box_hi, dt
    side = 0.3 if n <= 20000 else 0.5
    positions, radii, box_hi = random_fill(n, side, seed)
    dt = 0.2 * lammps_peer.rayleigh_time_step(radii.min(), DENSITY, YOUNGS, POISSON)
    path = os.path.join(CACHE, f"bed_{n}_{seed}.npz")
    if os.path.exists(path):
        return np.load(path)["positions"], radii, box_hi, dt
    log(f"settling {n} grains ({settle_time} s at dt = {dt:.3g} s; cached in {path}) ...")
    sim = build(positions, radii, box_hi, device, "double")
    started = time.perf_counter()
    sim.run(settle_time, dt)
    log(f"  settled in {time.perf_counter() - started:.0f} s")
    settled = sim.positions()[np.argsort(sim.model.particle_order)]
    os.makedirs(CACHE, exist_ok=True)
    np.savez(path, positions=settled)
    return settled, radii, box_hi, dt


def tile(positions, radii, box_hi, nx: int, ny: int):
    """nx x ny copies of a bed side by side in x and y (its walls between them removed)."""
    shifts = [(i * box_hi[0], j * box_hi[1], 0.0) for i in range(nx) for j in range(ny)]
    tiled = np.concatenate([positions + np.asarray(s) for s in shifts])
    return tiled, np.tile(radii, nx * ny), np.array([nx * box_hi[0], ny * box_hi[1], box_hi[2]])
