"""The GPU suite: one prepared command for an 8-minute window on one H100/H200.

    python benchmarks/gpu_suite.py                          # on cuda:0; results in runs/gpu_suite/
    python benchmarks/gpu_suite.py --small --device cpu     # the same checks, small, on the CPU
                                                            # (the test suite runs this: it cannot rot)

Sections, each timed, in this order (the tests last, within what is left of --budget):

- throughput: a random fill settled on the device (Earth gravity, double), tiled to 100,000 and
  1,000,000 grains; particle-steps/s in single, mixed and double (targets: single >= 3e8 at
  1M; double >= 0.5 x and mixed >= 0.8 x single).
- repeat: a short coupled run (a grousered wheel resting pressed into a standing bed, driven
  through it by cosim.DemSoil) twice on the device: every wheel wrench and every grain bit for
  bit the same, with the wheel touching grains.
- agreement: the same short settling run on the CPU and on the device, replicas differing
  only in summation order (order_seed): the device's bed statistics lie within the CPU
  replicas' scatter.
- paper: the paper's case, 200,000 grains of Phobos regolith at Phobos gravity in double
  precision with a wheel driving through them: one tile settled to the kinetic-energy
  threshold of soil.bed.settle, tiled; 2,000 steps timed at the scene's step (0.2 Rayleigh
  steps) and 60 s projected (target: at most 10 minutes).
- tests: the CUDA variants of the soil tests (pytest -k cuda).

Writes results.json (every figure) and results.md (a table with the targets) to --out.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
import warnings

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import warp as wp  # noqa: E402

from benchmarks import beds  # noqa: E402
from cosim.contract import WheelKinematics  # noqa: E402
from cosim.dem_soil import DemSoil  # noqa: E402
from soil import GrouserWheel, Material, Simulation, SoilBuilder, quiet_warp  # noqa: E402
from soil.advisor import rayleigh_time_step  # noqa: E402
from soil.bed import PHOBOS_REGOLITH, BedSpec, insert_grains, kinetic_energy_threshold  # noqa: E402
from soil.gravity import GRAVITY_PRESETS  # noqa: E402

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
WHEEL = GrouserWheel(radius=0.09, width=0.06, grouser_count=12, grouser_height=0.006, grouser_thickness=0.003)
"""The MMX-like wheel of examples/phobos_single_wheel_gpu.toml."""
SIZES = {
    # name: (full, small)
    "base": (20000, 300),  # grains of the settled bed the throughput beds are tiled from
    "tiles": ({"100k": (5, 1), "1M": (10, 5)}, {"100k": (2, 1), "1M": (2, 2)}),
    "throughput_steps": (200, 10),
    "repeat_macro_steps": (20, 3),
    "agreement": ((2000, 4, 0.1), (300, 2, 0.01)),  # grains, replicas, simulated seconds
    "paper_tile": ((0.1, 0.1, 0.08), (0.03, 0.03, 0.03)),  # one tile of the Phobos bed [m]
    "paper_tiles": ((6, 5), (2, 2)),
    "paper_settle": ((30.0, 120.0), (20.0, 60.0)),  # settling of the tile at most [s simulated], [s wall]
    "paper_steps": (2000, 20),
}


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


class Suite:
    def __init__(self, device: str, small: bool, budget: float, out: str):
        self.device, self.small, self.budget, self.out = device, small, budget, out
        self.started = time.perf_counter()
        self.results: dict = {"device": device, "small": small, "machine": self.machine(), "sections": {}}

    def machine(self) -> str:
        if self.device.startswith("cuda"):
            return f"{wp.get_device(self.device).name}, Warp {wp.__version__}"
        return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Warp {wp.__version__}"

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def log(self, text: str) -> None:
        print(f"[{self.elapsed():6.1f} s] {text}", flush=True)

    def section(self, name, function):
        start = time.perf_counter()
        self.log(f"{name} ...")
        try:
            result = function()
            result["ok"] = bool(result.get("ok", True))
        except Exception as error:  # the suite reports a failed section and goes on
            result = {"ok": False, "error": f"{type(error).__name__}: {error}"}
        result["seconds"] = time.perf_counter() - start
        self.results["sections"][name] = result
        self.log(
            f"{name}: {'ok' if result['ok'] else 'FAILED'} ({result['seconds']:.1f} s) "
            f"{json.dumps({k: v for k, v in result.items() if not isinstance(v, (list, dict))})}"
        )
        self.write()

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
            for precision in ("single", "mixed", "double"):
                sim = beds.build(tiled, tiled_radii, tiled_box, self.device, precision)
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    sim.macro_step(20, dt)
                    wp.synchronize_device(self.device)
                    start = time.perf_counter()
                    sim.macro_step(steps, dt)
                    seconds = time.perf_counter() - start
                n = len(tiled_radii)
                rows.append(
                    dict(
                        bed=label,
                        grains=n,
                        precision=precision,
                        steps=steps,
                        seconds=seconds,
                        particle_steps_per_second=n * steps / seconds,
                        captured=sim.capture,
                        warnings=[str(w.message) for w in caught],
                        bytes_per_grain=sim.bytes_per_grain()["total"],
                        contacts_per_grain=float(sim.contact_counts().mean()),
                    )
                )
                self.log(json.dumps(rows[-1]))
                del sim
        rate = {(r["bed"], r["precision"]): r["particle_steps_per_second"] for r in rows}
        single = rate[("1M", "single")]
        targets = {
            "single at 1M >= 3e8 particle-steps/s": single >= 3e8,
            "double >= 0.5 x single at 1M": rate[("1M", "double")] >= 0.5 * single,
            "mixed >= 0.8 x single at 1M": rate[("1M", "mixed")] >= 0.8 * single,
        }
        return {"rows": rows, "targets": targets, "ok": True}

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
        positions, radii, box_hi = beds.random_fill(n, 0.1 if not self.small else 0.03, seed=3)
        dt = 0.2 * rayleigh_time_step(beds.YOUNGS, beds.POISSON, beds.DENSITY, radii.min())
        stats = []
        for seed in range(replicas):
            builder = SoilBuilder(gravity=9.81)
            mat = builder.add_material(beds.material())
            builder.add_container((0, 0, 0), box_hi, mat)
            builder.add_particles(positions, radii, mat)
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

    def paper(self):
        """200,000 grains of Phobos regolith at Phobos gravity, double, a wheel driving through."""
        length, width, depth = size("paper_tile", self.small)
        spec = BedSpec(
            length=length, width=width, depth=depth, radius_mean=2.0e-3, radius_spread=0.2, material=PHOBOS_REGOLITH
        )
        positions, radii = insert_grains(spec)
        dt = 0.2 * rayleigh_time_step(
            PHOBOS_REGOLITH.youngs_modulus, PHOBOS_REGOLITH.poisson_ratio, PHOBOS_REGOLITH.density, radii.min()
        )
        wall_height = 4 * depth
        box = np.array([length, width, wall_height])
        tile = beds.build(positions, radii, box, self.device, "double", gravity="phobos", grains=PHOBOS_REGOLITH)
        settling = self.settle(tile, dt, *size("paper_settle", self.small))
        settled = tile.positions()[np.argsort(tile.model.particle_order)]
        tx, ty = size("paper_tiles", self.small)
        positions, radii, box = beds.tile(settled, radii, box, tx, ty)
        builder = SoilBuilder(gravity="phobos")
        mat = builder.add_material(PHOBOS_REGOLITH)
        builder.add_container((0, 0, 0), box, mat)
        builder.add_particles(positions, radii, mat)
        wheel = (
            WHEEL
            if not self.small
            else GrouserWheel(radius=0.012, width=0.01, grouser_count=8, grouser_height=0.001, grouser_thickness=0.001)
        )
        builder.add_wheel(
            wheel,
            builder.add_material(
                Material(youngs_modulus=2e5, stick_angle=math.radians(30), slip_angle=math.radians(25))
            ),
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model, state, control = builder.finalize(self.device, "double")
        soil = DemSoil(Simulation(model, state, control), dt, surface_height=0.0)
        centre = (0.3 * box[0], 0.5 * box[1], 0.0)
        # resting on the grains, pressed in by half a grain radius: it works in them from the start
        hub = np.array([centre[0], centre[1], resting_height(soil.sim, wheel, *centre[:2]) - 0.5 * spec.radius_mean])
        omega = 0.11 if not self.small else 0.8
        velocity = np.array([omega * wheel.radius, 0.0, 0.0])
        steps, macro = size("paper_steps", self.small), 10
        warm = max(1, steps // 20)

        def advance(k):
            start = WheelKinematics(hub + velocity * k * macro * dt, [1.0, 0, 0, 0], velocity, [0.0, omega, 0.0])
            return soil.advance((k + 1) * macro * dt, [start])[0]

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for k in range(warm):  # kernels loaded, graphs captured
                advance(k)
            wp.synchronize_device(self.device)
            started = time.perf_counter()
            for k in range(warm, warm + steps // macro):
                wrench = advance(k)
            seconds = time.perf_counter() - started
        per_step = seconds / steps
        projected = per_step * 60.0 / dt
        n = model.particle_count
        return {
            "grains": n,
            "dt": dt,
            "settling": settling,
            "timed_steps": steps,
            "timed_seconds": seconds,
            "particle_steps_per_second": n * steps / seconds,
            "projected_60s_seconds": projected,
            "gravity": GRAVITY_PRESETS["phobos"],
            "wheel_contacts": int(wrench.contact_count),
            "contacts_per_grain": float(soil.sim.contact_counts().mean()),
            "targets": {"60 s in at most 10 minutes": projected <= 600.0},
            "ok": True,
        }

    def settle(self, sim, dt: float, max_time: float, max_seconds: float) -> dict:
        """Run until the kinetic energy is below soil.bed's settling threshold (as soil.bed.settle
        does), for at most max_time [s] simulated and max_seconds [s] of wall clock."""
        threshold = kinetic_energy_threshold(sim)
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
        command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", "cuda", *TEST_FILES]
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
        os.makedirs(self.out, exist_ok=True)
        self.results["seconds"] = self.elapsed()
        with open(os.path.join(self.out, "results.json"), "w") as f:
            json.dump(self.results, f, indent=1, default=str)
        with open(os.path.join(self.out, "results.md"), "w") as f:
            f.write(self.markdown())

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
                "| bed | grains | precision | particle-steps/s | bytes per grain | captured |",
                "|---|---|---|---|---|---|",
            ]
            for row in throughput["rows"]:
                lines.append(
                    f"| {row['bed']} | {row['grains']} | {row['precision']} | "
                    f"{row['particle_steps_per_second']:.3g} | {row['bytes_per_grain']:.0f} | "
                    f"{row['captured']} |"
                )
        paper = r["sections"].get("paper", {})
        if "projected_60s_seconds" in paper:
            projected = paper["projected_60s_seconds"]
            settling = paper["settling"]
            lines += [
                "",
                f"Paper case: {paper['grains']} grains, Phobos gravity, double, dt = {paper['dt']:.3g} s "
                f"(tile {'settled' if settling['settled'] else 'NOT settled'} in "
                f"{settling['simulated_seconds']:.3g} s, {settling['contacts_per_grain']:.1f} contacts per "
                "grain): "
                f"{paper['particle_steps_per_second']:.3g} particle-steps/s "
                f"({paper['contacts_per_grain']:.1f} contacts per grain), 60 s projected in {projected:.0f} s "
                f"({projected / 60:.1f} min).",
            ]
        targets = {}
        for result in r["sections"].values():
            targets.update(result.get("targets", {}))
        checks = {
            "repeat": "a coupled run repeats bit for bit",
            "agreement": "device agrees with the CPU within the replica scatter",
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
    parser.add_argument("--out", default="runs/gpu_suite", help="folder for results.json and results.md")
    parser.add_argument("--budget", type=float, default=480.0, help="seconds the whole suite should take")
    parser.add_argument(
        "--sections",
        nargs="+",
        default=["throughput", "repeat", "agreement", "paper", "tests"],
        choices=["throughput", "repeat", "agreement", "paper", "tests"],
    )
    args = parser.parse_args(argv)
    quiet_warp()
    wp.init()
    device = args.device or ("cpu" if args.small else "cuda:0")
    if device.startswith("cuda") and not wp.is_cuda_available():
        print("no CUDA device here: run with --small --device cpu for the CPU check", file=sys.stderr)
        return 2
    suite = Suite(device, args.small, args.budget, args.out)
    for name in args.sections:
        suite.section(name, getattr(suite, name))
    print(suite.markdown())
    return 0 if all(result["ok"] for result in suite.results["sections"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
