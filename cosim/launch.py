"""The entry points of a run: run a plan, run a scene, resume a run folder.

    result = run_scene("examples/phobos_single_wheel.toml", "runs/phobos")
    result = resume("runs/phobos")

`run_scene` resolves the scene into a plan (cosim.plan); `run_plan` takes the output folder's
lock (cosim.folders), settles or reuses the bed when the plan's terrain needs one (cosim.beds,
cosim.system.needs_bed), builds the coupled system (cosim.system) and only then replaces a
previous run; then the Runner (cosim.runner) steps it, writing results.h5 (cosim.output) with
the rows of cosim.records. `resume` checks a run folder's files, rebuilds the system from its
checkpoint.npz and continues to the result an uninterrupted run gives (bitwise on the CPU).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import uuid
from collections.abc import Iterator

import numpy as np

from soil.errors import ArgumentError
from soil.files import atomic_write_text
from soil.stability import read_checkpoint

from . import metrics, records
from .beds import BED_FILE, Bed, bed_from_file, check_memory, memory_estimate, save_bed_cache, settled_bed
from .contract import SoilSide
from .folders import EDITED_SCENE_FILE, RUN_FILE, SCENE_FILE, RunFolder, read_json, write_json
from .output import ResultsWriter, read_series, stored_wheel_mesh
from .plan import RunPlan, load_plan, resolve
from .runner import Runner, RunResult
from .scene import Scene, SceneError, scene_from_text
from .scm_soil import check_scm_grid
from .system import CoupledSystem, needs_bed, used_mesh, validity, wheel_display_mesh

log = logging.getLogger(__name__)


def run_plan(
    plan: RunPlan,
    out_dir: str,
    overwrite: bool = False,
    progress: bool = False,
    hooks: dict | None = None,
    source: str = "",
) -> RunResult:
    """Run a resolved plan into `out_dir` (see the module docstring)."""
    with open_run(plan, out_dir, overwrite=overwrite, progress=progress, source=source) as (system, writer, folder):
        return Runner(system, writer, folder, progress=progress, hooks=hooks).run()


@contextlib.contextmanager
def open_run(
    plan: RunPlan,
    out_dir: str,
    overwrite: bool = False,
    progress: bool = False,
    source: str = "",
    soil: SoilSide | None = None,
) -> Iterator[tuple[CoupledSystem, ResultsWriter, RunFolder]]:
    """A run set up in `out_dir` and not yet stepped: (system, writer, folder), the folder locked until the
    block ends. `soil`: the soil side to couple (a world of a batch, cosim.batch); None: the plan's own,
    on its settled bed."""
    bedded = needs_bed(plan)
    if soil is None:  # before anything is allocated or written
        grains = (0, 0)
        if bedded:
            check_memory(plan)
            estimate = memory_estimate(plan)
            grains = (estimate.device_bytes, estimate.host_bytes)
        check_scm_grid(plan, reserved=grains)  # a mixed terrain's SCM wheels beside its grains
    folder = RunFolder(out_dir)
    with folder.locked():
        folder.check_free(overwrite)
        # a bed settled over the cache of a run still in the folder is written once that run is gone: the run
        # stays resumable, on its own bed, until the new one is built (a stop or a kill before then)
        replacing = folder.holds_run()
        bed = settled_bed(plan, folder.path, progress=progress, save=not replacing) if bedded else None
        system = CoupledSystem.build(plan, bed, soil=soil)
        findings = validity(plan, system.soil.surface_height)
        for finding in findings:
            if not finding.ok:
                log.warning("validity: %s", finding.message)
        # everything is built: only now the previous run goes
        folder.clear_run()
        if bed is not None and replacing and bed.settled is not None:  # settled now, not read from a file
            save_bed_cache(bed)
        run_id = uuid.uuid4().hex
        # run.json first: a folder with a scene.toml of a run and no run.json is no run's (RunFolder.holds_run)
        write_json(
            folder.file(RUN_FILE),
            {
                "status": "running",
                "run_id": run_id,
                "device": plan.device,
                "precision": plan.precision,
                "bed": {} if bed is None else bed.info,
                "findings": [f.as_dict() for f in findings],
            },
        )
        atomic_write_text(folder.file(SCENE_FILE), plan.scene.to_toml())
        try:
            particles = system.soil.particles()
            writer = ResultsWriter.create(
                folder.results,
                attrs={**records.attributes(plan, system, source, findings), "run_id": run_id},
                radius=np.zeros(0) if particles is None else particles.radius,
                wheel_count=len(system.rover.wheel_names),
                mesh=system.wheel_mesh(),
                rover_columns=system.rover.state_columns,
                rover_units=system.rover.state_units,
                boundaries=system.boundaries(),
                flush_every=plan.output.flush_every,
                ragged=particles is not None and particles.ids is not None,
            )
            yield system, writer, folder
        finally:
            system.close()


def run_scene(
    scene: Scene | str | os.PathLike,
    out_dir: str,
    overwrite: bool = False,
    progress: bool = False,
    hooks: dict | None = None,
    overrides=None,
) -> RunResult:
    """Run a scene (a Scene or a TOML path, with --set overrides) into `out_dir`."""
    source = ""
    if isinstance(scene, Scene):
        plan = resolve(scene)
    else:
        path = os.fspath(scene)
        plan = load_plan(path, overrides)
        with open(path) as f:
            source = f.read()
    return run_plan(plan, out_dir, overwrite=overwrite, progress=progress, hooks=hooks, source=source)


def load_checkpoint(path: str) -> dict:
    """A checkpoint's arrays (numpy; no pickles), its checksum verified (DamagedFileError when damaged)."""
    return read_checkpoint(path)


FINISHED = ("complete", "unsteady")
"""The statuses of a run whose results are written to the end."""


def resume(out_dir: str, progress: bool = False, hooks: dict | None = None) -> RunResult:
    """Continue a run from its checkpoint to the result an uninterrupted run gives.

    Every file is checked before anything is changed: a damaged results.h5 or checkpoint, or a
    checkpoint of another run, is refused (DamagedFileError naming the file and what is left) and the
    folder stays as it was. A run whose drive is complete in the checkpoint but whose results were not
    finished (killed after its final checkpoint) gets its results finished: status, summary, run.json.
    A run that diverged is refused (ArgumentError): its resume would repeat the same steps.
    """
    folder = RunFolder(out_dir)
    if not os.path.isdir(folder.path):
        raise ArgumentError(f"{folder.path!r} is not a folder: nothing to resume")
    needed = (SCENE_FILE, RUN_FILE, os.path.basename(folder.checkpoint), os.path.basename(folder.results))

    def check_files() -> None:
        missing = [name for name in needed if not os.path.isfile(folder.file(name))]
        if missing == [os.path.basename(folder.checkpoint)]:  # a run without a checkpoint: say how it ended
            info = read_json(folder.file(RUN_FILE))
            status, message = info.get("status"), info.get("message") or "run.json has no message"
            summary = info.get("summary")
            summary = summary if isinstance(summary, dict) else {}
            if status in FINISHED and summary and not metrics.summary_is_current(summary):
                raise ArgumentError(
                    f"{folder.path!r}: the run finished ({status}) under an older steady-window rule "
                    "(cosim.metrics.SUMMARY_RULE), and its checkpoint is gone: its summary cannot be made again; run "
                    f"it again: cosim run {folder.file(SCENE_FILE)} --out {folder.path} --overwrite"
                )
            if status in FINISHED:
                raise ArgumentError(
                    f"{folder.path!r}: the run finished ({status}) and its checkpoint is gone: nothing is left to "
                    "resume (its results are in results.h5)"
                )
            again = f"cosim run {folder.file(SCENE_FILE)} --out {folder.path} --overwrite"
            if status == "diverged" and not summary.get("diverged_elsewhere"):  # as it was, it diverges again
                raise ArgumentError(
                    f"{folder.path!r}: the run diverged before its first checkpoint ({message}); nothing to resume "
                    f"from: run its scene again with the change that message names (cosim run "
                    f"{folder.file(SCENE_FILE)} --set KEY=VALUE --out NEW_FOLDER)"
                )
            if status in ("diverged", "failed"):
                raise ArgumentError(
                    f"{folder.path!r}: the run {status} before its first checkpoint ({message}); nothing to resume "
                    f"from: run it again: {again}"
                )
            raise ArgumentError(
                f"{folder.path!r}: the run stopped before its first checkpoint (output.checkpoint_interval into "
                f"it): nothing to resume from; run it again: {again}"
            )
        if missing:
            raise ArgumentError(f"{folder.path!r} has no {missing[0]}: not a run folder that can be resumed")

    check_files()  # before the lock: a folder that is not a run gets no .lock either
    with folder.locked():
        check_files()
        checkpoint, info = _checked_inputs(folder)
        if diverged_here(folder.results):  # the same steps from the same state: again
            raise ArgumentError(
                f"{folder.path!r} diverged ({info.get('message') or 'run.json has no message'}); a resume repeats "
                f"the same steps from its checkpoint (t = {float(checkpoint['coupler/time']):.6g} s) and diverges "
                f"again: run its scene again with the change that message names (cosim run "
                f"{folder.file(SCENE_FILE)} --set KEY=VALUE --out NEW_FOLDER); nothing was changed"
            )
        base_dir = str(checkpoint["scene_base_dir"]) if "scene_base_dir" in checkpoint else ""
        scene = scene_from_text(str(checkpoint["scene_toml"]), base_dir=base_dir or None)
        plan = resolve(scene)
        _check_macro_step(checkpoint, plan)
        steps = int(checkpoint["loop/steps"])
        if checkpoint["coupler/step_count"] and _finished(checkpoint, plan):
            finished = info.get("status") in FINISHED and _results_status(folder.results) == info["status"]
            if finished and metrics.summary_is_current(info.get("summary")):
                log.info("%s: the run is already complete", folder.path)
                _put_back_scene(folder, scene.to_toml())
                return RunResult(folder.path, info["status"], info.get("summary", {}))
            if finished:
                log.warning(
                    "%s: its summary was made under an older steady-window rule (cosim.metrics.SUMMARY_RULE); "
                    "summarizing its results again",
                    folder.path,
                )
            else:
                log.info("%s: the drive is complete in the checkpoint; finishing the results", folder.path)
        else:  # what is left to drive, on the wheel the run drove
            _check_wheel_mesh(folder, plan)
        system = CoupledSystem.build(plan, _run_bed(folder, checkpoint, info) if needs_bed(plan) else None)
        try:
            system.load_state_dict(checkpoint)
            writer = ResultsWriter.resume(
                folder.results, steps, int(checkpoint["loop/snapshots"]), flush_every=plan.output.flush_every
            )
            _put_back_scene(folder, scene.to_toml())  # every check passed: now the folder may change
            loop = {k[len("loop/") :]: v for k, v in checkpoint.items() if k.startswith("loop/")}
            run_id = str(checkpoint["run_id"]) if "run_id" in checkpoint else None
            if system.bed is not None and "bed" in info:  # where the bed lies now (a folder moved whole)
                info["bed"] = system.bed.info
            _mark_running(folder, info, run_id, float(checkpoint["coupler/time"]))
            return Runner(system, writer, folder, loop=loop, progress=progress, hooks=hooks, run_id=run_id).run()
        finally:
            system.close()


def _mark_running(folder: RunFolder, info: dict, run_id: str | None, time: float) -> None:
    """run.json says the run runs again, as a run's start does (a resume killed later is then not taken for
    the interruption before it); the partial summary goes, the run writes its own at its end."""
    info = {k: v for k, v in info.items() if k != "summary"}
    if run_id is not None:
        info.setdefault("run_id", run_id)
    info.update(status="running", message=f"resumed from its checkpoint at t = {time:.6g} s")
    write_json(folder.file(RUN_FILE), info)


def _check_wheel_mesh(folder: RunFolder, plan: RunPlan) -> None:
    """Refuse to resume onto another wheel than the run drove (ArgumentError naming the mesh file): a mesh
    file changed since the run started would drive the rest of it on a wheel its results do not hold (their
    wheels/mesh: the run's own)."""
    if all(hasattr(w.shape, "to_mesh") for w in plan.wheels):  # grouser wheels: the scene's keys say it all
        return
    stored, planned = used_mesh(stored_wheel_mesh(folder.results)), used_mesh(wheel_display_mesh(plan))
    if all(np.array_equal(a, b) for a, b in zip(stored, planned)):
        return
    keys = sorted(_mesh_keys(plan))
    raise ArgumentError(
        f"{folder.path!r}: the wheel mesh read now ({', '.join(keys)}) is not the one the run drove (its "
        f"{os.path.basename(folder.results)} holds that one): the file changed since the run started, or is read "
        "otherwise; put the run's mesh back to resume it, or run the scene again into another folder; nothing "
        "was changed"
    )


def _mesh_keys(plan: RunPlan) -> set[str]:
    """The scene keys that name a plan's mesh wheels' files (wheel.file, rover.wheel_shape.NAME.file)."""
    if plan.rover is None:
        return {"wheel.file"}
    assert plan.scene.rover is not None
    shapes = plan.scene.rover.wheel_shape or {}
    return {
        f"rover.wheel_shape.{name}.file" if name in shapes else "wheel.file"
        for name, wheel in zip(plan.rover.wheel_names, plan.wheels)
        if not hasattr(wheel.shape, "to_mesh")
    }


def _put_back_scene(folder: RunFolder, scene_toml: str) -> None:
    """The checkpoint's copy of the scene is the one resumed: a scene.toml edited (or damaged) since the run
    started is kept as scene.edited.toml (scene.edited.2.toml, ... when that is taken: an earlier edit is
    kept too) and scene.toml written again, so the folder's scene is its results'."""
    path = folder.file(SCENE_FILE)
    try:
        with open(path, encoding="utf-8") as f:
            if f.read() == scene_toml:
                return
        note = "was edited after the run started"
    except (OSError, UnicodeDecodeError) as error:
        note = f"cannot be read ({error})"
    stem, suffix = os.path.splitext(EDITED_SCENE_FILE)
    names = (EDITED_SCENE_FILE, *(f"{stem}.{k}{suffix}" for k in range(2, 1000)))
    kept = next((folder.file(n) for n in names if not os.path.lexists(folder.file(n))), folder.file(names[-1]))
    try:
        try:
            os.link(path, kept)  # the edit kept whole, even if the rewrite below is cut short
        except OSError:  # a file system without hard links (FAT, some network mounts)
            shutil.copy2(path, kept)
        atomic_write_text(path, scene_toml)
    except OSError as error:
        log.warning(
            "scene.toml %s; the checkpoint's copy of the scene is used, but scene.toml was NOT written back (%s)",
            note,
            error,
        )
        return
    log.warning(
        "scene.toml %s; the checkpoint's copy of the scene is used and written back to scene.toml, "
        "the edited file kept as %s",
        note,
        os.path.basename(kept),
    )


def _run_bed(folder: RunFolder, checkpoint: dict, info: dict) -> Bed:
    """The bed a run started on (its checkpoint names it), refused when it is missing or was replaced. A
    folder moved whole since (to another disk or machine) resumes on the bed it carried along (the
    checkpoint's path of it from the folder, bed.h5 for a checkpoint written before that was kept),
    provided run.json's key of the run's bed says it is the same one."""
    bed_path = str(checkpoint["bed_path"])
    if not os.path.exists(bed_path):
        carried = str(checkpoint.get("bed_path_from_folder", "")) or BED_FILE
        moved = os.path.normpath(os.path.join(folder.path, carried))
        if info.get("bed", {}).get("key") and os.path.isfile(moved):
            log.info("%s: the bed %s is gone; resuming on %s, moved with the folder", folder.path, bed_path, moved)
            bed_path = moved
        else:
            raise ArgumentError(
                f"{folder.path!r}: the run's bed {bed_path!r} is gone (its checkpoint continues the grains settled "
                f"there): put the bed back at that path to resume the run, or run its scene again (cosim run "
                f"{folder.file(SCENE_FILE)} --out NEW_FOLDER); nothing was changed"
            )
    try:
        bed = bed_from_file(bed_path, "checkpoint bed")
    except SceneError as error:
        raise SceneError(error.problems + [f"the run's bed {bed_path!r} is needed to resume"]) from None
    _check_run_bed(bed_path, info.get("bed", {}))
    return Bed(bed.path, bed.surface_height, {**info["bed"], "path": bed.path} if "bed" in info else bed.info)


def _checked_inputs(folder: RunFolder) -> tuple[dict, dict]:
    """(checkpoint arrays, run.json) of a folder to resume, after checking that results.h5 is readable, that
    the checkpoint is intact and that both belong to the same run; DamagedFileError naming the file otherwise."""
    from soil.errors import DamagedFileError

    from .output import check_results

    unchanged = "; nothing was changed"
    try:
        checkpoint = load_checkpoint(folder.checkpoint)
    except DamagedFileError as error:
        raise DamagedFileError(f"{error}{unchanged}. {_recoverable(folder.results)}") from None
    at = f"t = {float(checkpoint.get('coupler/time', np.nan)):.6g} s"
    try:
        attrs = check_results(folder.results)
    except DamagedFileError as error:
        raise DamagedFileError(
            f"{error}{unchanged}. The checkpoint ({at}) is intact, but the records it continues are lost: "
            "start the run again with `cosim run SCENE --out FOLDER --overwrite`"
        ) from None
    info = read_json(folder.file(RUN_FILE))
    if not info:  # emptied or garbled: the resumed run writes it again from the checkpoint and the results
        log.warning("%s cannot be read as a run's record: it is written again as the run goes on", RUN_FILE)
    run_id = str(checkpoint["run_id"]) if "run_id" in checkpoint else None
    expected = info.get("run_id") or attrs.get("run_id")
    if run_id is not None and expected is not None:
        same = run_id == expected
    else:  # a run written before run ids: its scene must be the checkpoint's
        same = str(checkpoint["scene_toml"]) == attrs.get("scene_toml", str(checkpoint["scene_toml"]))
    owner = attrs.get("run_id")
    if not same and not info.get("run_id") and owner is not None:  # run.json cannot say which is this run's
        raise DamagedFileError(
            f"{folder.checkpoint} (run id {run_id}) and {folder.results} (run id {owner}) belong to different "
            f"runs, and {RUN_FILE} cannot be read to tell which is this folder's{unchanged}. Put back the "
            "other file of the same run, or start the run again with `cosim run SCENE --out FOLDER --overwrite`"
        )
    if not same:
        name = scene_from_text(str(checkpoint["scene_toml"])).scene.name
        raise DamagedFileError(
            f"{folder.checkpoint}: the checkpoint belongs to another run (scene {name!r}, run id {run_id}; "
            f"this folder's run is {expected}){unchanged}. Put back this run's checkpoint, or start it again "
            "with `cosim run SCENE --out FOLDER --overwrite`"
        )
    if run_id is not None and owner is not None and str(owner) != run_id:  # another run's results copied in
        raise DamagedFileError(
            f"{folder.results}: the results file belongs to another run (run id {owner}; the checkpoint's and this "
            f"folder's run is {run_id}){unchanged}. Put back this run's results.h5, or start it again with "
            "`cosim run SCENE --out FOLDER --overwrite`"
        )
    return checkpoint, info


def _recoverable(results: str) -> str:
    """What can still be read of a results.h5, in words (for a message about a damaged folder)."""
    from soil.errors import DamagedFileError

    from .output import check_results

    try:
        check_results(results)
        series = read_series(results)
    except (DamagedFileError, OSError, KeyError, ValueError, RuntimeError):
        return f"{results} is damaged too: nothing can be recovered; start the run again with --overwrite"
    count = len(series["time"])
    status = series["attrs"].get("status")
    if status in FINISHED:
        return f"{results} is intact and finished (status {status}, {count} macro steps): the run's result is kept"
    last = f" (up to t = {series['time'][-1]:.6g} s)" if count else ""
    return (
        f"{results} is readable: it holds {count} macro steps{last}, the results up to its last flush "
        "(cosim plot FOLDER shows them); to finish the run start it again with --overwrite"
    )


def diverged_here(path: str) -> bool:
    """The run of results.h5 at `path` diverged itself: a resume would repeat it (a run that stopped as
    another world of its batch diverged did not: its summary says so, diverged_elsewhere)."""
    from .output import open_results

    with open_results(path) as f:  # a file a killed writer left open for writing opens too
        status, summary = f.attrs.get("status", ""), f.attrs.get("summary", "{}")
    status = status.decode() if isinstance(status, bytes) else str(status)
    try:
        elsewhere = bool(json.loads(summary).get("diverged_elsewhere", False))
    except (ValueError, AttributeError):  # a summary that is no JSON table: check_results refused it before
        elsewhere = False
    return status == "diverged" and not elsewhere


def _results_status(path: str) -> str:
    from .output import open_results

    with open_results(path) as f:
        status = f.attrs.get("status", "")
    return status.decode() if isinstance(status, bytes) else str(status)


def _check_run_bed(path: str, info: dict) -> None:
    """Refuse a run's bed that is not the one it started on (replaced since: another scene's bed)."""
    from soil.bed import read_bed_header
    from soil.errors import DamagedFileError

    key = info.get("key")
    if not key:
        return
    found = read_bed_header(path)
    if (found["key"] and found["key"] != key) or found["particle_count"] != info.get(
        "particle_count", found["particle_count"]
    ):
        raise DamagedFileError(
            f"{path}: the run's bed was replaced ({found['particle_count']} grains, key {found['key'] or 'none'}; "
            f"the run started on {info.get('particle_count')} grains, key {key}); nothing was changed"
        )


def _check_macro_step(checkpoint: dict, plan: RunPlan) -> None:
    """The checkpoint's coupler time must be its step count of the plan's macro steps: a scene that
    resolves to another step now (SCM's own coupling step, new since the run began) cannot continue
    the run it began."""
    count, time = int(checkpoint["coupler/step_count"]), float(checkpoint["coupler/time"])
    if count and abs(time - count * plan.macro_step) > 1e-6 * count * plan.macro_step:
        raise SceneError(
            [
                f"run.macro_step: the run stepped {time / count:.6g} s per macro step, its scene now resolves to "
                f"{plan.macro_step:.6g} s ({plan.dt_setting}); start it again (cosim run ... --overwrite)"
            ]
        )


def _finished(checkpoint: dict, plan: RunPlan) -> bool:
    start = int(checkpoint["loop/drive_start_step"])
    return bool(checkpoint["loop/landing_failed"]) or (
        start >= 0 and int(checkpoint["coupler/step_count"]) - start >= plan.drive_steps
    )


def final_state(out_dir: str) -> dict:
    """The latest checkpoint's system state arrays (for comparisons)."""
    data = load_checkpoint(os.path.join(out_dir, "checkpoint.npz"))
    return {k: v for k, v in data.items() if k.split("/")[0] in ("soil", "rover", "coupler")}


__all__ = [
    "final_state",
    "load_checkpoint",
    "open_run",
    "resume",
    "run_plan",
    "run_scene",
]
