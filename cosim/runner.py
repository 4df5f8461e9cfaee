"""Run a scene: settle (or load) the bed, add the wheel, couple it with the single-wheel rig,
write results.h5 + XDMF, checkpoint, and resume bit-identically.

Output folder (``OUT``):

    scene.toml        the scene as run (overrides applied) - `cosim resume` reads it
    run.json          status, device, precision, bed, wall time, summary
    bed.h5, bed.json  the settled bed (cached: a rerun with the same bed/soil/gravity reuses it)
    results.h5        time series and particle snapshots (cosim.output documents the layout)
    results.xdmf      ParaView view of the snapshots
    checkpoint.npz    everything needed to continue the run bit-identically (written atomically)
    plots/            `cosim plot OUT`

`run_scene(scene, out)` runs; `resume(out)` continues from checkpoint.npz to the same result
an uninterrupted run gives (bitwise on the CPU). A first Ctrl-C finishes the macro step,
writes a checkpoint and stops cleanly; a second one stops at once (resume then starts from
the previous checkpoint).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import time
from dataclasses import dataclass, field

import numpy as np

from soil.files import atomic_write_text
from soil.stability import write_checkpoint

from .output import RESULTS_FILE, XDMF_FILE, ResultsWriter
from .scene import Scene, load_scene, scene_from_text

CHECKPOINT_FILE = "checkpoint.npz"
RUN_FILE = "run.json"
SCENE_FILE = "scene.toml"
BED_FILE = "bed.h5"
BED_INFO_FILE = "bed.json"
ROVER_COLUMNS = ["x", "y", "z", "vx", "vy", "vz", "angle"]
_RUN_OUTPUTS = (RESULTS_FILE, XDMF_FILE, CHECKPOINT_FILE, RUN_FILE, SCENE_FILE, "diverged_state.npz", "plots")


class OutputExistsError(FileExistsError):
    """The output folder already holds files and --overwrite was not given."""


class RunDiverged(RuntimeError):
    """The DEM exploded; the message says where the last good state is."""


class RunInterrupted(KeyboardInterrupt):
    """The run was stopped (Ctrl-C); `cosim resume OUT` continues it."""


@dataclass
class RunResult:
    out_dir: str
    status: str
    summary: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------
# output folder


def prepare_output(out_dir: str, overwrite: bool = False) -> None:
    """Create the output folder; refuse a non-empty one unless `overwrite`.

    With `overwrite` only this package's run files are removed; a cached bed (bed.h5)
    and any other file stay.
    """
    os.makedirs(out_dir, exist_ok=True)
    present = sorted(os.listdir(out_dir))
    if not present:
        return
    if not overwrite:
        raise OutputExistsError(f"output folder {out_dir!r} is not empty ({', '.join(present[:6])}"
                                f"{', ...' if len(present) > 6 else ''}); nothing is overwritten: choose another "
                                "--out, continue with `cosim resume`, or pass --overwrite to replace the run "
                                "(a cached bed.h5 is kept and reused)")
    for name in _RUN_OUTPUTS:
        path = os.path.join(out_dir, name)
        if os.path.isdir(path):
            shutil.rmtree(path)
        elif os.path.exists(path):
            os.remove(path)


def write_json(path: str, data: dict) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, default=_json_default) + "\n")


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(type(value).__name__)


# ------------------------------------------------------------------------------------
# the bed


def bed_key(scene: Scene) -> str:
    """Hash of everything the settled bed depends on."""
    parts = {"bed": scene.bed.model_dump(exclude={"bed_file"}), "soil": scene.soil.model_dump(exclude={"law"}),
             "gravity": [float(g) for g in scene.scene.gravity_vector()], "device": _device_kind(scene.scene.device),
             "format": 1}
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]


def _device_kind(device: str) -> str:
    return "cpu" if device == "cpu" else "cuda"


def settled_bed(scene: Scene, folder: str, progress: bool = True, log=print) -> tuple[str, dict]:
    """Path of the settled bed for `scene` and its info: scene.bed.bed_file, else a cached
    bed in `folder` with the same key, else a new one settled now and saved there."""
    from soil.bed import bed_metrics, make_settled_bed, rayleigh_time_step, save_bed

    if scene.bed.bed_file:
        path = scene.resolve(scene.bed.bed_file)
        return path, {"source": "file", "path": path}
    key = bed_key(scene)
    path = os.path.join(folder, BED_FILE)
    info_path = os.path.join(folder, BED_INFO_FILE)
    if os.path.isfile(path) and os.path.isfile(info_path):
        with open(info_path) as f:
            info = json.load(f)
        if info.get("key") == key:
            log(f"reusing the settled bed {path} (key {key})")
            return path, {**info, "source": "cache"}
    spec = scene.bed_spec()
    dt = scene.bed.settle_dt_factor * rayleigh_time_step(spec.material, spec.radius_mean * (1 - spec.radius_spread))
    bar = _settle_bar(scene, progress)
    start = time.perf_counter()
    try:
        sim, report, metrics = make_settled_bed(spec, scene.scene.gravity_vector(), device=scene.scene.device,
                                                precision="double", dt=dt, ke_ratio=scene.bed.settle_ke_ratio,
                                                max_time=scene.bed.settle_max_time, progress=bar.update_settle)
    finally:
        bar.close()
    wall = time.perf_counter() - start
    if not report["settled"]:
        log(f"note: the bed did not reach the kinetic-energy threshold in bed.settle_max_time = "
            f"{scene.bed.settle_max_time} s (KE {report['kinetic_energy']:.3g} J > {report['threshold']:.3g} J); "
            "it is used as it is (raise bed.settle_max_time or bed.settle_ke_ratio)")
    metrics = bed_metrics(sim, spec)
    save_bed(path, sim, spec, metrics)
    info = {"key": key, "report": report, "metrics": metrics, "dt": dt, "wall_time": wall,
            "particle_count": sim.model.particle_count}
    write_json(info_path, info)
    log(f"settled {sim.model.particle_count} grains in {wall:.1f} s wall ({report['time']:.3g} s simulated); "
        f"surface at z = {metrics['height']:.4g} m, packing {metrics['packing_fraction']:.3f}")
    return path, {**info, "source": "settled"}


class _settle_bar:
    def __init__(self, scene, enabled):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=scene.bed.settle_max_time, desc="settling bed", unit="s",
                            bar_format="{desc}: {n:.2f}/{total:.2f} s sim [{elapsed}, {postfix}]", leave=True)
        self._last = 0.0

    def update_settle(self, t, energy, threshold):
        if self.bar is not None:
            self.bar.update(t - self._last)
            self._last = t
            self.bar.set_postfix_str(f"KE/threshold {energy / max(threshold, 1e-300):.3g}")

    def close(self):
        if self.bar is not None:
            self.bar.close()


# ------------------------------------------------------------------------------------
# the run


class Runner:
    """One single-wheel run of a scene in an output folder (see the module docstring)."""

    def __init__(self, scene: Scene, out_dir: str, progress: bool = True, log=print, hooks: dict | None = None):
        self.scene = scene
        self.out_dir = os.path.abspath(out_dir)
        self.progress = progress
        self.log = log if log is not None else (lambda *a, **k: None)
        self.hooks = hooks or {}
        self.stop_requested = False
        """Set (e.g. by the SIGINT handler or a hook) to stop cleanly after the current macro step."""
        self.wall_before = 0.0
        self.x0 = None

    # -- building --------------------------------------------------------------------
    def build(self, bed_path: str):
        from soil import Simulation
        from soil.bed import load_bed, restore_state

        from .coupler import Coupler
        from .dem_soil import DemSoil
        from .single_wheel import SingleWheelRig

        scene = self.scene
        builder, saved = load_bed(bed_path)
        gravity = scene.scene.gravity_vector()
        if not np.allclose(builder.gravity, gravity, rtol=1e-12, atol=0):
            raise ValueError(f"bed.bed_file was settled under gravity {builder.gravity} m/s^2, the scene has "
                             f"{gravity} (scene.gravity)")
        self.shape = scene.wheel_shape()
        builder.add_wheel(self.shape, scene.wheel_material())
        model, state, control = builder.finalize(device=scene.scene.device, precision=scene.scene.precision,
                                                 law=scene.contact_law(), order_seed=scene.run.order_seed)
        restore_state(model, state, saved)
        self.surface = float(saved["metrics"]["height"])
        self.dt, self.macro_step, self.substeps = scene.time_steps()
        self.sim = Simulation(model, state, control)
        self.soil = DemSoil(self.sim, self.dt, self.surface)
        _, _, rim = scene.wheel_extent()
        self.rim_radius = rim
        self.start = self._start_position()
        tb = scene.testbed
        self.rig = SingleWheelRig(mass=tb.mass, radius=rim, omega=tb.omega, hub=self.start, mode=tb.mode,
                                  slip=tb.slip, drawbar_load=tb.drawbar_load, gravity=model.gravity)
        self.rig.time = self.sim.time
        self.x0 = float(self.start[0])
        self._make_coupler = lambda: Coupler(self.soil, self.rig, self.macro_step, scheme=scene.run.scheme,
                                             gravity=model.gravity)
        self.total_steps = scene.macro_step_count()
        h = self.macro_step
        self.snapshot_every = (max(1, int(round(scene.output.snapshot_interval / h)))
                               if scene.output.snapshot_interval > 0 else self.total_steps)
        self.checkpoint_every = max(1, int(round(scene.output.checkpoint_interval / h)))
        self.mesh = _wheel_mesh([self.shape])

    def _start_position(self) -> list[float]:
        """Hub over the bed, its lowest point on the highest grain under the wheel (no initial overlap)."""
        outer, width, _ = self.scene.wheel_extent()
        start = self.scene.start_position(self.surface)
        x = self.sim.positions()
        r = self.sim.model.radius_numpy()
        under = (np.abs(x[:, 0] - start[0]) < outer + r) & (np.abs(x[:, 1] - start[1]) < 0.5 * width + r)
        if under.any():
            dx = np.abs(x[under, 0] - start[0])
            reach = np.sqrt(np.maximum((outer + r[under]) ** 2 - dx**2, 0.0))  # hub height that just touches
            start[2] = max(start[2], float(np.max(x[under, 2] + reach)) + 1e-6 * outer)
        return start

    def _attrs(self, bed_info: dict, scene_source: str) -> dict:
        s = self.scene
        return {
            "name": s.scene.name, "scene_toml": s.to_toml(), "scene_source": scene_source,
            "precision": s.scene.precision, "device": s.scene.device, "scheme": s.run.scheme,
            "order_seed": -1 if s.run.order_seed is None else int(s.run.order_seed), "dt": self.dt,
            "macro_step": self.macro_step, "substeps": self.substeps, "duration": self.total_steps * self.macro_step,
            "gravity": np.asarray(self.sim.model.gravity, dtype=np.float64), "surface_height": self.surface,
            "start_position": np.asarray(self.start, dtype=np.float64), "omega": s.testbed.omega,
            "rim_radius": self.rim_radius, "particle_count": self.sim.model.particle_count,
            "wheel_names": json.dumps(["wheel"]), "bed": json.dumps(bed_info, default=_json_default),
        }

    # -- run ---------------------------------------------------------------------------
    def start_new(self, scene_source: str = "", overwrite: bool = False) -> RunResult:
        prepare_output(self.out_dir, overwrite)
        atomic_write_text(os.path.join(self.out_dir, SCENE_FILE), self.scene.to_toml())
        bed_path, bed_info = settled_bed(self.scene, self.out_dir, self.progress, self.log)
        self.bed_path = bed_path
        self.build(bed_path)
        self.coupler = self._make_coupler()
        self.soil.place_wheels(self.rig.wheel_kinematics())
        self.run_info = {"status": "running", "bed_file": bed_path, "bed": bed_info, "scene_source": scene_source,
                         "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "particle_count": self.sim.model.particle_count,
                         "dt": self.dt, "macro_step": self.macro_step, "macro_steps": self.total_steps}
        write_json(os.path.join(self.out_dir, RUN_FILE), self.run_info)
        self.writer = ResultsWriter.create(
            os.path.join(self.out_dir, RESULTS_FILE), attrs=self._attrs(bed_info, scene_source),
            radius=self.sim.model.radius_numpy(), wheel_count=1, mesh=self.mesh, rover_columns=ROVER_COLUMNS,
            flush_every=self.scene.output.flush_every)
        self._snapshot()
        self._checkpoint()
        return self._loop()

    def continue_from(self, checkpoint: dict) -> RunResult:
        """Rebuild from the run's own bed and continue from a loaded checkpoint."""
        with open(os.path.join(self.out_dir, RUN_FILE)) as f:
            self.run_info = json.load(f)
        self.bed_path = self.run_info["bed_file"]
        self.build(self.bed_path)
        _restore(self, checkpoint)
        self.writer = ResultsWriter.reopen(os.path.join(self.out_dir, RESULTS_FILE), int(checkpoint["runner/steps"]),
                                           int(checkpoint["runner/snapshots"]), self.scene.output.flush_every)
        self.run_info["status"] = "running"
        write_json(os.path.join(self.out_dir, RUN_FILE), self.run_info)
        return self._loop()

    def _loop(self) -> RunResult:
        from soil import SimulationDiverged

        coupler, sim = self.coupler, self.sim
        n = sim.model.particle_count
        bar = None
        if self.progress:
            from tqdm import tqdm

            bar = tqdm(total=round(self.total_steps * self.macro_step, 9), desc=self.scene.scene.name, unit="s",
                       initial=round(coupler.step_count * self.macro_step, 9),
                       bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.3f}/{total:.3f} s sim "
                                  "[{elapsed}<{remaining}{postfix}]")
        started = time.perf_counter()
        steps_at_start = coupler.step_count
        previous_handler = _install_sigint(self)
        status, message = "running", ""
        try:
            while coupler.step_count < self.total_steps:
                coupler.step()
                self._record()
                if "after_step" in self.hooks:
                    self.hooks["after_step"](self)
                k = coupler.step_count
                last = k == self.total_steps
                if k % 10 == 0 or k % self.checkpoint_every == 0 or last:
                    self._check_speed()
                if k % self.snapshot_every == 0 or last:
                    self._snapshot()
                if k % self.checkpoint_every == 0 or last or self.stop_requested:
                    self._checkpoint(time.perf_counter() - started)
                    if "after_checkpoint" in self.hooks:
                        self.hooks["after_checkpoint"](self)
                if bar is not None:
                    wall = time.perf_counter() - started
                    rate = n * self.substeps * (k - steps_at_start) / max(wall, 1e-9)
                    bar.update(min(self.macro_step, bar.total - bar.n))  # float sums must not pass the total
                    bar.set_postfix_str(f"dt {self.dt:.3g} s, {rate:.3g} particle-steps/s", refresh=False)
                if self.stop_requested and not last:
                    raise RunInterrupted(f"stopped at t = {coupler.time:.6g} s after a checkpoint; "
                                         f"continue with: cosim resume {self.out_dir}")
            status = "complete"
        except SimulationDiverged as error:
            status = "diverged"
            checkpoint_time = self._last_checkpoint_time
            message = (f"the simulation diverged near t = {coupler.time:.6g} s: {error}. The last good state is "
                       f"{os.path.join(self.out_dir, CHECKPOINT_FILE)} (t = {checkpoint_time:.6g} s). "
                       f"Try a smaller run.dt_factor (now dt = {self.dt:.3g} s), a softer soil "
                       "(cosim advise) or a smaller macro step.")
            if getattr(error, "last_good", None):
                np.savez(os.path.join(self.out_dir, "diverged_state.npz"), **error.last_good)
            raise RunDiverged(message) from error
        except KeyboardInterrupt as error:
            status = "interrupted"
            message = str(error) or (f"interrupted at t = {coupler.time:.6g} s; resume continues from the checkpoint "
                                     f"at t = {self._last_checkpoint_time:.6g} s")
            raise
        except BaseException as error:
            status, message = "failed", f"{type(error).__name__}: {error}"
            raise
        finally:
            if previous_handler is not None:
                signal.signal(signal.SIGINT, previous_handler)
            if bar is not None:
                bar.close()
            wall = time.perf_counter() - started
            summary = self.summary(wall)
            self.writer.close(status, message)
            self.run_info.update(status=status, message=message, summary=summary,
                                 wall_time=self.wall_before + wall)
            write_json(os.path.join(self.out_dir, RUN_FILE), self.run_info)
        return RunResult(self.out_dir, status, summary)

    # -- per step ------------------------------------------------------------------------
    def _record(self) -> None:
        r = self.coupler._records  # the latest macro step (Coupler keeps lists)
        position = np.asarray(r["position"][-1])
        velocity = np.asarray(r["linear_velocity"][-1])
        force = np.asarray(r["force"][-1])
        torque = np.asarray(r["torque"][-1])
        rim = self.rig.omega * self.rig.radius
        record = {
            "time": r["time"][-1], "position": position, "orientation": np.asarray(r["orientation"][-1]),
            "linear_velocity": velocity, "angular_velocity": np.asarray(r["angular_velocity"][-1]),
            "force": force, "torque": torque, "sinkage": np.asarray(r["sinkage"][-1]),
            "contact_count": np.asarray(r["contact_count"][-1]), "work_on_rover": np.asarray(r["work_on_rover"][-1]),
            "work_on_soil": np.asarray(r["work_on_soil"][-1]), "travel": position[:, 0] - self.x0,
            "slip": (1.0 - velocity[:, 0] / rim) if rim else np.zeros(1), "drawbar_pull": force[:, 0],
            "driving_torque": -torque[:, 1],
            "rover_state": np.r_[self.rig.position, self.rig.velocity, self.rig.angle],
        }
        self.writer.append_step(record)

    def _check_speed(self) -> None:
        from soil import SimulationDiverged

        v = self.sim.velocities()
        speed = np.sqrt(np.max(np.einsum("ij,ij->i", v, v))) if len(v) else 0.0
        limit = self.scene.max_speed()
        if not np.isfinite(speed) or speed > limit:
            raise SimulationDiverged(f"a grain moves at {speed:.3g} m/s, above run.max_speed = {limit:.3g} m/s "
                                     "(an explosion)")

    def _snapshot(self) -> None:
        sim = self.sim
        control = sim.control
        vertices, _, owner = self.mesh
        posed = np.einsum("vij,vj->vi", control.body_rotation_host[owner], vertices) + control.body_position_host[owner]
        self.writer.add_snapshot(self.coupler.time, sim.positions(), sim.velocities().astype(np.float32),
                                 posed.astype(np.float32))

    def _checkpoint(self, wall: float = 0.0) -> None:
        self.writer.flush()
        data = _capture(self)
        data["runner/wall_time"] = np.float64(self.wall_before + wall)
        save_checkpoint(os.path.join(self.out_dir, CHECKPOINT_FILE), data)
        self._last_checkpoint_time = self.coupler.time

    _last_checkpoint_time = 0.0
    _steps_at_start = 0

    # -- results -----------------------------------------------------------------------------
    def summary(self, wall: float) -> dict:
        rec = self.coupler.records()
        steps = len(rec["time"])
        out = {"simulated_time": float(self.coupler.time), "macro_steps": int(self.coupler.step_count),
               "wall_time": float(self.wall_before + wall), "particle_count": int(self.sim.model.particle_count),
               "dt": self.dt, "macro_step": self.macro_step}
        if steps:
            tail = slice(steps // 2, steps)
            velocity = rec["linear_velocity"][:, 0, 0]
            rim = self.rig.omega * self.rig.radius
            slip = 1.0 - velocity / rim if rim else np.zeros_like(velocity)
            travel = rec["position"][:, 0, 0] - self.x0
            duration = rec["time"][-1] - rec["time"][0] + self.macro_step
            out.update(
                travel=float(travel[-1]), mean_slip=float(np.mean(slip[tail])),
                travel_slip=float(1.0 - travel[-1] / (rim * duration)) if rim else 0.0,
                mean_sinkage=float(np.mean(rec["sinkage"][tail, 0])), final_sinkage=float(rec["sinkage"][-1, 0]),
                mean_drawbar_pull=float(np.mean(rec["force"][tail, 0, 0])),
                mean_driving_torque=float(np.mean(-rec["torque"][tail, 0, 1])),
                coupling_energy_created=float(self.coupler.energy_created))
        if wall > 0:
            done = self.coupler.step_count - getattr(self, "_steps_at_start", 0)
            out["particle_steps_per_second"] = float(self.sim.model.particle_count * self.substeps * done / wall)
        return out


# ------------------------------------------------------------------------------------
# checkpoints


def save_checkpoint(path: str, data: dict) -> None:
    """Write a checkpoint atomically (soil.stability.write_checkpoint: temp file, fsync, os.replace)."""
    write_checkpoint(path, data)


def load_checkpoint(path: str) -> dict:
    with np.load(path, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}


_WRENCH_FIELDS = ("force", "torque", "force_end", "torque_end", "contact_count", "sinkage", "work_on_soil")


def _capture(runner: Runner) -> dict:
    """Everything the continuation depends on, as numpy arrays (no pickles, no RNG)."""
    sim, rig, coupler, soil = runner.sim, runner.rig, runner.coupler, runner.soil
    data = {f"soil/{k}": np.asarray(v) for k, v in sim.state.to_numpy().items()}
    data["soil/steps"] = np.int64(sim.steps)
    data["soil/warned_wall"] = np.bool_(soil._warned_wall)
    control = sim.control
    for name in ("body_position_host", "body_rotation_host", "body_velocity_host", "body_angular_velocity_host"):
        data[f"control/{name}"] = getattr(control, name).copy()
    data["rig/position"] = rig.position.copy()
    data["rig/velocity"] = rig.velocity.copy()
    data["rig/angle"] = np.float64(rig.angle)
    data["rig/time"] = np.float64(rig.time)
    for name in _WRENCH_FIELDS:
        data[f"rig/wrench/{name}"] = np.asarray(getattr(rig._wrench, name))
    data["coupler/time"] = np.float64(coupler.time)
    data["coupler/step_count"] = np.int64(coupler.step_count)
    data["coupler/energy_created"] = np.float64(coupler.energy_created)
    data["coupler/energy_exchanged"] = np.float64(coupler.energy_exchanged)
    data["coupler/warned"] = np.bool_(coupler._warned)
    for key, value in coupler.records().items():
        data[f"coupler/records/{key}"] = value
    for which in ("_lagged", "_last"):
        for name in _WRENCH_FIELDS:
            data[f"coupler/{which}/{name}"] = np.array([np.asarray(getattr(w, name)) for w in getattr(coupler, which)])
    data["runner/steps"] = np.int64(runner.writer.steps)
    data["runner/snapshots"] = np.int64(runner.writer.snapshots)
    data["runner/x0"] = np.float64(runner.x0)
    data["runner/scene_toml"] = np.array(runner.scene.to_toml())
    return data


def _restore(runner: Runner, data: dict) -> None:
    from .contract import WheelWrench

    sim, rig, soil = runner.sim, runner.rig, runner.soil
    state = {k[len("soil/"):]: v for k, v in data.items() if k.startswith("soil/") and k not in
             ("soil/steps", "soil/warned_wall")}
    sim.state.load_numpy(state)
    # a Simulation made before the load has a second buffer of the old capacity
    if sim._next.capacity < sim.state.capacity:
        sim._next.grow_capacity(sim.state.capacity)
    sim.steps = int(data["soil/steps"])
    soil._warned_wall = bool(data["soil/warned_wall"])
    control = sim.control
    for name in ("body_position_host", "body_rotation_host", "body_velocity_host", "body_angular_velocity_host"):
        getattr(control, name)[...] = data[f"control/{name}"]
    control._dirty = True
    control.push()
    rig.position = data["rig/position"].copy()
    rig.velocity = data["rig/velocity"].copy()
    rig.angle = float(data["rig/angle"])
    rig.time = float(data["rig/time"])
    rig._wrench = _wrench(data, "rig/wrench/", None, WheelWrench)
    coupler = runner._make_coupler()
    coupler.time = float(data["coupler/time"])
    coupler.step_count = int(data["coupler/step_count"])
    coupler.energy_created = float(data["coupler/energy_created"])
    coupler.energy_exchanged = float(data["coupler/energy_exchanged"])
    coupler._warned = bool(data["coupler/warned"])
    for key in coupler._records:
        coupler._records[key] = list(data[f"coupler/records/{key}"])
    for which in ("_lagged", "_last"):
        count = len(data[f"coupler/{which}/force"])
        setattr(coupler, which, [_wrench(data, f"coupler/{which}/", i, WheelWrench) for i in range(count)])
    runner.coupler = coupler
    runner.x0 = float(data["runner/x0"])
    runner.wall_before = float(data.get("runner/wall_time", 0.0))
    runner._last_checkpoint_time = coupler.time
    runner._steps_at_start = coupler.step_count


def _wrench(data, prefix, index, cls):
    values = {}
    for name in _WRENCH_FIELDS:
        value = data[prefix + name] if index is None else data[prefix + name][index]
        if name == "contact_count":
            values[name] = int(value)
        elif np.ndim(value) == 0:
            values[name] = float(value)
        else:
            values[name] = np.array(value, dtype=np.float64)
    return cls(**values)


def _wheel_mesh(shapes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Display meshes of the wheels: (vertices (V, 3), triangles (F, 3), owner wheel (V,))."""
    vertices, triangles, owner = [], [], []
    offset = 0
    for index, shape in enumerate(shapes):
        if hasattr(shape, "to_mesh"):
            v, t = shape.to_mesh(arc_segments=240)
        else:
            v, t = shape.vertices, shape.triangles
        vertices.append(v)
        triangles.append(t + offset)
        owner.append(np.full(len(v), index, dtype=np.int32))
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(triangles), np.concatenate(owner)


def _install_sigint(runner: Runner):
    """First Ctrl-C: stop cleanly after the macro step (with a checkpoint); second: at once."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        if runner.stop_requested:
            raise KeyboardInterrupt("interrupted twice: stopped at once")
        runner.stop_requested = True
        runner.log("\nCtrl-C: finishing the macro step and writing a checkpoint (Ctrl-C again to stop at once)")

    return signal.signal(signal.SIGINT, handler)


# ------------------------------------------------------------------------------------
# entry points


def run_scene(scene: Scene | str, out_dir: str, overwrite: bool = False, progress: bool = True, log=print,
              hooks: dict | None = None, overrides=None) -> RunResult:
    """Run a scene (a Scene or a TOML path) into `out_dir`."""
    source = ""
    if not isinstance(scene, Scene):
        path = os.fspath(scene)
        scene = load_scene(path, overrides)
        with open(path) as f:
            source = f.read()
    runner = Runner(absolute_paths(scene), out_dir, progress=progress, log=log, hooks=hooks)
    return runner.start_new(scene_source=source, overwrite=overwrite)


def resume(out_dir: str, progress: bool = True, log=print, hooks: dict | None = None) -> RunResult:
    """Continue a run from its checkpoint to the result an uninterrupted run gives."""
    out_dir = os.path.abspath(out_dir)
    checkpoint_path = os.path.join(out_dir, CHECKPOINT_FILE)
    for name in (SCENE_FILE, RUN_FILE, CHECKPOINT_FILE, RESULTS_FILE):
        if not os.path.isfile(os.path.join(out_dir, name)):
            raise FileNotFoundError(f"{out_dir!r} has no {name}: not a run folder that can be resumed")
    checkpoint = load_checkpoint(checkpoint_path)
    scene = scene_from_text(str(checkpoint["runner/scene_toml"]), check_files=False)
    with open(os.path.join(out_dir, SCENE_FILE)) as f:
        if f.read() != scene.to_toml():
            log("note: scene.toml was edited after the run started; the checkpoint's copy of the scene is used")
    runner = Runner(scene, out_dir, progress=progress, log=log, hooks=hooks)
    if int(checkpoint["coupler/step_count"]) >= scene.macro_step_count():
        with open(os.path.join(out_dir, RUN_FILE)) as f:
            info = json.load(f)
        log(f"{out_dir}: the run is already complete")
        return RunResult(out_dir, "complete", info.get("summary", {}))
    return runner.continue_from(checkpoint)


def absolute_paths(scene: Scene) -> Scene:
    """The scene with wheel.file and bed.bed_file made absolute (the run folder's scene.toml must not
    depend on where the original scene file was)."""
    wheel = scene.wheel
    if wheel.type == "mesh" and wheel.file:
        wheel = wheel.model_copy(update={"file": scene.resolve(wheel.file)})
    bed = scene.bed
    if bed.bed_file:
        bed = bed.model_copy(update={"bed_file": scene.resolve(bed.bed_file)})
    return scene.model_copy(update={"wheel": wheel, "bed": bed})


def final_state(out_dir: str) -> dict:
    """The soil state arrays of the latest checkpoint (for comparisons)."""
    data = load_checkpoint(os.path.join(out_dir, CHECKPOINT_FILE))
    return {k: v for k, v in data.items() if k.startswith(("soil/", "rig/", "coupler/"))}


def wheel_mesh_for(scene: Scene):
    return _wheel_mesh([scene.wheel_shape()])


__all__ = ["OutputExistsError", "RunDiverged", "RunInterrupted", "RunResult", "Runner", "bed_key", "final_state",
           "load_checkpoint", "prepare_output", "resume", "run_scene", "save_checkpoint", "settled_bed"]
