"""The GPU suite: one prepared command for an 8-9 minute window on one H100/H200.

    python benchmarks/gpu_suite.py                          # on cuda:0; results in runs/gpu_suite/
    python benchmarks/gpu_suite.py --small --device cpu     # the same checks, small, on the CPU
                                                            # (the test suite runs this: it cannot rot)
    python benchmarks/gpu_suite.py --device cpu --sections batched --worlds 1 4   # batching on a CPU
    python benchmarks/gpu_suite.py --sections batched --step-control pid          # batched PID worlds

Sections, each timed, in this order (the tests last, within what is left of --budget):

- throughput: a random fill settled on the device (Earth gravity, double), tiled to 100,000 and
  1,000,000 grains; particle-steps/s in single, mixed and double, and next to them the mixed
  layout: each precision's device bytes per grain, measured (Simulation.bytes_per_grain) and
  estimated (soil.memory). Targets at 1M: single >= 6e8 particle-steps/s, mixed >= 0.85 x and
  double >= 0.5 x single, mixed bytes per grain <= 0.75 x double's. The single and mixed rows
  again with the lists and contact history stored per slot (slot-major,
  `SoilBuilder.finalize(storage="slot")`, what neighbouring GPU threads read at once): their
  particle-steps/s against the per-grain rows (no target).
- profile: where a step's time goes, kernel by kernel, on the device (Warp's CUDA activity timing,
  `wp.timing_begin`): the steps of a 5,600-grain cut of the settled bed (the main job's size) and of
  the 100k and 1M beds in single (1M in mixed too) launched one by one, not replayed from a graph;
  per bed the wall per step, the kernels' sum per step and each kernel's share. A small scene's
  fixed cost per step and mixed's arithmetic show here. On the CPU it reports the wall per step
  only (the timing covers CUDA activity).
- repeat: a short coupled run (a grousered wheel resting pressed into a standing bed, driven
  through it by cosim.dem_soil.DemSoil) twice on the device: every wheel wrench and every grain bit for
  bit the same, with the wheel touching grains.
- agreement: the same short settling run on the CPU and on the device, as replicas whose
  grains start displaced by 1e-6 of a radius at random (and summed in another order): the
  device's bed statistics lie within the replicas' scatter. (Replicas differing in summation
  order alone scatter less than a GPU and a CPU differ in rounding in the first 0.1 s: on
  2026-12-04 the kinetic energy's replicas agreed to 8e-9 while the devices differed by 2e-7.)
- batched: replicas of the main job (examples/phobos_single_wheel.toml, mixed, landing off, a
  short drive) as K = 1, 4, 20 worlds of one simulation (cosim.batch.run_batched, the path of
  `cosim run --replicas K` on a GPU); the total particle-steps/s of the drive per K (target: 20
  worlds at least 10 x one), the DEM steps' share of the wall and the runs' host work per world
  per macro step (each run in a process of its own) with the serving process's part of it, the
  wheel's contact count, and whether world 0 of every batch gave its run alone (K = 1) bit for bit
  on the device. With --step-control pid every run takes PID substeps, each world under its own
  controller; the loop of a batch's substeps then runs as long as its slowest world, and the
  section reports that padding: the substeps the loop ran (per macro step the most any world
  tried) over the mean a world tried (1 alone).
- paper: the testbed scene at the paper's scale (examples/phobos_single_wheel_gpu.toml: Phobos
  regolith at Phobos gravity, here in double) run through cosim.launch.run_plan with the wheel in
  the grains: it lands under its 8 kg load and drives at the main job's imposed slip (testbed
  mode "slip", s = 0.1: the carriage's motion prescribed, the wheel free to sink). The bed is
  the scene's [bed] as 2 x 2 copies of one quarter of it settled here (202k grains; the whole
  bed, settled in one piece, holds 212k). 10 s of driving timed; the wheel's contact count
  (grains touching it) at every macro step, min / mean / max, fails the section if it drops to
  0 while driving; 60 s projected (target: at most 5 minutes).
- rover: a short segment of the full-size rover scene (examples/phobos_rover_gpu.toml: the
  MMX-like rover on a 1.1 m moving patch of about 770,000 grains, mixed): it drives 4 s from
  its placement, touching down as it goes (no landing phase: at Phobos gravity the rover is
  not at rest within the seconds a suite can spend); particle-steps/s and wall time per
  simulated second. Its [bed] (the tile the patch is copied from) is made 15 cm square so that
  it settles in seconds.
- tests: the CUDA variants of the soil tests (pytest -k cuda).

The paper and rover runs stop at their section's wall-clock allowance (SIZES) and report what
they reached. --small runs both scenes through the same code path, shrunk by scene overrides
(PAPER_OVERRIDES, ROVER_OVERRIDES: coarse grains, a small wheel, a stronger gravity so that
fractions of a second do, the rover without its landing): a check that the suite runs, not a
measurement.

Writes results.json (every figure) and results.md (a table with the targets) to --out, and to
--results too when given, after every section. On a lent machine (where Warp and MuJoCo travel as
benchmarks/gpu_carry.py's parts) run it as BENCHMARKS.md, "Running the GPU suite on a lent
machine", says.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import re
import subprocess
import sys
import time
import warnings

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import warp as wp  # noqa: E402

from benchmarks import beds  # noqa: E402
from cosim.batch import run_batched  # noqa: E402
from cosim.beds import settled_bed  # noqa: E402
from cosim.contract import WheelKinematics  # noqa: E402
from cosim.dem_soil import DemSoil  # noqa: E402
from cosim.folders import RunFolder  # noqa: E402
from cosim.launch import run_plan  # noqa: E402
from cosim.output import read_series  # noqa: E402
from cosim.plan import RunPlan, load_plan  # noqa: E402
from cosim.runner import RunInterrupted  # noqa: E402
from cosim.stop_signals import exit_status, stop_name  # noqa: E402
from soil import GrouserWheel, Simulation, SoilBuilder, quiet_warp  # noqa: E402
from soil.advisor import rayleigh_time_step  # noqa: E402
from soil.bed import bed_metrics, build_bed, kinetic_energy_threshold, save_bed  # noqa: E402
from soil.files import atomic_write_text  # noqa: E402
from soil.memory import device_bytes_per_grain  # noqa: E402

TEST_FILES = [
    "tests/test_neighbours.py",
    "tests/test_macro_step.py",
    "tests/test_contact_law.py",
    "tests/test_friction.py",
    "tests/test_integrator.py",
    "tests/test_energy.py",
    "tests/test_boundaries.py",
    "tests/test_stability.py",
    "tests/test_dem_soil_state.py",
]
SIZES = {
    # name: (full, small)
    "base": (20000, 300),  # grains of the settled bed the throughput beds are tiled from
    "tiles": ({"100k": (5, 1), "1M": (10, 5)}, {"100k": (2, 1), "1M": (2, 2)}),
    "throughput_steps": (200, 10),
    "profile_beds": (
        {"5.6k": 5642, "100k": (5, 1), "1M": (10, 5)},
        {"5.6k": 150, "100k": (2, 1), "1M": (2, 2)},
    ),  # a cut of the base bed (grains), or its tiles (nx, ny)
    "profile_steps": (20, 3),
    "repeat_macro_steps": (20, 3),
    "agreement": ((2000, 4, 0.1), (300, 2, 0.01)),  # grains, replicas, simulated seconds
    "paper_tiles": ((2, 2), (2, 1)),  # the scene's bed as nx x ny copies of one settled tile (202k grains)
    "paper_settle_seconds": (60.0, 30.0),  # wall-clock allowance of the tile's settling [s]
    "paper_seconds": (150.0, 60.0),  # wall-clock allowance of the coupled run [s]
    "rover_seconds": (150.0, 60.0),
    "batch_worlds": ((1, 4, 20), (1, 2)),
}
SOIL_LAYOUTS = (
    ("single", "grain"),
    ("mixed", "grain"),
    ("double", "grain"),
    ("single", "slot"),
    ("mixed", "slot"),
)
"""(precision, storage order) of the throughput rows: every precision stored per grain, and the two that
GPU runs use stored per slot (soil.state: the lists and history as neighbouring threads read them)."""
AGREEMENT_JITTER = 1e-6
"""The agreement section's replicas: their grains' start displaced by this fraction of a radius (rms, per axis)."""
TESTS_RESERVE = 60.0
"""Seconds of --budget the paper and rover runs leave for the sections after them [s]."""
WARMUP_STEPS = 10
"""Macro steps at the start of a scene run left out of its rates: the build, kernel loads, graph captures."""
PROFILE_ROWS = (("5.6k", "single"), ("100k", "single"), ("1M", "single"), ("1M", "mixed"))
"""(bed, precision) of the profile section."""
SECTIONS = ("throughput", "profile", "repeat", "agreement", "batched", "paper", "rover", "tests")
MAIN_SCENE = os.path.join(ROOT, "examples", "phobos_single_wheel.toml")
PAPER_SCENE = os.path.join(ROOT, "examples", "phobos_single_wheel_gpu.toml")
ROVER_SCENE = os.path.join(ROOT, "examples", "phobos_rover_gpu.toml")
QUIET_OUTPUT = {"output.snapshot_interval": 0.0, "output.checkpoint_interval": 1.0e9}
"""No snapshots but the first and last, no checkpoint but the last: the timed drive writes only its rows."""
PAPER_OVERRIDES = (
    {
        "scene.precision": "double",
        "testbed.mode": "slip",  # the main job's: the carriage driven at v = omega r (1 - s)
        "testbed.slip": 0.1,
        "run.duration": 10.0,
    },
    {  # the same scene shrunk, at Earth gravity (41 x faster in simulated time: fewer steps) with
        # a load to match: 8 mm grains, a 4 cm wheel of 50 g, 0.3 s of driving
        "scene.gravity": "earth",
        "bed.length": 0.25,
        "bed.width": 0.15,
        "bed.depth": 0.07,
        "bed.radius_mean": 0.008,
        "bed.settle_max_time": 0.5,
        "wheel.radius": 0.04,
        "wheel.width": 0.03,
        "wheel.grouser_count": 8,
        "wheel.grouser_height": 0.004,
        "wheel.grouser_thickness": 0.003,
        "testbed.mass": 0.05,
        "landing.max_time": 2.0,
        "run.duration": 0.3,
    },
)
"""Scene overrides of the paper section (full, small; small adds to full)."""
ROVER_OVERRIDES = (
    {
        "bed.length": 0.15,  # the tile the patch is copied from: settles in seconds, not minutes
        "bed.width": 0.15,
        "bed.settle_max_time": 15.0,
        # no landing phase: at Phobos gravity the rover was still not at rest (1 s held) after 8 s of it
        # (2026-12-04), and the scene's own allows 120 s; it drives as it touches down
        "landing.enabled": False,
        "run.duration": 4.0,
    },
    {  # the full-size rover (its 25 kg: lighter wheels would make the coupling stiff) at 0.2 m/s^2
        # (it touches down sooner than at Phobos gravity, the soil still holding it) on 1.5 cm
        # grains: a 1.25 m patch of about 2,000 of them, 0.7 s of driving
        "scene.gravity": 0.2,
        "bed.length": 0.3,
        "bed.width": 0.3,
        "bed.depth": 0.075,
        "bed.radius_mean": 0.015,
        "bed.settle_max_time": 1.5,
        "patch.length": 1.25,  # the least window that holds the rover, the clearance and the band
        "patch.width": 1.25,
        "patch.band": 0.06,
        "patch.clearance": 0.06,
        "patch.tile_margin": 0.0,
        "run.duration": 0.7,  # (its wheels touch down after 0.2-0.55 s)
    },
)
"""Scene overrides of the rover section (full, small; small adds to full)."""
BATCH_OVERRIDES = (
    {"landing.enabled": False, "run.duration": 1.5},  # the wheel touches down within 0.2 s
    {  # a coarse bed at lunar gravity, stiffened to stay valid there (tests/helpers.py's tiny scene):
        # fractions of a second do
        "scene.gravity": "moon",
        "soil.youngs_modulus": 1.0e6,
        "run.dt_factor": 0.25,  # 10 steps per contact time
        "bed.length": 0.12,
        "bed.width": 0.06,
        "bed.depth": 0.03,
        "bed.radius_mean": 0.0035,
        "bed.settle_max_time": 0.3,
        "wheel.radius": 0.025,
        "wheel.width": 0.02,
        "wheel.grouser_height": 0.003,
        "testbed.omega": 1.0,
        "run.duration": 0.15,
    },
)
"""Scene overrides of the batched section (full, small; small adds to full)."""


RESULT_UNITS = {
    **dict.fromkeys(("dt", "seconds", "simulated_seconds", "wall_seconds", "timed_seconds"), "s"),
    **dict.fromkeys(("drive_simulated_seconds", "drive_timed_simulated_seconds", "drive_wall_seconds"), "s"),
    **dict.fromkeys(("landing_simulated_seconds", "projected_60s_seconds", "wall_per_simulated_second"), "s"),
    **dict.fromkeys(("host_ms_per_world_step", "serve_ms_per_world_step"), "ms"),
    **dict.fromkeys(("wall_us_per_step", "kernel_us_per_step", "us_per_step"), "us"),
    "share": "1",
    **dict.fromkeys(("particle_steps_per_second", "landing_particle_steps_per_second"), "1/s"),
    **dict.fromkeys(("bytes_per_grain", "bytes_per_grain_estimate"), "B"),
    **dict.fromkeys(("mean_height", "top"), "m"),  # the agreement's: cpu_mean, device_mean, replica_scatter
    **dict.fromkeys(("kinetic_energy", "threshold"), "J"),
    **dict.fromkeys(("slip", "dem_share_of_wall", "loop_padding", "x_double", "x_single", "x_one_world"), "1"),
    **dict.fromkeys(("particle_steps_x_single", "x_grain_storage", "substeps_per_macro_step"), "1"),
    **dict.fromkeys(("grains", "grains_max", "grains_min", "grains_per_world", "bed_grains", "tile_grains"), "count"),
    **dict.fromkeys(("tiles", "worlds", "steps", "substeps", "macro_steps", "drive_steps"), "count"),
    **dict.fromkeys(("contact_capacity", "contacts_per_grain", "wheel_contacts_min", "wheel_contacts_mean"), "count"),
    **dict.fromkeys(("wheel_contacts_max", "drive_min", "drive_mean", "drive_max"), "count"),
    **dict.fromkeys(("landing_min", "landing_mean", "landing_max"), "count"),
}
"""The unit of each figure results.json holds, by its name wherever it appears (a scene override: its key's,
cosim.scene.key_unit); drive_* and landing_*: the grains touching a wheel."""


def _figure(value) -> str:
    """A table's figure to 2 decimals, '-' when not measured."""
    return "-" if value is None else f"{value:.2f}"


def size(name, small):
    return SIZES[name][1 if small else 0]


def resting_height(sim, wheel: GrouserWheel, x: float, y: float) -> float:
    """Hub height [m] at which the wheel (a cylinder of its outer radius, axle along y, hub above
    (x, y)) rests on the highest grain under it."""
    p = sim.positions()
    radius = sim.model.radius_numpy()
    reach = wheel.outer_radius + radius
    dx = p[:, 0] - x
    under = (np.abs(dx) < reach) & (np.abs(p[:, 1] - y) < 0.5 * wheel.width + radius)
    return float(np.max(p[under, 2] + np.sqrt(reach[under] ** 2 - dx[under] ** 2)))


def kernel_name(timed: str) -> str:
    """A kernel's own name from Warp's timing name ('forward kernel soil__solver__contact_kernels__locals__
    grain_contacts_1a2b3c4d' -> 'grain_contacts'); builtin kernels keep theirs."""
    if not timed.startswith("forward kernel "):
        return timed
    return re.sub(r"_[0-9a-f]{8}$", "", timed.removeprefix("forward kernel ")).split("__")[-1]


class OutOfTime(Exception):
    """A section's wall-clock allowance ran out in a coupled run: the run stops, its figures so far stand."""


class Suite:
    def __init__(
        self, device: str, small: bool, budget: float, out: str, results: str | None = None, step_control="fixed"
    ):
        self.device, self.small, self.budget, self.out = device, small, budget, out
        self.step_control = step_control
        """The batched section's DEM steps: 'fixed' or 'pid' (run.step_control)."""
        self.results_dirs = list(dict.fromkeys([out, results or out]))
        """Where results.json and results.md go after every section (--out, and --results: a lent
        machine's $OUT, so that a command stopped at its time limit still returns the sections done)."""
        self.started = time.perf_counter()
        self.results: dict = {"device": device, "small": small, "machine": self.machine(), "sections": {}}

    def machine(self) -> str:
        if self.device.startswith("cuda"):
            return f"{wp.get_device(self.device).name}, Warp {wp.__version__}"
        return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Warp {wp.__version__}"

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def allowance(self, name: str) -> float:
        """Wall clock [s] a timed part may take: its SIZES entry, within what is left of --budget
        after TESTS_RESERVE for the tests (at least 30 s)."""
        return min(size(name, self.small), max(30.0, self.budget - self.elapsed() - TESTS_RESERVE))

    def log(self, text: str) -> None:
        print(f"[{self.elapsed():6.1f} s] {text}", flush=True)

    def section(self, name, function):
        start = time.perf_counter()
        self.log(f"{name} ...")
        stop = None
        try:
            result = function()
            result["ok"] = bool(result.get("ok", True))
        except (KeyboardInterrupt, RunInterrupted) as error:  # Ctrl-C or SIGTERM: the suite ends here
            result, stop = {"ok": False, "error": f"stopped: {error}"}, error
        except Exception as error:  # the suite reports a failed section and goes on
            result = {"ok": False, "error": f"{type(error).__name__}: {error}"}
        result["seconds"] = time.perf_counter() - start
        self.results["sections"][name] = result
        self.log(
            f"{name}: {'ok' if result['ok'] else 'FAILED'} ({result['seconds']:.1f} s) "
            f"{json.dumps({k: v for k, v in result.items() if not isinstance(v, (list, dict))})}"
        )
        self.write()  # what the suite measured so far is kept, stopped or not
        if stop is not None:  # named by its signal: main's exit status says which (cosim.stop_signals)
            name = stop_name(stop)
            raise KeyboardInterrupt(f"{name}: {stop}")

    # -- sections -------------------------------------------------------------------------
    def base_bed(self):
        """A random fill settled on the device under Earth gravity (double)."""
        if not hasattr(self, "_base"):
            n = size("base", self.small)
            side = 0.2 * (n / 20000) ** 0.5 if not self.small else 0.03
            positions, radii, box_hi = beds.random_fill(n, side, seed=0)
            dt = 0.2 * rayleigh_time_step(beds.YOUNGS, beds.POISSON, beds.DENSITY, radii.min())
            sim = beds.build(positions, radii, box_hi, self.device, "double")
            sim.run(0.01 if self.small else 0.1, dt)
            self._base = (sim.positions()[np.argsort(sim.model.particle_order)], radii, box_hi, dt)
        return self._base

    def throughput(self):
        positions, radii, box_hi, dt = self.base_bed()
        steps = size("throughput_steps", self.small)
        rows = []
        for label, (tx, ty) in size("tiles", self.small).items():
            tiled, tiled_radii, tiled_box = beds.tile(positions, radii, box_hi, tx, ty)
            for precision, storage in SOIL_LAYOUTS:
                sim = beds.build(tiled, tiled_radii, tiled_box, self.device, precision, storage=storage)
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    sim.macro_step(20, dt)
                    wp.synchronize_device(self.device)
                    start = time.perf_counter()
                    sim.macro_step(steps, dt)
                    seconds = time.perf_counter() - start
                sim.arm_monitor()  # its last good state is device memory every run holds (after the timing)
                n = len(tiled_radii)
                rows.append(
                    dict(
                        bed=label,
                        grains=n,
                        precision=precision,
                        storage=storage,
                        steps=steps,
                        seconds=seconds,
                        particle_steps_per_second=n * steps / seconds,
                        captured=sim.capture,
                        warnings=[str(w.message) for w in caught],
                        bytes_per_grain=sim.bytes_per_grain()["total"],
                        bytes_per_grain_estimate=device_bytes_per_grain(precision, sim.state.capacity),
                        contact_capacity=sim.state.capacity,
                        contacts_per_grain=float(sim.contact_counts().mean()),
                    )
                )
                self.log(json.dumps(rows[-1]))
                del sim
        slot_rows = [r for r in rows if r["storage"] == "slot"]
        rows = [r for r in rows if r["storage"] == "grain"]
        rate = {(r["bed"], r["precision"]): r["particle_steps_per_second"] for r in rows}
        memory = {(r["bed"], r["precision"]): r["bytes_per_grain"] for r in rows}
        for r in slot_rows:
            r["x_grain_storage"] = r["particle_steps_per_second"] / rate[(r["bed"], r["precision"])]
        single = rate[("1M", "single")]
        layout = {
            precision: {
                "bytes_per_grain": memory[("1M", precision)],
                "x_double": memory[("1M", precision)] / memory[("1M", "double")],
                "particle_steps_x_single": rate[("1M", precision)] / single,
            }
            for precision in ("single", "mixed", "double")
        }
        targets = {
            "single at 1M >= 6e8 particle-steps/s": single >= 6e8,
            "double >= 0.5 x single at 1M": rate[("1M", "double")] >= 0.5 * single,
            "mixed >= 0.85 x single at 1M": rate[("1M", "mixed")] >= 0.85 * single,
            "mixed layout: bytes per grain <= 0.75 x double at 1M": layout["mixed"]["x_double"] <= 0.75,
        }
        return {"rows": rows, "slot_rows": slot_rows, "layout": layout, "targets": targets, "ok": True}

    def profile_bed(self, label: str):
        """The profile section's bed: a cut of the base bed holding `grains` (its first grains along x,
        the box shortened to them) or the base bed tiled."""
        positions, radii, box_hi, dt = self.base_bed()
        spec = size("profile_beds", self.small)[label]
        if isinstance(spec, tuple):
            return (*beds.tile(positions, radii, box_hi, *spec), dt)
        keep = np.argsort(positions[:, 0], kind="stable")[:spec]
        box = box_hi.copy()
        box[0] = float(np.max(positions[keep, 0] + radii[keep]))
        return positions[keep], radii[keep], box, dt

    def profile(self):
        steps = size("profile_steps", self.small)
        cuda = self.device.startswith("cuda")
        rows = []
        for label, precision in PROFILE_ROWS:
            positions, radii, box_hi, dt = self.profile_bed(label)
            sim = beds.build(positions, radii, box_hi, self.device, precision, capture=False)
            sim.macro_step(5, dt)  # kernels loaded, scratch sized
            wp.synchronize_device(self.device)
            if cuda:
                wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_KERNEL_BUILTIN)
            start = time.perf_counter()
            sim.macro_step(steps, dt)
            wp.synchronize_device(self.device)
            wall = time.perf_counter() - start
            timings = wp.timing_end() if cuda else []
            kernels: dict[str, float] = {}
            for timing in timings:
                name = kernel_name(timing.name)
                kernels[name] = kernels.get(name, 0.0) + timing.elapsed * 1e3 / steps  # [us per step]
            kernel_sum = sum(kernels.values())
            rows.append(
                dict(
                    bed=label,
                    grains=len(radii),
                    precision=precision,
                    steps=steps,
                    wall_us_per_step=wall * 1e6 / steps,
                    kernel_us_per_step=kernel_sum if cuda else None,
                    kernels=[
                        dict(name=name, us_per_step=us, share=us / kernel_sum)
                        for name, us in sorted(kernels.items(), key=lambda item: -item[1])
                    ],
                )
            )
            self.log(json.dumps({k: v for k, v in rows[-1].items() if k != "kernels"}))
            del sim
        return {"rows": rows, "timed": "CUDA kernels" if cuda else "wall only (Warp times CUDA activity)"}

    def coupled_run(self):
        """A grousered wheel (radius 2 cm) resting on a standing bed (a pressed lattice: no
        settling needed), pressed in by a grain radius and driven into and along it by DemSoil
        with 20 % slip."""
        positions, radii, box_hi = beds.lattice_bed(size("base", self.small), "shallow")
        dt = 0.2 * rayleigh_time_step(beds.YOUNGS, beds.POISSON, beds.DENSITY, radii.min())
        wheel = GrouserWheel(radius=0.02, width=0.012, grouser_count=8, grouser_height=0.002, grouser_thickness=0.0015)
        builder = SoilBuilder(gravity=9.81)
        mat = builder.add_material(beds.material())
        builder.add_container((0, 0, 0), box_hi, mat)
        builder.add_particles(positions, radii, mat)
        builder.add_wheel(wheel, mat)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model, state, control = builder.finalize(self.device, "double")
        soil = DemSoil(Simulation(model, state, control), dt, surface_height=0.0)
        centre = (0.5 * box_hi[0], 0.5 * box_hi[1])
        hub = np.array([*centre, resting_height(soil.sim, wheel, *centre) - beds.RADIUS])
        velocity = np.array([0.1, 0.0, -0.01])
        spin = np.array([0.0, 1.2 * velocity[0] / wheel.radius, 0.0])
        wrenches = []
        macro = 10 * dt
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for k in range(size("repeat_macro_steps", self.small)):
                start = WheelKinematics(hub + velocity * k * macro, [1.0, 0, 0, 0], velocity, spin)
                w = soil.advance((k + 1) * macro, [start])[0]
                wrenches.append(np.r_[w.force, w.torque, w.work_on_soil, w.contact_count])
        return np.array(wrenches), soil.sim.positions(), soil.sim.velocities()

    def repeat(self):
        first, second = self.coupled_run(), self.coupled_run()
        same = all(np.array_equal(a, b) for a, b in zip(first, second))
        touching = float(first[0][:, 7].max())
        return {"bitwise_equal": same, "wheel_contacts_max": touching, "ok": same and touching > 0}

    def settle_statistics(self, device: str, n: int, replicas: int, duration: float) -> list[dict]:
        """Bed statistics of `replicas` settling runs: replica k's grains start displaced at random by
        AGREEMENT_JITTER of their radius (seed k; the same displacements on every device) and are summed
        in order k. Such a displacement is macroscopically nothing, and its effect outgrows any rounding
        difference between devices: the replicas' scatter is what 'the same run' can mean."""
        positions, radii, box_hi = beds.random_fill(n, 0.1 if not self.small else 0.03, seed=3)
        dt = 0.2 * rayleigh_time_step(beds.YOUNGS, beds.POISSON, beds.DENSITY, radii.min())
        stats = []
        for seed in range(replicas):
            jitter = np.random.default_rng(seed).normal(0.0, AGREEMENT_JITTER, positions.shape) * radii[:, None]
            builder = SoilBuilder(gravity=9.81)
            mat = builder.add_material(beds.material())
            builder.add_container((0, 0, 0), box_hi, mat)
            builder.add_particles(positions + jitter, radii, mat)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                sim = Simulation(*builder.finalize(device, "double", order_seed=seed))
            sim.run(duration, dt)
            z = sim.positions()[:, 2]
            stats.append(
                {
                    "mean_height": float(z.mean()),
                    "top": float(np.max(z + sim.model.radius_numpy())),
                    "kinetic_energy": sim.kinetic_energy(),
                }
            )
        return stats

    def agreement(self):
        n, replicas, duration = size("agreement", self.small)
        cpu = self.settle_statistics("cpu", n, replicas, duration)
        device = self.settle_statistics(self.device, n, replicas, duration)
        verdict = {}
        for key in ("mean_height", "top", "kinetic_energy"):
            a = np.array([s[key] for s in cpu])
            b = np.array([s[key] for s in device])
            scatter = math.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b)) if len(a) > 1 else 0.0
            allowed = 4.0 * scatter + 1e-9 * abs(a.mean())
            verdict[key] = {
                "cpu_mean": float(a.mean()),
                "device_mean": float(b.mean()),
                "replica_scatter": scatter,
                "agrees": bool(abs(a.mean() - b.mean()) <= allowed),
            }
        return {"statistics": verdict, "ok": all(v["agrees"] for v in verdict.values())}

    def batched(self):
        """Replicas of the main job as K worlds of one simulation (module docstring)."""
        overrides = {**self.scene_overrides(BATCH_OVERRIDES), "run.step_control": self.step_control}
        folder = os.path.join(self.out, "batched")
        bed = settled_bed(load_plan(MAIN_SCENE, overrides), folder)
        overrides["bed.bed_file"] = os.path.abspath(bed.path)

        def padding(every) -> float:
            """The substeps a batch's loop ran over those a world tried, the worlds' series `every`: per
            macro step the loop runs as long as the world that tried most (accepted and rejected)."""
            tried = np.array([s["soil_dem_steps"] + s["soil_dem_steps_rejected"] for s in every], dtype=float)
            return float(tried.max(axis=0).sum() / tried.mean(axis=0).sum()) if tried.sum() > 0 else 1.0

        def row(worlds, series, marks, dem_seconds, failed, serve_marks=None, every=None) -> dict:
            """The figures of a drive whose macro steps ended at host clock `marks` [s] (the DEM steps'
            own host clock per macro step `dem_seconds`, and the serving process's own host work so far
            at the end of each macro step `serve_marks` [s], None when not measured; `every`: every
            world's series)."""
            timed = slice(WARMUP_STEPS, len(marks))
            seconds = float(marks[-1] - marks[WARMUP_STEPS - 1]) if len(marks) > WARMUP_STEPS else 0.0
            grains = float(series["soil_particle_count"][0])
            # every world's own steps (under the PID step control each world takes its own)
            steps = float(sum(s["soil_dem_steps"][timed].sum() for s in (every or [series] * worlds)))
            counts = series["contact_count"][:, 0]
            dem = None if dem_seconds is None else float(np.sum(dem_seconds[timed]))
            return dict(
                worlds=worlds,
                grains_per_world=grains,
                macro_steps=len(marks),
                timed_seconds=seconds,
                particle_steps_per_second=grains * steps / seconds if seconds > 0 else 0.0,
                dem_share_of_wall=dem / seconds if dem is not None and seconds > 0 else None,
                host_ms_per_world_step=None
                if dem is None
                else 1e3 * (seconds - dem) / max(worlds * (len(marks) - WARMUP_STEPS), 1),
                serve_ms_per_world_step=None
                if serve_marks is None or len(serve_marks) <= WARMUP_STEPS
                else 1e3
                * (serve_marks[-1] - serve_marks[WARMUP_STEPS - 1])
                / (worlds * (len(serve_marks) - WARMUP_STEPS)),
                wheel_contacts_min=int(counts[len(counts) // 2 :].min()),
                wheel_contacts_mean=float(counts.mean()),
                substeps_per_macro_step=float(np.mean([s["soil_dem_steps"].mean() for s in every or [series]])),
                loop_padding=padding(every or [series]),
                failed=failed,
            )

        # the reference: world 0's replica run alone (cosim.launch.run_plan, as `cosim run` does)
        plan = load_plan(MAIN_SCENE, {**overrides, "run.order_seed": 0})
        out_alone = os.path.join(folder, "alone")
        marks: list[float] = []
        status = run_plan(plan, out_alone, overwrite=True, hooks={"step": lambda r: marks.append(time.perf_counter())})
        series = read_series(RunFolder(out_alone).results)
        alone = {
            **row(1, series, marks, None, [] if status.status in ("complete", "unsteady") else [status.status]),
            "worlds": "alone",
        }
        forces = {"alone": series["force"]}
        rows = [alone]
        for worlds in size("batch_worlds", self.small):
            plans = [load_plan(MAIN_SCENE, {**overrides, "run.order_seed": k}) for k in range(worlds)]
            out_dirs = [os.path.join(folder, f"worlds_{worlds}", f"replica_{k:03d}") for k in range(worlds)]
            results = run_batched(plans, out_dirs, overwrite=True)
            stopped = [r for r in results if r.get("status") == "interrupted" or r.get("stop_received")]
            if stopped:  # a stop the batch received ends the suite, as it ends a study (cosim.study._run_tasks)
                raise KeyboardInterrupt(stopped[0].get("stop_received") or "SIGINT: the batched runs stopped")
            batch = results[0]["batch"]
            failed = [r.get("error") for r in results if not r.get("ok")]
            every = [read_series(RunFolder(d).results) for d, r in zip(out_dirs, results) if r.get("ok")]
            series = read_series(RunFolder(out_dirs[0]).results)
            rows.append(
                row(
                    worlds,
                    series,
                    batch["round_ends"],
                    np.asarray(batch["round_steps"]),
                    failed,
                    batch["serve_marks"],
                    every,
                )
            )
            forces[worlds] = series["force"]
            self.log(json.dumps(rows[-1]))
        one = rows[0]["particle_steps_per_second"]
        for r in rows:
            r["x_one_world"] = r["particle_steps_per_second"] / one if one > 0 else 0.0
        same = all(np.array_equal(forces["alone"], f) for f in forces.values())
        most = rows[-1]
        return {
            "scene": os.path.relpath(MAIN_SCENE, ROOT),
            "overrides": overrides,
            "step_control": self.step_control,
            "rows": rows,
            "world_0_as_alone": same,
            "targets": {
                f"batched: {most['worlds']} worlds of the main job >= 10 x the particle-steps/s of one": most[
                    "x_one_world"
                ]
                >= 10.0,
                "batched: world 0 of every batch is its run alone, bit for bit": same,
            },
            "ok": same and not any(row["failed"] for row in rows) and all(r["wheel_contacts_min"] > 0 for r in rows),
        }

    def paper(self):
        """The testbed scene at the paper's scale, its wheel landed in the grains and driven at the
        main job's slip (module docstring)."""
        overrides = self.scene_overrides(PAPER_OVERRIDES)
        plan = load_plan(PAPER_SCENE, overrides)
        bed_path, settling = self.tiled_bed(plan, size("paper_tiles", self.small), "paper_bed.h5")
        plan = load_plan(PAPER_SCENE, {**overrides, "bed.bed_file": bed_path})
        run = self.scene_run(plan, "paper_run", self.allowance("paper_seconds"))
        contacts = run.pop("contacts")
        wheel = {k: v[0] for k, v in contacts.items()}  # the testbed has one wheel
        per_second = run["wall_per_simulated_second"]
        projected = None if per_second is None else 60.0 * per_second
        touching = run["drive_steps"] > 0 and wheel["drive_min"] > 0
        result = {
            "scene": os.path.relpath(PAPER_SCENE, ROOT),
            "overrides": overrides,
            "precision": plan.precision,
            "dt": plan.dt,
            "substeps": plan.substeps,
            "slip": plan.testbed.slip if plan.testbed else None,
            "settling": settling,
            **run,
            "wheel_contacts": wheel,
            "projected_60s_seconds": projected,
            "targets": {
                "paper: 60 s of Phobos driving in at most 5 minutes (double)": projected is not None
                and projected <= 300.0,
                "paper: the wheel touches grains at every macro step of the drive": touching,
            },
        }
        problems = self.drive_problems(run, plan)
        if run["drive_steps"] and not touching:
            problems.append("the wheel lost every grain contact while driving")
        result["ok"] = not problems
        if problems:
            result["error"] = "; ".join(problems)
        return result

    def rover(self):
        """A few seconds of the full-size rover scene after its landing (module docstring)."""
        overrides = self.scene_overrides(ROVER_OVERRIDES)
        plan = load_plan(ROVER_SCENE, overrides)
        run = self.scene_run(plan, "rover_run", self.allowance("rover_seconds"))
        contacts = run.pop("contacts")
        result = {
            "scene": os.path.relpath(ROVER_SCENE, ROOT),
            "overrides": overrides,
            "precision": plan.precision,
            "dt": plan.dt,
            "substeps": plan.substeps,
            "wheels": list(plan.rover.wheel_names) if plan.rover else [],
            **run,
            "wheel_contacts": contacts,
        }
        problems = self.drive_problems(run, plan)
        if run["drive_steps"] and min(contacts["drive_max"]) == 0:
            problems.append("a wheel never touched the grains while driving")
        result["ok"] = not problems
        if problems:
            result["error"] = "; ".join(problems)
        return result

    def scene_overrides(self, overrides: tuple[dict, dict]) -> dict:
        """A section's scene overrides on this device (the small ones over the full ones)."""
        full, small = overrides
        return {"scene.device": self.device, **QUIET_OUTPUT, **full, **(small if self.small else {})}

    @staticmethod
    def drive_problems(run: dict, plan: RunPlan) -> list[str]:
        """What kept a scene run from its drive: no landing, or a drive cut short."""
        if run["drive_steps"] == 0:
            return [f"no drive: the run ended {run['status']!r} after {run['simulated_seconds']:.3g} s simulated"]
        if run["drive_steps"] < plan.drive_steps:
            return [
                f"drove {run['drive_simulated_seconds']:.3g} s of the {plan.scene.run.duration:.3g} s asked "
                f"(run {run['status']!r})"
            ]
        return []

    def tiled_bed(self, plan: RunPlan, tiles: tuple[int, int], name: str) -> tuple[str, dict]:
        """The plan's [bed] as nx x ny copies of one tile of it, settled here as the scene would
        settle the whole bed (double, its settling step and kinetic-energy ratio, at most its
        settle_max_time), the copies' shared walls removed; saved as a bed file for bed.bed_file.
        A copy's grains start at rest and without contact history: the landing takes that up."""
        spec = plan.bed.spec
        nx, ny = tiles
        piece = dataclasses.replace(spec, length=spec.length / nx, width=spec.width / ny)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tile = Simulation(*build_bed(piece, plan.settle_gravity).finalize(self.device, "double"))
        settling = self.settle(
            tile,
            plan.bed.settle_dt,
            plan.bed.settle_max_time,
            self.allowance("paper_settle_seconds"),
            plan.bed.settle_ke_ratio,
        )
        wall_height = 4 * spec.depth  # soil.bed.build_bed's container
        positions, radii, box = beds.tile(
            tile.positions(), tile.radii(), np.array([piece.length, piece.width, wall_height]), nx, ny
        )
        builder = SoilBuilder(gravity=plan.settle_gravity)
        grain = builder.add_material(spec.material)
        wall = builder.add_material(spec.wall_material) if spec.wall_material else grain
        builder.add_container((0.0, 0.0, 0.0), box, wall)
        builder.add_particles(positions, radii, grain)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the seams start with the walls' nm overlaps at most
            bed = Simulation(*builder.finalize(self.device, "double"))
        path = os.path.join(os.path.abspath(self.out), name)
        os.makedirs(self.out, exist_ok=True)
        save_bed(path, bed, spec, bed_metrics(bed, spec))
        settling.update(tiles=[nx, ny], tile_grains=tile.particle_count, bed_grains=bed.particle_count)
        return path, settling

    def scene_run(self, plan: RunPlan, folder: str, allowance: float) -> dict:
        """Run a plan through cosim.launch.run_plan into `folder` under --out, timing each macro
        step on the host, for at most `allowance` [s] of wall clock (then it stops after the macro
        step and reports what it reached). A macro step ends with the soil's one report read, so
        the host clock between two steps is the device's time for one. The rates leave out the
        run's first WARMUP_STEPS macro steps (the build, kernel loads, graph captures); the drive's
        figures count only its own macro steps, not the landing's. Grain counts, DEM steps and the
        wheels' contact counts (grains touching each wheel at the end of each macro step) come
        from results.h5."""
        out_dir = os.path.join(self.out, folder)
        marks = []  # per macro step: (step number, host clock [s], simulated time [s], a drive step)
        deadline = time.perf_counter() + allowance

        def after_step(runner) -> None:
            coupler = runner.system.coupler
            driving = coupler.step_count > runner.drive_start_step >= 0  # the landing's last step is its own
            marks.append((coupler.step_count, time.perf_counter(), coupler.time, driving))
            if marks[-1][1] > deadline:
                raise OutOfTime(f"{folder}: the {allowance:.3g} s allowance ran out at t = {coupler.time:.4g} s")

        started = time.perf_counter()
        try:
            status = run_plan(plan, out_dir, overwrite=True, hooks={"step": after_step}).status
        except OutOfTime as error:
            status = str(error)
        wall = time.perf_counter() - started
        series = read_series(RunFolder(out_dir).results)
        rows = np.array([m[0] for m in marks], dtype=np.int64) - 1
        clock = np.diff([started] + [m[1] for m in marks])  # host seconds of each macro step
        span = np.diff([0.0] + [m[2] for m in marks])  # its simulated seconds
        driving = np.array([m[3] for m in marks], dtype=bool)
        timed = rows >= WARMUP_STEPS
        grains = series["soil_particle_count"][rows].astype(np.float64)
        particle_steps = grains * series["soil_dem_steps"][rows]
        counts = series["contact_count"][rows]  # (macro steps, wheels)

        def rate(which) -> float:
            seconds = float(clock[which].sum())
            return float(particle_steps[which].sum()) / seconds if seconds > 0 else 0.0

        def contacts(which) -> dict:
            if not which.any():
                return {}
            c = counts[which]
            return {"min": c.min(axis=0).tolist(), "mean": c.mean(axis=0).tolist(), "max": c.max(axis=0).tolist()}

        drive_timed = driving & timed
        drive_wall, drive_time = float(clock[drive_timed].sum()), float(span[drive_timed].sum())
        result = {
            "status": status,
            "wall_seconds": wall,
            "simulated_seconds": float(marks[-1][2]) if marks else 0.0,
            "grains_min": float(grains.min()) if len(grains) else 0.0,
            "grains_max": float(grains.max()) if len(grains) else 0.0,
            "landing_simulated_seconds": float(span[~driving].sum()),
            "landing_particle_steps_per_second": rate(~driving & timed),
            "drive_steps": int(driving.sum()),
            "drive_simulated_seconds": float(span[driving].sum()),
            "drive_timed_simulated_seconds": drive_time,
            "drive_wall_seconds": drive_wall,
            "particle_steps_per_second": rate(drive_timed),
            "wall_per_simulated_second": drive_wall / drive_time if drive_time > 0 else None,
            "contacts": {
                **{f"drive_{k}": v for k, v in contacts(driving).items()},
                **{f"landing_{k}": v for k, v in contacts(~driving).items()},
            },
        }
        self.log(f"{folder}: {json.dumps({k: v for k, v in result.items() if k != 'contacts'})}")
        return result

    def settle(self, sim, dt: float, max_time: float, max_seconds: float, ke_ratio: float = 1e-4) -> dict:
        """Run until the kinetic energy is below soil.bed's settling threshold (as soil.bed.settle
        does), for at most max_time [s] simulated and max_seconds [s] of wall clock."""
        threshold = kinetic_energy_threshold(sim, ke_ratio)
        interval = max(50 * dt, 0.01 * max_time)
        started, start = time.perf_counter(), sim.time
        energy = sim.kinetic_energy()
        settled = False
        while sim.time - start < max_time and time.perf_counter() - started < max_seconds:
            sim.run(interval, dt)
            energy = sim.kinetic_energy()
            if energy < threshold and sim.time - start > 10 * interval:
                settled = True
                break
        result = {
            "settled": settled,
            "simulated_seconds": sim.time - start,
            "wall_seconds": time.perf_counter() - started,
            "kinetic_energy": energy,
            "threshold": threshold,
            "contacts_per_grain": float(sim.contact_counts().mean()),
        }
        self.log(f"tile settling: {json.dumps(result)}")
        return result

    def tests(self):
        if self.small or not self.device.startswith("cuda"):
            return {"skipped": "the CUDA tests need a CUDA device", "ok": True}
        left = max(60.0, self.budget - self.elapsed() - 20.0)
        # in one process: the lent machine's pytest has no xdist for the project's parallel default
        command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=", "-k", "cuda"]
        command += TEST_FILES
        try:
            done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=left)
        except subprocess.TimeoutExpired as error:
            return {
                "ok": False,
                "error": f"the CUDA tests did not finish in {left:.0f} s",
                "tail": (error.stdout or b"")[-2000:].decode(errors="replace") if error.stdout else "",
            }
        tail = (done.stdout + done.stderr).strip().splitlines()[-15:]
        return {
            "returncode": done.returncode,
            "summary": tail[-1] if tail else "",
            "tail": tail,
            "ok": done.returncode == 0,
        }

    # -- output ---------------------------------------------------------------------------------
    def write(self) -> None:
        self.results["seconds"] = self.elapsed()
        self.results["units"] = RESULT_UNITS
        for folder in self.results_dirs:
            os.makedirs(folder, exist_ok=True)
            # whole or the previous one: a suite killed while writing keeps the sections written before
            atomic_write_text(os.path.join(folder, "results.json"), json.dumps(self.results, indent=1, default=str))
            atomic_write_text(os.path.join(folder, "results.md"), self.markdown())

    def markdown(self) -> str:
        r = self.results
        lines = [
            f"GPU suite on {r['device']} ({r['machine']}){' (small mode)' if r['small'] else ''}: "
            f"{r.get('seconds', 0):.0f} s",
            "",
        ]
        lines += ["| section | result | seconds |", "|---|---|---|"]
        for name, result in r["sections"].items():
            lines.append(
                f"| {name} | {'ok' if result['ok'] else 'FAILED: ' + result.get('error', '')} | "
                f"{result['seconds']:.1f} |"
            )
        throughput = r["sections"].get("throughput", {})
        if throughput.get("rows"):
            lines += [
                "",
                "| bed | grains | precision | particle-steps/s | x single | device bytes per grain (estimate) "
                "| x double | captured |",
                "|---|---|---|---|---|---|---|---|",
            ]
            rate = {(row["bed"], row["precision"]): row["particle_steps_per_second"] for row in throughput["rows"]}
            memory = {(row["bed"], row["precision"]): row["bytes_per_grain"] for row in throughput["rows"]}
            for row in throughput["rows"]:
                bed = row["bed"]
                lines.append(
                    f"| {bed} | {row['grains']} | {row['precision']} | {row['particle_steps_per_second']:.3g} | "
                    f"{row['particle_steps_per_second'] / rate[(bed, 'single')]:.2f} | "
                    f"{row['bytes_per_grain']:.0f} ({row['bytes_per_grain_estimate']:.0f}) | "
                    f"{row['bytes_per_grain'] / memory[(bed, 'double')]:.2f} | {row['captured']} |"
                )
        profile = r["sections"].get("profile", {})
        if profile.get("rows"):
            lines += [
                "",
                f"Profile: steps launched one by one (no graph); timed: {profile['timed']}. Per bed the wall per "
                "step, the kernels' sum and the five largest kernels [us per step] (share of the sum):",
                "",
                "| bed | grains | precision | wall [us/step] | kernels [us/step] | largest kernels |",
                "|---|---|---|---|---|---|",
            ]
            lines += [
                f"| {row['bed']} | {row['grains']} | {row['precision']} | {row['wall_us_per_step']:.0f} | "
                f"{_figure(row['kernel_us_per_step'])} | "
                + (
                    ", ".join(f"{k['name']} {k['us_per_step']:.1f} ({k['share']:.0%})" for k in row["kernels"][:5])
                    or "-"
                )
                + " |"
                for row in profile["rows"]
            ]
        batched = r["sections"].get("batched", {})
        if batched.get("rows"):
            lines += [
                "",
                f"Batched replicas of {batched['scene']} (worlds of one simulation, each run in a process of its "
                f"own; steps: {batched['step_control']}; 'x one world' against world 0's replica run alone; world 0 "
                f"of every batch equal to that run bit for bit: {'yes' if batched['world_0_as_alone'] else 'NO'}):",
                "",
                "| worlds | grains per world | particle-steps/s (all worlds) | x one world "
                "| DEM steps' share of the wall | host work per world per macro step [ms] "
                "| of it the server's [ms] | wheel contacts min / mean | substeps per macro step | loop padding |",
                "|---|---|---|---|---|---|---|---|---|---|",
            ]
            lines += [
                f"| {row['worlds']} | {row['grains_per_world']:.0f} | {row['particle_steps_per_second']:.3g} | "
                f"{row['x_one_world']:.2f} | {_figure(row['dem_share_of_wall'])} | "
                f"{_figure(row['host_ms_per_world_step'])} | {_figure(row['serve_ms_per_world_step'])} | "
                f"{row['wheel_contacts_min']} / {row['wheel_contacts_mean']:.1f} | "
                f"{row['substeps_per_macro_step']:.1f} | {row['loop_padding']:.3f} |"
                for row in batched["rows"]
            ]
        if throughput.get("slot_rows"):
            lines += [
                "",
                "Storage order: the neighbour lists and contact history stored per slot (slot-major) against per "
                "grain, the same bed and steps:",
                "",
                "| bed | precision | particle-steps/s, per slot | x per grain |",
                "|---|---|---|---|",
            ]
            lines += [
                f"| {row['bed']} | {row['precision']} | {row['particle_steps_per_second']:.3g} | "
                f"{row['x_grain_storage']:.2f} |"
                for row in throughput["slot_rows"]
            ]
        paper = r["sections"].get("paper", {})
        if paper.get("projected_60s_seconds"):
            settling, contacts = paper["settling"], paper["wheel_contacts"]
            lines += [
                "",
                f"Paper case ({paper['scene']}, {paper['precision']}, slip {paper['slip']}, dt = {paper['dt']:.3g} s): "
                f"{settling['bed_grains']} grains ({settling['tiles'][0]} x {settling['tiles'][1]} tiles of "
                f"{settling['tile_grains']}, the tile {'settled' if settling['settled'] else 'NOT settled'} in "
                f"{settling['simulated_seconds']:.3g} s); landed in {paper['landing_simulated_seconds']:.3g} s, "
                f"drove {paper['drive_simulated_seconds']:.3g} s ({paper['drive_timed_simulated_seconds']:.3g} s "
                f"of it timed: {paper['drive_wall_seconds']:.1f} s wall): "
                f"{paper['particle_steps_per_second']:.3g} particle-steps/s, 60 s projected in "
                f"{paper['projected_60s_seconds']:.0f} s ({paper['projected_60s_seconds'] / 60:.1f} min); "
                f"grains touching the wheel while driving: min {contacts['drive_min']}, mean "
                f"{contacts['drive_mean']:.1f}, max {contacts['drive_max']}.",
            ]
        rover = r["sections"].get("rover", {})
        if rover.get("wall_per_simulated_second"):
            contacts = rover["wheel_contacts"]
            lines += [
                "",
                f"Rover ({rover['scene']}, {rover['precision']}, dt = {rover['dt']:.3g} s): "
                f"{rover['grains_min']:.0f}-{rover['grains_max']:.0f} grains in the patch; "
                + (
                    f"landed in {rover['landing_simulated_seconds']:.3g} s"
                    if rover["landing_simulated_seconds"] > 0
                    else "no landing phase"
                )
                + f", drove {rover['drive_simulated_seconds']:.3g} s ({rover['drive_timed_simulated_seconds']:.3g} s "
                f"of it timed: {rover['drive_wall_seconds']:.1f} s wall): {rover['particle_steps_per_second']:.3g} "
                f"particle-steps/s, {rover['wall_per_simulated_second']:.3g} s wall per simulated second; "
                f"least grains touching a wheel while driving: {contacts['drive_min']} "
                f"({', '.join(rover['wheels'])}).",
            ]
        targets = {}
        for result in r["sections"].values():
            targets.update(result.get("targets", {}))
        checks = {
            "repeat": "a coupled run repeats bit for bit",
            "agreement": "device agrees with the CPU within the replica scatter",
            "rover": "rover: lands and drives its segment",
            "tests": "the CUDA tests pass",
        }
        for name, label in checks.items():
            if name in r["sections"]:
                targets[label] = r["sections"][name]["ok"]
        if targets:
            lines += ["", "| target | met |", "|---|---|"]
            lines += [f"| {name} | {'yes' if met else 'NO'} |" for name, met in targets.items()]
        return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=None, help="Warp device (default: cuda:0, or cpu with --small)")
    parser.add_argument("--small", action="store_true", help="small sizes: the suite's own check, on any device")
    parser.add_argument("--out", default="runs/gpu_suite", help="folder for the runs, results.json and results.md")
    parser.add_argument("--results", help="a second folder for results.json and results.md (a lent machine's $OUT)")
    parser.add_argument("--budget", type=float, default=510.0, help="seconds the whole suite should take")
    parser.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    parser.add_argument("--worlds", nargs="+", type=int, help="the batched section's world counts (default 1 4 20)")
    parser.add_argument(
        "--compile-for-arch",
        type=int,
        metavar="SM",
        help="after the sections, compile every Warp module they loaded for CUDA architecture SM (90: H100/H200) "
        "into Warp's kernel cache, no GPU needed (benchmarks/gpu_carry.py carries them to a lent machine)",
    )
    parser.add_argument(
        "--step-control",
        choices=("fixed", "pid"),
        default="fixed",
        help="the batched section's DEM steps: fixed (default) or PID substeps, each world its own controller",
    )
    args = parser.parse_args(argv)
    if args.worlds:
        SIZES["batch_worlds"] = (tuple(args.worlds), tuple(args.worlds))
    quiet_warp()
    wp.init()
    device = args.device or ("cpu" if args.small else "cuda:0")
    if device.startswith("cuda") and not wp.is_cuda_available():
        print("no CUDA device here: run with --small --device cpu for the CPU check", file=sys.stderr)
        return 2
    suite = Suite(device, args.small, args.budget, args.out, args.results, args.step_control)
    try:
        for name in args.sections:
            suite.section(name, getattr(suite, name))
    except KeyboardInterrupt as stop:  # the sections so far are written (Suite.section); the rest are not run
        print(suite.markdown())
        print(f"stopped ({stop}): the sections after it were not run", file=sys.stderr)
        return exit_status(stop_name(stop))  # as cosim's commands exit: 130 SIGINT, 143 SIGTERM, 129 SIGHUP
    print(suite.markdown())
    if args.compile_for_arch:
        compiled = compile_loaded_modules(args.compile_for_arch)
        print(f"compiled {len(compiled)} Warp modules for sm_{args.compile_for_arch} into {wp.config.kernel_cache_dir}")
    return 0 if all(result["ok"] for result in suite.results["sections"].values()) else 1


def compile_loaded_modules(arch: int) -> list[str]:
    """Compile every Warp module this process has loaded (with the kernel overloads its launches made)
    for CUDA architecture `arch`, to machine code (cubin), into Warp's kernel cache; returns their names.
    A fresh GPU machine then loads them from the cache instead of compiling each on first use (NVRTC
    runs without a GPU; the cache key is the module's hash, the same on every device)."""
    from warp._src.context import user_modules  # Warp's registry of modules; no public accessor

    names = []
    for module in list(user_modules.values()):
        if module.execs:
            wp.compile_aot_module(module, arch=arch, use_ptx=False)
            names.append(module.name)
    return names


if __name__ == "__main__":
    sys.exit(main())
