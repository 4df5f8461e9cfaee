"""Studies over many runs, on dask.distributed (LocalCluster by default, or --scheduler ADDRESS).

- precision: the paper's experiment (figures 3, 4). N replicas per precision that differ
  only in the summation order (run.order_seed = replica index: a permutation of the
  particle indices), all on the same settled bed. Reports wall time and the scatter
  (std, min, max) of travel, slip and sinkage per precision, as a table
  (study.csv, study.json) and plots (replicas overlaid; scatter per precision).
- timestep: the largest stable DEM step (soil.advisor.largest_stable_step: the step grows
  geometrically until the scene explodes) next to the advisor's recommended range.
- sweep: a grid over scene keys (--param wheel.radius=0.03,0.04 ...), one run per point.

Warp's CPU kernels are single-threaded, so the cluster uses processes with one thread
each, as many as the machine has cores. A replica that fails is reported; the others
still finish. `executor="serial"` runs the tasks one after another in this process
(tests, debugging); results are the same on the CPU.
"""

from __future__ import annotations

import itertools
import math
import os
import time
import traceback

import numpy as np

from .runner import BED_FILE, settled_bed, write_json
from .scene import Scene, SceneError, scene_from_text

PRECISION_ORDER = ("single", "mixed", "double")


# ------------------------------------------------------------------------------------
# tasks (module-level functions: picklable for dask workers)


def run_task(task: dict) -> dict:
    """Run one scene (task: scene_toml, base_dir, overrides, out_dir, label); never raises."""
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    from .runner import run_scene

    started = time.perf_counter()
    out = {"label": task.get("label"), "out_dir": task["out_dir"], "overrides": task.get("overrides", {})}
    try:
        scene = scene_from_text(task["scene_toml"], base_dir=task.get("base_dir"), overrides=task.get("overrides"))
        result = run_scene(scene, task["out_dir"], overwrite=task.get("overwrite", False), progress=False, log=None)
        out.update(ok=True, status=result.status, summary=result.summary)
    except BaseException as error:  # noqa: BLE001 - a failed replica is a result, not a crash
        out.update(ok=False, status="failed", error=f"{type(error).__name__}: {error}",
                   traceback=traceback.format_exc(limit=5))
        if isinstance(error, KeyboardInterrupt):
            raise
    out["wall_time"] = time.perf_counter() - started
    return out


def settle_task(task: dict) -> dict:
    """Settle the bed of a scene into task['folder'] (cached there)."""
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    scene = scene_from_text(task["scene_toml"], base_dir=task.get("base_dir"), overrides=task.get("overrides"))
    os.makedirs(task["folder"], exist_ok=True)
    path, info = settled_bed(scene, task["folder"], progress=False, log=lambda *a, **k: None)
    return {"path": path, "info": info}


# ------------------------------------------------------------------------------------
# execution


class Executor:
    """Maps tasks over a dask cluster (or serially). Use as a context manager."""

    def __init__(self, kind: str = "dask", scheduler: str | None = None, workers: int | None = None, log=print):
        self.kind = kind
        self.scheduler = scheduler
        self.workers = workers or os.cpu_count() or 1
        self.log = log
        self.client = None
        self.cluster = None

    def __enter__(self):
        if self.kind == "serial":
            return self
        from dask.distributed import Client, LocalCluster

        if self.scheduler:
            self.client = Client(self.scheduler)
        else:
            self.cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                        dashboard_address=None)
            self.client = Client(self.cluster)
        self.log(f"dask: {self.client}")
        return self

    def __exit__(self, *exc):
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        return False

    def map(self, function, tasks: list[dict], describe=lambda t: t.get("label")) -> list[dict]:
        """Results in task order; a task whose worker died becomes {'ok': False, 'error': ...}."""
        if self.kind == "serial":
            results = []
            for task in tasks:
                results.append(function(task))
                self._report(results[-1], describe(task), len(results), len(tasks))
            return results
        from dask.distributed import as_completed

        futures = self.client.map(function, tasks, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        results: list = [None] * len(tasks)
        done = 0
        for future in as_completed(futures):
            i = index[future.key]
            try:
                results[i] = future.result()
            except Exception as error:  # the worker itself failed
                results[i] = {"label": describe(tasks[i]), "ok": False, "status": "failed",
                              "error": f"{type(error).__name__}: {error}", "out_dir": tasks[i].get("out_dir")}
            done += 1
            self._report(results[i], describe(tasks[i]), done, len(tasks))
        return results

    def _report(self, result, label, done, total):
        if not isinstance(result, dict) or "ok" not in result:
            return
        state = "ok" if result.get("ok") else f"FAILED: {result.get('error')}"
        wall = result.get("wall_time")
        self.log(f"[{done}/{total}] {label}: {state}" + (f" ({wall:.1f} s)" if wall else ""))


# ------------------------------------------------------------------------------------
# precision study


def precision_study(scene: Scene, out_dir: str, replicas: int = 3, precisions=PRECISION_ORDER,
                    executor: str = "dask", scheduler: str | None = None, workers: int | None = None,
                    overwrite: bool = False, log=print, plot: bool = True) -> dict:
    """The paper's replica experiment; returns {'rows': table rows, 'replicas': per-replica results}."""
    from .runner import absolute_paths

    scene = absolute_paths(scene)
    for p in precisions:
        if p not in PRECISION_ORDER:
            raise SceneError([f"--precisions: unknown precision {p!r}; allowed: {', '.join(PRECISION_ORDER)}"])
    if replicas < 1:
        raise ValueError("--replicas must be >= 1")
    out_dir = os.path.abspath(out_dir)
    prepare_study(out_dir, overwrite)
    text = scene.to_toml()
    with Executor(executor, scheduler, workers, log) as ex:
        bed = _shared_bed(scene, out_dir, ex, log)
        tasks = []
        for precision in precisions:
            for k in range(replicas):
                tasks.append({"scene_toml": text, "out_dir": os.path.join(out_dir, precision, f"replica_{k:03d}"),
                              "overrides": {"scene.precision": precision, "run.order_seed": k, "bed.bed_file": bed},
                              "label": f"{precision}/replica_{k:03d}", "precision": precision, "replica": k})
        started = time.perf_counter()
        results = ex.map(run_task, tasks)
        wall = time.perf_counter() - started
    for task, result in zip(tasks, results):
        result["precision"] = task["precision"]
        result["replica"] = task["replica"]
    rows = scatter_table(results, "precision", [p for p in precisions])
    report = {"kind": "precision", "replicas": results, "rows": rows, "wall_time": wall, "bed_file": bed,
              "scene_toml": text}
    _write_report(out_dir, report, rows, log)
    if plot:
        _plots(out_dir, rows, log)
    return report


def scatter_table(results: list[dict], key: str, groups: list) -> list[dict]:
    """Per group: replicas ok/failed, wall time, and mean/std/min/max of travel, slip, sinkage."""
    rows = []
    for group in groups:
        members = [r for r in results if r.get(key) == group]
        ok = [r for r in members if r.get("ok")]
        row = {key: group, "replicas": len(members), "ok": len(ok), "failed": len(members) - len(ok)}
        if ok:
            row["wall_time_mean"] = float(np.mean([r["summary"]["wall_time"] for r in ok]))
            for name in ("travel", "mean_slip", "mean_sinkage", "mean_drawbar_pull"):
                values = np.array([r["summary"].get(name, np.nan) for r in ok], dtype=float)
                row[f"{name}_mean"] = float(np.mean(values))
                row[f"{name}_std"] = float(np.std(values, ddof=1)) if len(values) > 1 else 0.0
                row[f"{name}_min"] = float(np.min(values))
                row[f"{name}_max"] = float(np.max(values))
        row["errors"] = [r.get("error") for r in members if not r.get("ok")]
        rows.append(row)
    return rows


TABLE_KEYS = ["ok", "failed", "wall_time_mean", "travel_mean", "travel_std", "travel_min", "travel_max",
              "mean_slip_mean", "mean_slip_std", "mean_slip_min", "mean_slip_max", "mean_sinkage_mean",
              "mean_sinkage_std", "mean_sinkage_min", "mean_sinkage_max"]


def _write_report(out_dir: str, report: dict, rows: list[dict], log) -> None:
    from .plots import plot_table

    write_json(os.path.join(out_dir, "study.json"), report)
    first = [k for k in rows[0] if k not in TABLE_KEYS and k not in ("replicas", "errors")] if rows else []
    keys = first + [k for k in TABLE_KEYS if any(k in r for r in rows)]
    with open(os.path.join(out_dir, "study.csv"), "w") as f:
        f.write(",".join(keys) + "\n")
        for r in rows:
            f.write(",".join("" if r.get(k) is None else str(r.get(k)) for k in keys) + "\n")
    log(plot_table(rows, keys))
    for r in rows:
        for error in r.get("errors", []):
            log(f"failed: {error}")


def _plots(out_dir: str, rows: list[dict], log) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plots import plot_output

    try:
        written = plot_output(out_dir)
    except FileNotFoundError as error:
        log(str(error))
        return
    groups = [r for r in rows if r.get("ok")]
    if groups:
        key = [k for k in rows[0] if k not in TABLE_KEYS and k not in ("replicas", "errors")][0]
        fig, axes = plt.subplots(1, 3, figsize=(14, 4))
        for ax, (name, label, scale) in zip(axes, [("travel", "travel [mm]", 1e3), ("mean_slip", "mean slip [-]", 1),
                                                   ("mean_sinkage", "mean sinkage [mm]", 1e3)]):
            x = np.arange(len(groups))
            mean = np.array([g[f"{name}_mean"] for g in groups]) * scale
            low = mean - np.array([g[f"{name}_min"] for g in groups]) * scale
            high = np.array([g[f"{name}_max"] for g in groups]) * scale - mean
            std = np.array([g[f"{name}_std"] for g in groups]) * scale
            ax.errorbar(x, mean, yerr=[low, high], fmt="o", capsize=6, label="min-max")
            ax.errorbar(x + 0.08, mean, yerr=std, fmt="s", capsize=3, label="std")
            ax.set_xticks(x, [str(g[key]) for g in groups])
            ax.set_ylabel(label)
            ax.grid(True, alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.suptitle(f"scatter over replicas ({groups[0]['ok']} per group)")
        fig.tight_layout()
        path = os.path.join(out_dir, "plots", "scatter.png")
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)
    log("plots: " + ", ".join(written))


def prepare_study(out_dir: str, overwrite: bool) -> None:
    os.makedirs(out_dir, exist_ok=True)
    present = [n for n in os.listdir(out_dir) if n not in (BED_FILE, "bed.json", "beds")]
    if present and not overwrite:
        raise FileExistsError(f"study folder {out_dir!r} is not empty ({', '.join(sorted(present)[:6])}); nothing is "
                              "overwritten: choose another --out or pass --overwrite (the settled bed is kept)")
    if present:
        import shutil

        for name in present:
            path = os.path.join(out_dir, name)
            shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)


def _shared_bed(scene: Scene, out_dir: str, ex: Executor, log) -> str:
    if scene.bed.bed_file:
        return scene.resolve(scene.bed.bed_file)
    log("settling the shared bed ...")
    result = ex.map(settle_task, [{"scene_toml": scene.to_toml(), "folder": out_dir, "label": "bed"}],
                    describe=lambda t: "bed")[0]
    if not isinstance(result, dict) or "path" not in result:
        raise RuntimeError(f"settling the bed failed: {result}")
    return result["path"]


# ------------------------------------------------------------------------------------
# sweep


def parse_params(params: list[str]) -> dict[str, list]:
    """['wheel.radius=0.03,0.04', ...] -> {'wheel.radius': [0.03, 0.04], ...} (values read as TOML)."""
    from .scene import tomllib

    grid = {}
    for text in params:
        if "=" not in text:
            raise SceneError([f"--param {text!r}: expected key=v1,v2,..."])
        key, values = text.split("=", 1)
        parsed = []
        for value in values.split(","):
            try:
                parsed.append(tomllib.loads(f"v = {value.strip()}")["v"])
            except tomllib.TOMLDecodeError:
                parsed.append(value.strip())
        grid[key.strip()] = parsed
    return grid


def sweep(scene: Scene, out_dir: str, params: list[str], executor: str = "dask", scheduler: str | None = None,
          workers: int | None = None, overwrite: bool = False, log=print, plot: bool = True) -> dict:
    """One run per point of the grid; points that share a bed share one settled bed."""
    from .runner import absolute_paths, bed_key

    scene = absolute_paths(scene)
    grid = parse_params(params)
    if not grid:
        raise SceneError(["--param: give at least one key=v1,v2,..."])
    text = scene.to_toml()
    points = [dict(zip(grid, values)) for values in itertools.product(*grid.values())]
    scenes, problems = [], []
    for point in points:  # validate every point before running any
        try:
            scenes.append(scene_from_text(text, overrides=point))
        except SceneError as error:
            problems += [f"point {point}: {p}" for p in error.problems]
    if problems:
        raise SceneError(problems)
    out_dir = os.path.abspath(out_dir)
    prepare_study(out_dir, overwrite)
    with Executor(executor, scheduler, workers, log) as ex:
        beds = {}
        for s in scenes:
            if not s.bed.bed_file:
                beds.setdefault(bed_key(s), s)
        settled = ex.map(settle_task, [{"scene_toml": s.to_toml(), "folder": os.path.join(out_dir, "beds", key),
                                        "label": f"bed {key}"} for key, s in beds.items()])
        bed_paths = {key: r.get("path") for key, r in zip(beds, settled)}
        tasks = []
        for i, (point, s) in enumerate(zip(points, scenes)):
            overrides = dict(point)
            if not s.bed.bed_file:
                overrides["bed.bed_file"] = bed_paths[bed_key(s)]
            name = f"{i:03d}_" + "_".join(f"{k.split('.')[-1]}={v}" for k, v in point.items())
            tasks.append({"scene_toml": text, "overrides": overrides, "out_dir": os.path.join(out_dir, name),
                          "label": name, "point": point})
        results = ex.map(run_task, tasks)
    rows = []
    for task, result in zip(tasks, results):
        row = {**task["point"], "ok": result.get("ok"), "status": result.get("status")}
        row.update({k: result.get("summary", {}).get(k) for k in ("travel", "mean_slip", "mean_sinkage",
                                                                   "mean_drawbar_pull", "wall_time")})
        if not result.get("ok"):
            row["error"] = result.get("error")
        rows.append(row)
    report = {"kind": "sweep", "grid": grid, "rows": rows, "runs": results, "scene_toml": text}
    write_json(os.path.join(out_dir, "study.json"), report)
    from .plots import plot_table

    keys = list(grid) + ["ok", "travel", "mean_slip", "mean_sinkage", "mean_drawbar_pull", "wall_time"]
    table = plot_table(rows, keys)
    log(table)
    with open(os.path.join(out_dir, "study.csv"), "w") as f:
        f.write(",".join(keys) + "\n")
        for r in rows:
            f.write(",".join("" if r.get(k) is None else str(r.get(k)) for k in keys) + "\n")
    for r in rows:
        if r.get("error"):
            log(f"failed: {r['error']}")
    if plot:
        from .plots import plot_output

        try:
            log("plots: " + ", ".join(plot_output(out_dir)))
        except FileNotFoundError as error:
            log(str(error))
    return report


# ------------------------------------------------------------------------------------
# time-step study


def timestep_study(scene: Scene, out_dir: str, duration: float = 0.2, growth: float = 1.5,
                   dt_start_factor: float = 0.1, overwrite: bool = False, log=print) -> dict:
    """Largest stable DEM step for the scene's bed with the wheel resting on it, plus the advisor's range."""
    from soil import Simulation
    from soil.bed import load_bed, restore_state

    from .runner import absolute_paths

    scene = absolute_paths(scene)
    out_dir = os.path.abspath(out_dir)
    prepare_study(out_dir, overwrite)
    bed_path, _ = settled_bed(scene, out_dir, progress=False, log=log)

    def make_simulation():
        builder, saved = load_bed(bed_path)
        builder.add_wheel(scene.wheel_shape(), scene.wheel_material())
        model, state, control = builder.finalize(device=scene.scene.device, precision=scene.scene.precision,
                                                 law=scene.contact_law())
        restore_state(model, state, saved)
        sim = Simulation(model, state, control)
        outer, _, _ = scene.wheel_extent()
        hub = scene.start_position(float(saved["metrics"]["height"]))
        hub[2] -= 0.1 * scene.bed.radius_mean  # pressed in a little: wheel contacts are in the test
        sim.control.set_body_motion(0, hub, [1, 0, 0, 0], [scene.testbed.omega * outer, 0, 0],
                                    [0, scene.testbed.omega, 0])
        sim.refresh_forces()
        return sim

    rayleigh = scene.rayleigh_step()
    report = {"kind": "timestep", "rayleigh_step": rayleigh, "scene_dt": scene.time_steps()[0]}
    try:
        from soil import advisor
    except ImportError:  # pragma: no cover - advisor is part of soil now
        advisor = None
    if advisor is not None and hasattr(advisor, "largest_stable_step"):
        search = advisor.largest_stable_step(make_simulation, duration=duration, dt_start=dt_start_factor * rayleigh,
                                             growth=growth)
        report.update(largest_stable=search.largest_stable, first_unstable=search.first_unstable,
                      recommended=search.recommended,
                      tried=[{"dt": dt, "stable": ok, "message": m} for dt, ok, m in search.tried])
        advice = advisor.recommended_time_step(make_simulation())
        report["advisor"] = {"dt_min": advice.dt_min, "dt_max": advice.dt_max,
                             "critical_step": advice.critical_step, "contact_time": advice.contact_time}
    else:  # pragma: no cover
        raise RuntimeError("soil.advisor.largest_stable_step is not available")
    write_json(os.path.join(out_dir, "study.json"), report)
    for t in report["tried"]:
        log(f"dt = {t['dt']:.4g} s ({t['dt'] / rayleigh:.3g} x Rayleigh): {'stable' if t['stable'] else 'UNSTABLE'}")
    log(f"largest stable step {_s(report['largest_stable'])} s, first unstable {_s(report['first_unstable'])} s, "
        f"recommended {_s(report['recommended'])} s; Rayleigh {rayleigh:.4g} s; the scene uses "
        f"{report['scene_dt']:.4g} s")
    return report


def _s(value) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.4g}"
