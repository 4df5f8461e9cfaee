"""The `cosim` command line (also `python -m cosim`).

    cosim run SCENE.toml [--out DIR] [--device D] [--precision P] [--set key=value ...] [--overwrite]
                         [--replicas K [--vary-bed] [--workers N | --scheduler ADDRESS | --serial | --batched]]
    cosim resume OUT
    cosim advise SCENE.toml [--set key=value ...]
    cosim plot OUT
    cosim view RUN [--out movie.mp4|movie.gif|picture.png|frames/] [--color speed|displacement]
    cosim export vtkhdf RUN [--out FILE]
    cosim study precision SCENE.toml --replicas N [--precisions single,mixed,double] [--batched] [--out DIR] ...
    cosim study timestep SCENE.toml [--out DIR] [--duration S] [--max-tries N]
    cosim study slip SCENE.toml --slips 0.1,0.2,0.4 [--replicas K] [--vary-bed] [--batched] [--out DIR]
                     [--from-runs STUDY ...] ...
    cosim sweep SCENE.toml --param wheel.radius=0.03,0.04 --param wheel.grouser_count=0,12 [--out DIR] ...
    cosim scale SCENE.toml --gravity G --out TWIN.toml
    cosim lab repose|shear|plate SCENE.toml [--out DIR] [--replicas K] [--set key=value ...] [--workers N | --serial]
    cosim calibrate SCENE.toml --target repose=30 --vary soil.rolling_friction=0:0.3 [--tolerance repose=1] ...
    cosim calibrate-scm SCENE.toml --out terrain.toml [--replicas K] [--set KEY=VALUE] [--lab-sizes]
                        [--from-wheel [--slips 0.05,0.1,0.2,0.4,0.6] [--wheel-runs STUDY] [--lab FILE]]

Output: results and summaries on stdout; progress bars, notes and warnings on stderr;
Warp's own messages only with --verbose.

Exit status:
    0    done (a run: a steady-state result)
    1    an unexpected error (a bug: please report it with the traceback --verbose prints), or a failure
         that is not the input's (a model refused a step, a tool is missing: the message names it; a run
         of replicas, a sweep or a study one of whose runs failed or diverged: its table says which)
    2    bad input, and only that: a scene, an argument, a bed file, a mesh, an FMU or a run to view,
         export or resume (the message names it)
    3    the output folder holds a run, or an --out file exists (pass --overwrite), or the folder is in use
         by another process
    4    the simulation diverged (the message says where and what to change)
    5    an operating-system error: a path that cannot be written or read, a full disk
    6    the run finished without a steady-state result (the summary says why: airborne, stuck, ...);
         replicas, a sweep or a study, when one of its runs did (or had not finished: --from-runs)
    130  interrupted by Ctrl-C (`cosim resume OUT` continues)
    143  stopped by SIGTERM (a batch scheduler, `docker stop`): checkpointed, `cosim resume OUT` continues
    129  stopped by SIGHUP (the terminal or ssh session closed; not under `nohup`): checkpointed, as above
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import time

EXIT_OK, EXIT_ERROR, EXIT_INPUT, EXIT_FOLDER, EXIT_DIVERGED, EXIT_OS, EXIT_UNSTEADY = 0, 1, 2, 3, 4, 5, 6

log = logging.getLogger("cosim")


class _StderrHandler(logging.StreamHandler):
    """A log handler that writes to sys.stderr as it is when a record comes, not as it was when the
    handler was made: a caller that replaces sys.stderr between two commands in one process (a test's
    capture) gets the lines, not 'I/O operation on closed file'."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler sets it; the property reads sys.stderr instead
        pass


def _setup_output(verbose: bool) -> None:
    """Log lines on stderr; Warp's banner and module-load lines only when verbose."""
    import warnings

    import warp as wp

    from soil.errors import RegolithWarning

    wp.config.log_level = wp.LOG_INFO if verbose else wp.LOG_ERROR
    if not verbose:
        from soil import quiet_warp

        quiet_warp()
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s: %(message)s" if verbose else "%(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    logging.captureWarnings(True)
    captured = getattr(warnings.showwarning, "captured", warnings.showwarning)  # a second call wraps once
    label = "" if verbose else "warning: "  # verbose lines carry their level already

    def show(message, category, filename, lineno, file=None, line=None):
        # ours say what to change: the source line that raised one is of no use to its reader
        if file is None and issubclass(category, RegolithWarning):
            logging.getLogger("py.warnings").warning("%s%s", label, message)
        else:
            captured(message, category, filename, lineno, file, line)

    show.captured = captured  # type: ignore[attr-defined]
    warnings.showwarning = show
    warnings.simplefilter("default")
    # Warp leaves its compiler's precompiled-header folders to the interpreter's exit, which says so
    # after every first compile of a module: nothing of ours, and the folders are removed all the same
    warnings.filterwarnings("ignore", r"Implicitly cleaning up <TemporaryDirectory '.*wp_pch_", ResourceWarning)


def _overrides(args) -> list[str]:
    overrides = list(getattr(args, "set", None) or [])
    if getattr(args, "device", None):
        overrides.append(f'scene.device="{args.device}"')
    if getattr(args, "precision", None):
        overrides.append(f'scene.precision="{args.precision}"')
    return overrides


def _plan(args):
    from .plan import load_plan

    return load_plan(args.scene, _overrides(args))


def cmd_run(args) -> int:
    from soil.errors import ArgumentError

    from .launch import run_plan
    from .study import MAX_REPLICAS

    if not 1 <= args.replicas <= MAX_REPLICAS:  # before the scene is even read
        raise ArgumentError(
            f"--replicas must be 1 to {MAX_REPLICAS} (1: one run; >= 2: error bars), got {args.replicas}"
        )
    plan = _plan(args)
    out = args.out or os.path.join("runs", plan.name)
    if args.replicas > 1:
        from .study import replica_run

        vary = "bed" if args.vary_bed else "order"
        report = replica_run(
            plan, out, args.replicas, overwrite=args.overwrite, batched=args.batched, vary=vary, **_executor(args)
        )
        print(report["text"])
        return _study_exit(report["results"])
    if args.vary_bed:
        from soil.errors import ArgumentError

        raise ArgumentError("--vary-bed: varies the beds of replicas; give --replicas K (K >= 2)")
    _refuse_unused(args, ("--batched", *CLUSTER_OPTIONS), "one run runs in this process (give --replicas K for K)")
    with open(args.scene) as f:
        source = f.read()
    result = run_plan(plan, out, overwrite=args.overwrite, progress=not args.no_progress, source=source)
    _print_summary(result, scm_only=plan.terrain.model == "scm")
    return EXIT_OK if result.status == "complete" else EXIT_UNSTEADY


def cmd_resume(args) -> int:
    from soil.errors import RegolithError

    from .folders import SCENE_FILE
    from .launch import resume
    from .scene import load_scene
    from .study import (
        PRECISION_FILE,
        REPLICAS_FILE,
        SLIP_FILE,
        SWEEP_FILE,
        resume_precision_study,
        resume_replicas,
        resume_slip_study,
        resume_sweep,
    )

    if os.path.isfile(os.path.join(args.out, REPLICAS_FILE)):  # a set of replicas (cosim run --replicas K)
        report = resume_replicas(args.out)
        print(report["text"])
        return _study_exit(report["results"])
    if os.path.isfile(os.path.join(args.out, SWEEP_FILE)):  # a sweep (cosim sweep)
        return _print_sweep(resume_sweep(args.out), args.out)
    if os.path.isfile(os.path.join(args.out, SLIP_FILE)):  # a slip study (cosim study slip)
        report = resume_slip_study(args.out)
        print(report["text"])
        return _study_exit(report["runs"])
    if os.path.isfile(os.path.join(args.out, PRECISION_FILE)):  # a precision study (cosim study precision)
        report = resume_precision_study(args.out)
        failed = sum(1 for r in report["replicas"] if not r.get("ok"))
        print(
            f"study written to {args.out} ({failed} failed replica(s); resumed: its runs' wall times mix sessions "
            "and batches, compare precisions' wall times on a study run whole)"
        )
        return _study_exit(report["replicas"])
    _refuse_replicas_without_recipe(args.out)
    result = resume(args.out, progress=not args.no_progress)
    try:  # the run's scene as it ran (resume read it): SCM alone takes its error bars over beds
        terrain = load_scene(os.path.join(args.out, SCENE_FILE)).terrain
    except (RegolithError, OSError):  # changed since: the summary still printed, without a hint
        terrain = None
    _print_summary(result, scm_only=terrain is not None and terrain.model == "scm" and not terrain.dem_wheels)
    return EXIT_OK if result.status == "complete" else EXIT_UNSTEADY


def _refuse_replicas_without_recipe(out: str) -> None:
    """A set of replicas, a sweep or a slip or precision study made before it kept its recipe
    (cosim.study.RECIPES: its file missing) has no scene of its own to resume: ArgumentError naming its
    runs' folders, each of which resumes alone."""
    import glob

    from soil.errors import ArgumentError

    from .folders import SCENE_FILE

    if os.path.isfile(os.path.join(out, SCENE_FILE)):  # a run's own folder
        return
    from .study import PRECISION_ORDER

    precision = [os.path.join(name, "replica_*", SCENE_FILE) for name in PRECISION_ORDER]
    for what, patterns in (
        ("replicas", [os.path.join("replica_*", SCENE_FILE)]),
        ("a sweep's runs", [os.path.join("[0-9][0-9][0-9]_*", SCENE_FILE)]),
        ("a slip study's runs", [os.path.join("slip_*", "replica_*", SCENE_FILE)]),
        ("a precision study's runs", precision),
    ):
        runs = sorted(path for pattern in patterns for path in glob.glob(os.path.join(out, pattern)))
        if runs:
            folders = [os.path.relpath(os.path.dirname(path), out) for path in runs]
            shown = ", ".join(folders[:4]) + (", ..." if len(folders) > 4 else "")
            raise ArgumentError(
                f"{out!r} holds {what} ({shown}) without the recipe that resumes them together (it predates it, "
                f"or was removed): resume each (cosim resume {os.path.join(out, folders[0])}), or run them again"
            )


SUMMARY_KEYS = (
    ("steady_state", "", 1),
    ("validity", "", 1),
    ("landing_time", "s", 1),
    ("landing_sinkage", "mm", 1e3),
    ("deepest_sinkage", "mm", 1e3),
    ("window", "s", 1),
    ("grouser_passages", "", 1),
    ("slip", "", 1),
    ("travel", "mm", 1e3),
    ("forward_speed", "mm/s", 1e3),
    ("sinkage", "mm", 1e3),
    ("sinkage_tips", "mm", 1e3),
    ("drawbar_pull", "N", 1),
    ("dp_over_w", "", 1),
    ("driving_torque", "N m", 1),
    ("normal_force", "N", 1),
    ("net_traction", "N", 1),
    ("net_traction_over_weight", "", 1),
    ("power", "W", 1),
    ("displacement", "mm", 1e3),
    ("energy_per_metre", "J/m", 1),
    ("time_immobile", "s", 1),
    ("stuck", "", 1),
    ("stalled", "", 1),
    ("wheel_slip", "", 1),
    ("wheel_sinkage", "mm", 1e3),
    ("wheel_normal_force", "N", 1),
    ("wheel_power", "W", 1),
    ("patch_moves", "", 1),
    ("particle_count_max", "", 1),
    ("soil_mass_added", "kg", 1),
    ("soil_mass_removed", "kg", 1),
    ("contact_fraction", "", 1),
    ("froude_number", "", 1),
    ("simulated_time", "s", 1),
    ("wall_time", "s", 1),
    ("particle_count", "", 1),
    ("particle_steps_per_second", "1/s", 1),
)


def _print_summary(result, scm_only: bool = False) -> None:
    from .metrics import MIN_CORRELATION_TIMES, short_window, within_run_interval

    s = result.summary
    print(f"{result.status}: {result.out_dir}")
    short: list[str] = []  # "N of key": the window in correlation times of each key whose s.e. is too small
    for key, unit, scale in SUMMARY_KEYS:
        if key not in s:
            continue
        value = math.nan if s[key] is None else s[key]  # run.json's null (a finished run resumed): not measured
        if isinstance(value, float):
            sem = s.get(f"{key}_sem")
            # a value the drive holds (the carriage's speed) scatters by its rounding only: no error bar
            resolved = bool(sem) and sem > 1e-9 * abs(value)  # False for a nan too
            bar = f" +- {within_run_interval(sem) * scale:.2g} (95 %, within run)" if resolved else ""
            text = f"{value * scale:.4g}{bar}"
            if resolved and short_window(s, key) is not None:
                short.append(f"{short_window(s, key):.0f}{' correlation times' if not short else ''} of {key}")
        elif key == "window" and not all(isinstance(v, (int, float)) and math.isfinite(v) for v in value):
            print(f"  {key:26s} none (no steady state: {s.get('steady_state', 'not measured')})")  # was 'nan .. nan s'
            continue
        elif isinstance(value, list):
            text = (" .. " if key == "window" else ", ").join(
                f"{(math.nan if v is None else v) * scale:.4g}" for v in value
            )
        else:
            text = str(value)
        print(f"  {key:26s} {text} {unit}".rstrip())
    if short:
        print(
            f"  ! the window spans only {', '.join(short)} (< {MIN_CORRELATION_TIMES}): "
            "their within-run intervals are too narrow; replicas give the error bar"
        )
    if s.get("coupling_energy_over_tolerance"):  # the run's log said it once; the summary keeps it
        created, exchanged = s.get("coupling_energy_created"), s.get("coupling_energy_exchanged")
        print(
            f"  ! the coupling created {created:.3g} J of energy (over its tolerance; {exchanged:.3g} J exchanged "
            "between soil and rover): the macro step is too long for these contacts; shorten run.macro_step "
            "and run again"
        )
    for finding in s.get("findings", []):
        if not finding["ok"]:
            print(f"  ! {finding['message']}")
    if s.get("steady_state") == "steady" and scm_only:
        print(
            "  error bars: cosim run SCENE --replicas 3 --vary-bed (each replica on the soil its calibration fitted "
            "on one bed: calibrate-scm --replicas 3)"
        )
    elif s.get("steady_state") == "steady":
        print(  # the sinkage scatters 4.7x more between beds than between orders (README, "Replicas")
            "  error bars: cosim run SCENE --replicas 5 --vary-bed (a bed each: the sinkage scatters most between "
            "beds; without --vary-bed, summation orders on one bed)"
        )


def cmd_plot(args) -> int:
    from .plots import plot_output

    for path in plot_output(args.out, args.plot_dir):
        print(path)
    return EXIT_OK


def cmd_view(args) -> int:
    from .view import render, summary_line

    picture = render(
        args.run, args.out, colour=args.color, fps=args.fps, dpi=args.dpi, frame=args.frame, overwrite=args.overwrite
    )
    print(summary_line(picture))
    return EXIT_OK


def cmd_export(args) -> int:
    """cosim export vtkhdf RUN [--out FILE]: results.vtkhdf from what results.h5 holds."""
    from soil.errors import ArgumentError

    from .folders import CHECKPOINT_FILE, RESULTS_FILE, VTKHDF_FILE
    from .vtkhdf import VTKHDF_SUFFIXES, write_vtkhdf

    results = os.path.join(args.run, RESULTS_FILE) if os.path.isdir(args.run) else args.run
    if not os.path.isfile(results):
        raise ArgumentError(f"{args.run!r} is not a run folder: no {RESULTS_FILE} in it")
    own = os.path.join(os.path.dirname(os.path.abspath(results)), VTKHDF_FILE)
    replace = args.out is None or os.path.abspath(args.out) == own  # RUN/results.vtkhdf is the run's own: made again
    if not replace:  # never through a link to the run's results.h5, its checkpoint or a file not an export's
        inputs = (results, os.path.join(os.path.dirname(os.path.abspath(results)), CHECKPOINT_FILE))
        _free_output_file(args.out, VTKHDF_SUFFIXES, args.overwrite, inputs)
    # (the run's own export: write_vtkhdf checks the same before it writes)
    path = write_vtkhdf(results, args.out, replace=replace or args.overwrite)  # a file that appeared meanwhile: kept
    print(f"{path}: {os.path.getsize(path) / 1024:.0f} kB (open it in ParaView or with VTK's vtkHDFReader)")
    return EXIT_OK


def _free_output_file(path: str, suffixes: tuple[str, ...], overwrite: bool, inputs=()) -> None:
    """Refuse `--out` PATH before anything is written: a name without one of `suffixes` (ArgumentError:
    a run's results.h5 or a checkpoint is never taken for an export's file), a PATH that is or leads to
    one of `inputs` (the files the command reads), a symbolic link whose target does not end in one of
    `suffixes` (a link is written through, its target replaced, only when that is an export's file:
    soil.files.output_target) or, without --overwrite, a file that exists (OutputExistsError)."""
    from soil.errors import ArgumentError
    from soil.files import output_target

    from .folders import OutputExistsError

    if not path.lower().endswith(suffixes):
        raise ArgumentError(f"--out {path!r}: the file must end in {' or '.join(suffixes)}")
    if os.path.isdir(path):
        raise ArgumentError(f"--out {path!r} is a folder; name the file to write")
    output_target(path, suffixes, inputs)
    if os.path.lexists(path) and not overwrite:
        raise OutputExistsError(f"--out {path!r} exists; pass --overwrite to replace it")


def cmd_advise(args) -> int:
    for line in advise_lines(_plan(args)):
        print(line)
    return EXIT_OK


def advise_lines(plan) -> list[str]:
    """Stiffness, time-step and validity advice for a plan (soil.advisor, cosim.advice); on SCM the
    grid, the static sinkage and the coupling step instead of the grains' scales."""
    from soil.errors import InputError

    from . import advice
    from .scm_soil import check_scm_grid
    from .system import TERRAIN_MODELS, needs_bed

    lines = _scm_advice(plan) if plan.terrain.model == "scm" else _dem_advice(plan)
    if plan.terrain.model == "mixed":
        lines += _scm_advice(plan)[1:]
    lines.append(
        f"validity checks ({plan.terrain.model} terrain):" if plan.terrain.model != "dem" else "validity checks:"
    )
    findings = TERRAIN_MODELS[plan.terrain.model].validity(plan)
    try:
        check_scm_grid(plan)  # what a run refuses before it starts
    except InputError as refused:
        findings.append(
            advice.Finding("scm_grid_size", math.nan, math.nan, False, str(refused), "terrain.node_spacing")
        )
    if needs_bed(plan):  # the grains' memory, which a run also refuses before it starts
        from .beds import memory_estimate

        memory = memory_estimate(plan)
        if not memory.fits:
            findings.append(
                advice.Finding(
                    "memory",
                    math.nan,
                    math.nan,
                    False,
                    f"{memory.text()}: does not fit; fewer or larger grains (a smaller bed, a [patch])",
                    "bed.length, bed.width, bed.depth, bed.radius_mean",
                )
            )
    for finding in findings:
        lines.append(f"  [{'ok' if finding.ok else 'OUT OF RANGE'}] {finding.check}: {finding.message}")
    pending = advice.judged_after_the_run(plan, findings)
    for check, what in pending:
        lines.append(f"  [after the run] {check}: {what}")
    waiting = (
        f" (before the run; {', '.join(c for c, _ in pending)} waiting for the run's measurements)" if pending else ""
    )
    lines.append(f"verdict: {advice.verdict(findings)}{waiting}")
    if plan.terrain.model != "scm":
        lines.append("largest stable step by trial: cosim study timestep SCENE")
    return lines


def _scm_advice(plan) -> list[str]:
    """An SCM scene's grid, its wheels' Bekker sinkage and elastic bounce, and its coupling step."""
    from soil.scm import grid_memory, grid_shape

    from .scm_soil import bekker_wheel_sinkage, elastic_bounce, scm_settings, scm_wheel_indices

    indices = scm_wheel_indices(plan)
    settings = scm_settings(plan, indices, 0.0)
    p = settings.parameters
    wheels = [plan.wheels[i] for i in indices]
    wheel = min(wheels, key=lambda w: w.width)
    sinkage = bekker_wheel_sinkage(p, plan.wheel_load, wheel.outer_radius, wheel.width)
    omega = max(elastic_bounce(p, w, plan.wheel_load, plan.g)[0] for w in wheels) if plan.g > 0 else math.nan
    given = plan.scene.run.macro_step is not None
    source = "run.macro_step" if given else ("the DEM's step" if plan.terrain.model == "mixed" else "SCM's own step")
    shape = grid_shape(settings.window, p.node_spacing)
    nodes = shape[0] * shape[1]
    device_bytes, host_bytes = grid_memory(nodes, plan.precision, plan.device)
    memory = f"{device_bytes / 1e6:,.0f} MB on {plan.device}, " if plan.device.startswith("cuda") else ""
    memory += f"{host_bytes / 1e6:,.0f} MB of host memory"
    return [
        f"scene {plan.name}: |g| = {plan.g:.4g} m/s^2 on SCM (no grains), wheel load {plan.wheel_load:.4g} N",
        f"  Bekker k_c, k_phi, n       {p.k_c:.4g} Pa m^(1-n), {p.k_phi:.4g} Pa m^-n, {p.n:.4g}; "
        f"c = {p.cohesion:.4g} Pa, phi = {p.friction_angle:.4g} deg, K = {p.janosi_k:.4g} m, K_e = "
        f"{p.elastic_stiffness:.4g} Pa/m",
        f"  grid                       node spacing {p.node_spacing:.4g} m, window {settings.window[0]:.3g} x "
        f"{settings.window[1]:.3g} m ({nodes:,} nodes, following the wheels; about {memory})",
        f"  static sinkage (Bekker)    {sinkage:.4g} m; elastic bounce omega_e = {omega:.4g} rad/s",
        f"  the scene couples at H = {plan.macro_step:.4g} s (omega_e H = {omega * plan.macro_step:.3g} rad; "
        f"set by {source}), "
        f"SCM steps of at most {settings.time_step:.4g} s",
    ]


NO_GRAVITY_IMPACT = "; no gravity: an impact at the rims' speed"
NO_LOAD_BOUND = "(no eq. 10 bound without gravity: no load; "


def _dem_advice(plan) -> list[str]:
    """A DEM scene's stiffness, time-step and memory advice (soil.advisor)."""
    from soil import advisor

    from . import advice
    from .scene import SceneError
    from .system import needs_bed

    spec = plan.bed.spec
    material = plan.soil_material
    r_min = spec.radius_min
    pressure = advice.ground_pressure(plan)
    e_min = advisor.macroscopic_stiffness(
        spec.depth, pressure, advice.OVERLAP_RATIO, spec.radius_mean, material.density, plan.g
    )
    rayleigh = advisor.rayleigh_time_step(material.youngs_modulus, material.poisson_ratio, material.density, r_min)
    # an impact's speed: a fall through the bed; without gravity, only the rims' (when the drive sets them)
    speeds = plan.wheel_speeds if plan.wheel_speeds is not None else []
    rims = [abs(float(v)) * w.outer_radius for v, w in zip(speeds, plan.wheels or (plan.wheel,))]
    impact = None if plan.g > 0 else max(rims, default=0.0)
    steps = None
    if impact is None or impact > 0:
        steps = advisor.recommended_time_step(
            material, radius=r_min, gravity=plan.g, height=spec.depth, pressure=pressure, impact_speed=impact
        )
    lines = [
        f"scene {plan.name}: |g| = {plan.g:.4g} m/s^2, grains r = {spec.radius_mean:.4g} m (smallest {r_min:.4g} m), "
        f"E = {material.youngs_modulus:.4g} Pa, wheel load {plan.wheel_load:.4g} N",
        f"  wheel ground pressure      {pressure:.4g} Pa",
        f"  eq. 10 stiffness E_mP >=   {e_min:.4g} Pa  (z_h = {spec.depth:.3g} m, u = {advice.OVERLAP_RATIO:g})",
        f"  Rayleigh step              {rayleigh:.4g} s  (0.1..0.3 x: {0.1 * rayleigh:.3g} .. {0.3 * rayleigh:.3g} s)",
    ]
    uses = f"  the scene uses dt = {plan.dt:.4g} s, macro step H = {plan.macro_step:.4g} s ({plan.substeps} substeps)"
    if steps is None:  # no gravity and no known speed: nothing sets an impact to resolve
        lines.append(
            "  recommended dt range       not estimated: no gravity and no wheel speed known (still wheels, or a "
            "drive that sets them as it goes): no impact speed to resolve; the run's contact check judges the "
            "speeds it measures"
        )
        lines.append(uses)
    else:
        lines.append(
            f"  recommended dt range       {steps.dt_min:.4g} .. {steps.dt_max:.4g} s  (critical step "
            f"{steps.critical_step:.4g} s{'' if plan.g > 0 else NO_GRAVITY_IMPACT})"
        )
        lines.append(
            f"{uses}; "
            + (
                "dt is within the advised stability limit"
                if plan.dt <= steps.dt_max
                else "dt is ABOVE the advised stability limit"
            )
            + (
                " (the check contact_steps, below or after the run, judges how finely it resolves an impact, the rims' "
                "speed included)"
                if plan.step_control != "pid"
                else " (the PID's substeps, not dt, are what the soil takes: the next line)"
            )
        )
    if plan.step_control == "pid" and steps is not None:  # the PID's substeps, not dt, are what the soil takes
        longest = plan.dt_max if plan.dt_max is not None else steps.dt_max
        shortest = plan.dt_min if plan.dt_min is not None else longest * 1e-4
        if shortest > longest:  # only run.dt_min given (both are checked when read): the run would refuse it
            raise SceneError(
                [
                    f"run.dt_min: {shortest:.4g} s is longer than the PID's longest substep, run.dt_max unset: the "
                    f"advised limit {longest:.4g} s (the run takes it from the settled bed, within a few percent); "
                    "lower run.dt_min or give run.dt_max"
                ]
            )
        ratio = longest / steps.critical_step
        lines.append(
            f"  the PID substeps between   {shortest:.4g} .. {longest:.4g} s at run.tolerance {plan.tolerance:g} "
            f"(run.dt_max{' unset: the advised limit,' if plan.dt_max is None else ':'} "
            f"{ratio:.3g} x the critical step)"
            + (
                ""
                if ratio <= 1
                else "; above the critical step only the error estimate keeps a substep stable, and a fast event "
                "(an impact, a bed settling at this gravity) can diverge first: lower run.dt_max if it does"
            )
        )
    if needs_bed(plan):  # what a stiffer soil costs: a step ~ 1/sqrt(E), so E far above the eq. 10 bound is paid
        lines.append(
            f"  the drive's {plan.scene.run.duration:.4g} s take {plan.scene.run.duration / plan.dt:.3g} DEM steps "
            + (f"(E = {material.youngs_modulus / e_min:.3g} x the eq. 10 bound; " if e_min > 0 else NO_LOAD_BOUND)
            + "the step scales as 1/sqrt(E))"
        )
        # the phases before it, at their longest (a soil of tiny grains settled an hour without a word)
        landing = plan.scene.landing.max_time / plan.dt if plan.scene.landing.enabled else 0.0
        settling = plan.bed.settle_max_time / plan.bed.settle_dt
        lines.append(
            f"  before it, at most         {settling:.3g} DEM steps settle the bed (bed.settle_max_time at "
            f"{plan.bed.settle_dt:.3g} s; a saved bed: none) and {landing:.3g} land the wheel (landing.max_time)"
        )
    from .beds import memory_estimate

    memory = memory_estimate(plan)
    lines.append(f"  memory estimate            {memory.text()}" + ("" if memory.fits else ": DOES NOT FIT"))
    return lines


def _executor(args) -> dict:
    from soil.errors import ArgumentError

    from .study import check_workers, reach_scheduler

    check_workers(args.workers)  # before any folder is made
    if args.serial and args.scheduler is not None:
        raise ArgumentError("--serial and --scheduler: the tasks run in this process or on the scheduler; choose one")
    if args.workers is not None and (args.serial or args.scheduler is not None):
        raise ArgumentError(
            f"--workers: sizes the LocalCluster started here; {'--serial' if args.serial else '--scheduler'} uses none"
        )
    # dask itself is checked where the tasks' executor is known (batched: none); the address is tried here,
    # before any folder is made (dask waits 30 s and fails after it)
    reach_scheduler(args.scheduler)
    return dict(executor="serial" if args.serial else "dask", scheduler=args.scheduler, workers=args.workers)


CLUSTER_OPTIONS = ("--workers", "--scheduler", "--serial")
"""The options that say where a command's tasks run (cluster_options)."""


def _refuse_unused(args, options, why: str) -> None:
    """ArgumentError naming the first of `options` given that this command ignores: `why` says what it
    does instead (an option silently ignored looks as if it had acted)."""
    from soil.errors import ArgumentError

    for option in options:
        value = getattr(args, option.lstrip("-").replace("-", "_"))
        if value is not None and value is not False:
            raise ArgumentError(f"{option}: does not apply here: {why}")


STUDY_DEFAULTS = {
    "replicas": 3,
    "precisions": "single,mixed,double",
    "slips": "0.1,0.2,0.3,0.5",
    "duration": 0.05,
    "max_tries": 8,
}
"""`cosim study`'s defaults of the options that only some kinds take (None in the parser: given or not)."""


def cmd_study(args) -> int:
    from . import study

    plan = _plan(args)
    if args.vary_bed and (args.kind != "slip" or args.from_runs):
        from soil.errors import ArgumentError

        why = {
            "precision": "compares the summation orders of each precision on one bed (the paper's experiment)",
            "timestep": "searches the largest stable step of one run",
        }.get(args.kind, "with --from-runs tabulates runs already made")
        raise ArgumentError(f"--vary-bed: for `cosim study slip` runs; `cosim study {args.kind}` {why}")
    if plan.rover is not None and args.kind in ("slip", "timestep"):
        from .scene import SceneError

        raise SceneError(
            [
                f"cosim study {args.kind}: runs the single-wheel [testbed]; for a rover compare drives "
                "with `cosim sweep SCENE --param rover.drive=NAME1,NAME2` ([rover.controllers])"
            ]
        )
    # the options of the other kinds: refused rather than ignored; then their defaults
    study_options = ("--replicas", "--precisions", "--slips", "--from-runs", "--include-sinking", "--batched")
    applies = {
        "precision": ("--replicas", "--precisions", "--batched", *CLUSTER_OPTIONS),
        "slip": ("--replicas", "--slips", "--batched", "--from-runs", *CLUSTER_OPTIONS),
        "timestep": ("--duration", "--max-tries"),
    }[args.kind]
    if args.kind == "slip" and args.from_runs:
        applies = ("--from-runs", "--include-sinking")
    unused = [o for o in (*study_options, "--duration", "--max-tries", *CLUSTER_OPTIONS) if o not in applies]
    _refuse_unused(
        args, unused, f"`cosim study {args.kind}{' --from-runs' if args.from_runs else ''}` takes {', '.join(applies)}"
    )
    for name, default in STUDY_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    if args.kind == "precision":
        out = args.out or os.path.join("runs", f"{plan.name}_precision")
        from .scene import parse_list

        precisions = [str(p) for p in parse_list(args.precisions, "--precisions")]
        report = study.precision_study(
            plan,
            out,
            replicas=args.replicas,
            precisions=precisions,
            overwrite=args.overwrite,
            batched=args.batched,
            **_executor(args),
        )
        failed = sum(1 for r in report["replicas"] if not r.get("ok"))
        print(f"study written to {out} ({failed} failed replica(s))")
        return _study_exit(report["replicas"])
    if args.kind == "slip":
        from .scene import parse_list

        out = args.out or os.path.join("runs", f"{plan.name}_slip")
        if args.from_runs:  # tabulate runs already made: a study stopped before its end, or run in parts
            report = study.slip_study_from_runs(
                args.from_runs, out, overwrite=args.overwrite, include_sinking=args.include_sinking, scene=plan.scene
            )
            print(report["text"])
            return _study_exit(report["runs"])
        slips = parse_list(args.slips, "--slips")
        report = study.slip_study(
            plan,
            out,
            slips,
            replicas=args.replicas,
            overwrite=args.overwrite,
            batched=args.batched,
            vary="bed" if args.vary_bed else "order",
            **_executor(args),
        )
        print(report["text"])
        return _study_exit(report["runs"])
    out = args.out or os.path.join("runs", f"{plan.name}_timestep")
    report = study.timestep_study(plan, out, duration=args.duration, max_tries=args.max_tries, overwrite=args.overwrite)
    return EXIT_OK if report.get("largest_stable") else EXIT_ERROR


def cmd_sweep(args) -> int:
    from soil.errors import ArgumentError

    from . import study

    fixed = {text.split("=", 1)[0].strip() for text in args.set or []}
    swept = {text.split("=", 1)[0].strip() for text in args.param}
    if fixed & swept:  # the sweep's values would replace the --set one without a word
        raise ArgumentError(f"--set {sorted(fixed & swept)[0]}: also swept by --param; give it in one of them")
    plan = _plan(args)
    out = args.out or os.path.join("runs", f"{plan.name}_sweep")
    report = study.sweep(plan, out, args.param, overwrite=args.overwrite, **_executor(args))
    return _print_sweep(report, out)


def _print_sweep(report: dict, out: str) -> int:
    """A sweep's outcome said (how many points failed or are not steady, and which are out of range or not
    judged); returns its exit status."""
    from . import study

    rows = report["rows"]
    failed = sum(1 for r in rows if not r.get("ok"))
    steady = sum(1 for r in rows if r.get("status") == "complete")
    invalid = [r for r in rows if study.out_of_range(r.get("validity"))]
    unjudged = [
        r for r in rows if not study.out_of_range(r.get("validity")) and study.NOT_JUDGED in (r["validity"] or "")
    ]
    print(f"sweep written to {out} ({failed} failed, {len(rows) - failed - steady} not steady of {len(rows)} points)")
    for marked, said, mark in ((invalid, "out of range", "!"), (unjudged, "not judged on every check", "-")):
        if marked:
            print(f"  {len(marked)} of {len(rows)} points {said} (each run.json says why):")
        for row in marked:  # a result printed says whether its scene was valid
            point = ", ".join(f"{key}={row.get(key)}" for key in report["grid"])
            print(f"  {mark} {point}: {row['validity']}")
    return _study_exit(report["runs"])


def _study_exit(results: list[dict]) -> int:
    """The exit status of a study's or an ensemble's runs: 1 when one failed (diverged or raised: it gives
    no result), else 6 when one finished without a steady state or did not finish (a slip study's runs
    tabulated while some still run; its table says which), else 0."""
    from .study import failed_run

    if any(map(failed_run, results)):
        return EXIT_ERROR
    # a run that did not finish (interrupted, running) is no result, whatever its partial summary says
    steady = all(r.get("ok", True) and (r.get("summary") or {}).get("steady_state") == "steady" for r in results)
    return EXIT_OK if steady else EXIT_UNSTEADY


def cmd_scale(args) -> int:
    from .scene import load_scene
    from .similarity import write_gravity_twin

    scene = load_scene(args.scene, _overrides(args))
    calibration = scene.resolve(scene.terrain.calibration) if scene.terrain is not None else None
    _refuse_an_input_as_out(args.out, {"the scene": args.scene, "the calibration (terrain.calibration)": calibration})
    _free_output_file(args.out, (".toml",), args.overwrite)
    path, factor = write_gravity_twin(
        args.scene, args.gravity, args.out, overwrite=args.overwrite, overrides=_overrides(args)
    )
    print(f"{path}: the DEM-similar scene at |g| x {factor:.6g}")
    return EXIT_OK


def cmd_export_fmu(args) -> int:
    """cosim export-fmu SCENE_OR_RUN_DIR --out soil.fmu [--fmi 2|3] [--wheels N] (docs/fmu.md)."""
    import tempfile

    from soil.errors import ArgumentError

    from .scene import is_device_name
    from .soil_fmu import export_soil_fmu, soil_config_from
    from .soil_fmu.config import scm_server_grid, verdict
    from .soil_fmu.server import DEVICE_VARIABLE

    _free_output_file(args.out, (".fmu",), args.overwrite)
    if not 1 <= args.wheels <= 10000:  # before a bed is settled for it
        raise ArgumentError(f"--wheels: must be a whole number from 1 to 10000, got {args.wheels}")
    if args.device and not is_device_name(args.device):
        raise ArgumentError(f"--device {args.device!r}: must be 'default', 'cpu', 'cuda' or 'cuda:N'")
    if args.bed_folder and os.path.exists(args.bed_folder) and not os.path.isdir(args.bed_folder):
        raise ArgumentError(f"--bed-folder {args.bed_folder!r} is a file; name a folder (made if missing)")
    if args.bed_folder:
        os.makedirs(args.bed_folder, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="soil_fmu_bed_") as scratch:
        config = soil_config_from(args.source, bed_folder=args.bed_folder or scratch)
        if args.device:
            config.device = args.device
        path = export_soil_fmu(
            config, args.out, fmi_version=args.fmi, wheel_count=args.wheels, python=args.python, replace=args.overwrite
        )  # without --overwrite, a file that appeared at --out while the FMU was made is kept
    grid = ""
    if config.terrain == "scm":  # what the server will allocate, said now: it may run on a smaller machine
        server = scm_server_grid(config, args.wheels)
        on_cpu = f"{server['cpu_bytes'] / 1e6:,.0f} MB of host memory on the CPU"
        on_gpu = (
            f"{server['gpu_bytes'] / 1e6:,.0f} MB on a GPU and {server['gpu_host_bytes'] / 1e6:,.0f} MB of host memory"
        )
        grid = (
            f"; the server's SCM grid: {server['window'][0]:.4g} x {server['window'][1]:.4g} m, "
            f"{server['nodes']:,} nodes, about {on_cpu if config.device == 'cpu' else on_gpu + ' (' + on_cpu + ')'}"
        )
    print(
        f"wrote {path}: FMI {args.fmi}.0 co-simulation, {args.wheels} wheel(s), "
        f"{config.terrain.upper()} step {config.dem_step:.4g} s, "
        f"surface z = {config.surface_height:.4g} m; the soil server runs on {config.device}"
        f"{' (a GPU on the machine that runs it, if it has one, else the CPU)' if config.device == 'default' else ''}"
        f" unless the FMU's device parameter or ${DEVICE_VARIABLE} says otherwise{grid}; "
        f"validity: {verdict(config.findings, config.unjudged)}"
    )
    return EXIT_OK


# -- the soil lab (cosim.lab, docs/lab.md) -------------------------------------------------------


def _lab_replicas(args) -> list[str]:
    """--replicas as the lab's override (lab.replicas), refused by its own name when below 1."""
    from soil.errors import ArgumentError

    if args.replicas is None:
        return []
    if args.replicas < 1:
        raise ArgumentError(f"--replicas: specimens (and beds) per test, at least 1, got {args.replicas}")
    return [f"lab.replicas={args.replicas}"]


def _lab_plan(args, test: str):
    from .lab.scene import load_lab_plan

    overrides = _overrides(args) + _lab_replicas(args)
    return load_lab_plan(args.scene, overrides, needs_gravity=test in ("repose", "plate", "calibrate"), test=test)


def cmd_lab(args) -> int:
    from .lab import plate_test, repose_test, shear_test

    plan = _lab_plan(args, args.test)
    out = args.out or os.path.join("runs", f"{plan.name}_{args.test}")
    run = {"repose": repose_test, "shear": shear_test, "plate": plate_test}[args.test]
    summary = run(plan, out, overwrite=args.overwrite, **_executor(args))
    print(f"{args.test}: {out}")
    for line in lab_lines(summary):
        print(f"  {line}")
    missing = lab_result_missing(summary)
    if missing:  # every replica ran, none measured it: no result (it said "ok" and exited 0)
        print(f"  ! no replica measured the {missing}: the test gives no result (the notes above say why)")
        return EXIT_UNSTEADY
    return EXIT_OK


def lab_result_missing(summary: dict) -> str | None:
    """What a lab test is for when none of its replicas measured it (an angle of repose of a heap cut
    short, a friction angle or Bekker's n not fitted), else None."""
    if summary["test"] == "repose":
        return None if summary["repose_angle_deg"].get("n", 0) > 0 else "angle of repose"
    if summary["test"] == "shear":  # one normal stress: no Mohr-Coulomb line, its angle through the origin
        peak = summary["peak"]
        angles = (peak.get("friction_angle_deg", math.nan), peak.get("friction_angle_origin_deg", math.nan))
        return None if any(math.isfinite(a) for a in angles) else "peak friction angle"
    return None if math.isfinite(summary["bekker"].get("n", math.nan)) else "Bekker exponent n"


def lab_lines(summary: dict) -> list[str]:
    """The measured values of a lab summary, its quasi-static numbers and notes, as text lines."""

    def stats(name, value, unit):
        if value.get("n", 0) > 1:
            return (
                f"{name:26s} {value['mean']:.4g} {unit} +- {value['ci95']:.2g} (95 %, {value['n']} replicas; "
                f"min {value['min']:.4g}, max {value['max']:.4g})"
            )
        return f"{name:26s} {value.get('mean', float('nan')):.4g} {unit}"

    lines = []
    if summary["test"] == "repose":
        lines.append(stats("angle of repose", summary["repose_angle_deg"], "deg"))
    elif summary["test"] == "shear":

        def with_error(value) -> str:  # a standard error where the fit has one (nan or null: none)
            return f" +- {value:.2g} (s.e.)" if isinstance(value, (int, float)) and math.isfinite(value) else ""

        unbarred = False
        for state in ("peak", "residual"):
            fit = summary[state]
            lines.append(
                f"{state + ' friction angle':26s} {fit['friction_angle_deg']:.4g} deg"
                + with_error(fit.get("friction_angle_se_deg"))
            )
            lines.append(
                f"{state + ' cohesion':26s} {fit['cohesion_pa']:.4g} Pa" + with_error(fit.get("cohesion_se_pa"))
            )
            lines.append(f"{state + ' angle (c = 0)':26s} {fit['friction_angle_origin_deg']:.4g} deg")
            unbarred = unbarred or not with_error(fit.get("friction_angle_se_deg"))
        if unbarred:  # a line through two points fits them exactly: its R^2 of 1 says nothing of the soil
            lines.append(
                "! no error bar on the Mohr-Coulomb line: it needs three points or more at two normal stresses or "
                "more (through two it passes exactly); add normal stresses (shear.normal_stresses) or replicas"
            )
    elif summary["test"] == "plate":
        fit = summary["bekker"]
        if fit["k_c"] == fit["k_c"]:
            lines.append(f"{'Bekker k_c':26s} {fit['k_c']:.4g} N/m^(n+1) +- {fit['k_c_se']:.2g} (s.e.)")
            lines.append(f"{'Bekker k_phi':26s} {fit['k_phi']:.4g} N/m^(n+2) +- {fit['k_phi_se']:.2g} (s.e.)")
        else:
            lines.append(f"{'Bekker k':26s} {fit['k']:.4g} N/m^(n+2) (one plate width: k = k_c / b + k_phi)")
        lines.append(f"{'Bekker n':26s} {fit['n']:.4g} +- {fit['n_se']:.2g} (s.e.); R^2 {fit['r_squared']:.3f}")
    for number in summary.get("quasi_static", []):
        flag = "ok" if number["ok"] else "OUT OF RANGE"
        lines.append(f"[{flag}] {number['name']} = {number['value']:.3g} (limit {number['limit']:.3g})")
    lines += [f"! {note}" for note in summary.get("notes", [])]
    for failed in summary.get("failed", []):  # the values above are over the others only
        error = str(failed.get("error") or "").strip().splitlines()
        lines.append(f"! {failed.get('label')} failed, left out of the values above: {error[-1] if error else '?'}")
    if summary.get("figure"):
        lines.append(f"figure: {summary['figure']}")
    return lines


def cmd_calibrate(args) -> int:
    from .lab.calibrate import calibrate, parse_parameters, parse_targets, parse_tolerances

    targets = parse_targets(args.target)
    parameters = parse_parameters(args.vary)
    tolerances = parse_tolerances(args.tolerance, targets)
    plan = _lab_plan(args, "calibrate" if "repose" in targets else "shear")
    out = args.out or os.path.join("runs", f"{plan.name}_calibrate")
    summary = calibrate(
        plan,
        out,
        targets,
        parameters,
        tolerances,
        max_evaluations=args.max_evaluations,
        overwrite=args.overwrite,
        **_executor(args),
    )
    best = summary["best"]
    print(f"calibrate: {out}: {summary['message']} ({len(summary['evaluations'])} evaluations, {summary['method']})")
    units = summary["units"]
    for key, value in best["values"].items():
        print(f"  {key:40s} {value:.6g} {units[key]}")
    for name, value in best["measured"].items():
        print(
            f"  {name + ' measured':40s} {value:.4g} {units[name]} (target {summary['targets'][name]:g} +- "
            f"{summary['tolerances'][name]:g} {units[name]})"
        )
    print(f"  calibrated scene: {summary['calibrated_scene'] or 'none written'}")
    return EXIT_OK if summary["converged"] else EXIT_UNSTEADY


def add_lab_commands(sub, scene_options, cluster_options) -> None:
    """`cosim lab TEST SCENE` and `cosim calibrate SCENE` (docs/lab.md)."""
    p = sub.add_parser("lab", help="soil lab tests: angle of repose, direct shear, pressure-sinkage (docs/lab.md)")
    p.add_argument("test", choices=["repose", "shear", "plate"])
    scene_options(p)
    cluster_options(p)
    p.add_argument("--replicas", type=int, help="specimens (overrides lab.replicas)")
    p.set_defaults(func=cmd_lab)

    p = sub.add_parser("calibrate", help="tune contact parameters to target bulk values with the lab tests")
    scene_options(p)
    cluster_options(p)
    p.add_argument(
        "--target",
        action="append",
        required=True,
        metavar="NAME=VALUE",
        help="repose [deg], friction, friction_residual [deg], cohesion, cohesion_residual [Pa]",
    )
    p.add_argument(
        "--vary",
        action="append",
        required=True,
        metavar="KEY[,KEY]=LOW:HIGH",
        help="a scene key (or keys set together) and its range, e.g. soil.rolling_friction=0:0.3",
    )
    p.add_argument("--tolerance", action="append", metavar="NAME=VALUE", help="per target (default 1 deg, 10 %% Pa)")
    p.add_argument("--max-evaluations", type=int, default=12, help="most lab evaluations (default 12)")
    p.add_argument("--replicas", type=int, help="specimens per evaluation (overrides lab.replicas)")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser(
        "calibrate-scm",
        help="SCM terrain parameters from DEM plate and shear tests of the scene's soil at its gravity",
    )
    scene_options(p)
    cluster_options(p, out=False)
    p.add_argument("--out", required=True, help="the calibration file to write (TOML; [terrain] calibration = ...)")
    p.add_argument("--work", help="folder of the DEM tests (default: the file's name without .toml + _runs)")
    p.add_argument(
        "--replicas",
        type=int,
        help="beds and specimens per test (overrides lab.replicas); 2 or more: each +- holds their scatter",
    )
    p.add_argument(
        "--lab-sizes",
        action="store_true",
        help="the lab's own test sizes (docs/lab.md) instead of calibrate-scm's small ones (CPU minutes)",
    )
    p.add_argument(
        "--from-wheel",
        action="store_true",
        help="then fit k_phi, n, phi and K to the DEM's single-wheel runs at --slips (cosim.lab.scm_wheel)",
    )
    p.add_argument("--slips", default="0.05,0.1,0.2,0.4,0.6", help="--from-wheel: the imposed slips of the DEM runs")
    p.add_argument("--wheel-runs", help="--from-wheel: fit to this slip study's folder (cosim study slip), no new runs")
    p.add_argument("--lab", help="--from-wheel: start from this calibration file, no plate and shear tests")
    p.add_argument(
        "--start",
        help="--from-wheel: start k_phi, n, phi and K from this calibration file (a former wheel fit), "
        "the held keys from --lab's",
    )
    p.add_argument(
        "--max-runs",
        type=int,
        default=30,
        help="--from-wheel: most evaluations of the SCM runs of the DEM's protocol, one run per slip each "
        "(default 30; 0: fit to the held wheel only)",
    )
    p.set_defaults(func=cmd_calibrate_scm)


def cmd_calibrate_scm(args) -> int:
    from soil.errors import ArgumentError

    from .advice import lab_check_keys
    from .lab.scene import load_lab_plan, load_lab_scene
    from .lab.scm import calibrate_scm, small_tests
    from .scm_calibration import (
        SOIL_KEYS,
        SOIL_UNITS,
        failed_lab_checks,
        out_of_range,
        read_calibration,
        write_calibration,
    )

    _refuse_an_input_as_out(args.out, {"the scene": args.scene, "--lab": args.lab, "--start": args.start})
    _free_output_file(args.out, (".toml",), args.overwrite)  # before an hour of DEM tests, not after them
    overrides = _overrides(args) + _lab_replicas(args)
    if not args.lab_sizes:  # the small default tests where the scene sizes none
        overrides = small_tests(load_lab_scene(args.scene, overrides)) + overrides
    work = args.work or os.path.splitext(args.out)[0] + "_runs"
    if not args.lab:  # the lab's tests empty --work (with --lab none run there: its wheel runs go in subfolders)
        _refuse_an_input_in_work(work, {"--wheel-runs": args.wheel_runs, "the scene": args.scene})
    wheel_only = ("--wheel-runs", args.wheel_runs), ("--lab", args.lab), ("--start", args.start)
    misplaced = [name for name, value in wheel_only if value and not args.from_wheel]
    if misplaced:
        raise ArgumentError(f"{', '.join(misplaced)}: only with --from-wheel")
    if args.max_runs < 0:  # before the lab's tests, not an hour into them
        raise ArgumentError(f"--max-runs: must be >= 0, got {args.max_runs}")
    if args.start:
        read_calibration(args.start)  # a damaged file named now, not after the lab's tests
    if args.from_wheel:
        _check_from_wheel(args)
    started = time.perf_counter()
    if args.lab:
        calibration = read_calibration(args.lab)
        # a refitted wheel fit keeps its root lab file, its path made relative to the new file's folder
        root = calibration.source.get("lab")
        root = os.path.join(os.path.dirname(os.path.abspath(args.lab)), root) if isinstance(root, str) else args.lab
        others = {k: v for k, v in calibration.source.items() if k != "lab"}
        calibration.source = {"lab": _relative_to_file(args.out, root), **others}
    else:
        plan = load_lab_plan(args.scene, overrides, needs_gravity=True, test="plate")
        calibration = calibrate_scm(plan, work, overwrite=args.overwrite, **_executor(args))
        calibration.source["overrides"] = overrides
    if args.from_wheel:
        calibration = _fit_to_wheel(args, calibration, work)
    calibration.source["wall_time_s"] = time.perf_counter() - started
    write_calibration(args.out, calibration, replace=args.overwrite)  # --out was free an hour ago; still?
    tests = f"DEM tests in {work}, " if os.path.isdir(work) else ""  # --lab with --wheel-runs ran none
    print(f"calibrate-scm: {args.out} ({tests}|g| = {calibration.gravity:.4g} m/s^2)")
    why = calibration.source.get("error_not_estimated", {})
    for key in SOIL_KEYS:
        value, error = calibration.parameters[key], calibration.standard_errors[key]
        if math.isfinite(error):
            print(f"  {key:20s} {value:12.5g} +- {error:.3g} {SOIL_UNITS[key]}")
        else:
            reason = why.get(key, "not estimated")
            print(f"  {key:20s} {value:12.5g} {SOIL_UNITS[key]}, no error bar: {reason}")
    if not args.from_wheel:
        print(_error_bar_note(calibration.source.get("replica_fits", {})))
    rising = calibration.source.get("shear", {}).get("still_rising", [])
    if rising:  # their peaks (c, phi) and their climbs (Janosi's K) are of curves that had not peaked
        curves = ", ".join(f"replica {replica}, sigma {stress:.4g} Pa" for replica, stress in rising)
        print(
            f"calibrate-scm: warning: shear curves still rising at the end of their travel ({curves}): their peaks "
            "(c, phi) and Janosi's K come from curves that had not peaked; lengthen shear.displacement "
            "(docs/lab.md)",
            file=sys.stderr,
        )
    for problem in failed_lab_checks(calibration) or ():  # said now, not first by a scene's advise
        keys = lab_check_keys([problem])
        print(
            f"calibrate-scm: warning: a DEM lab test out of its quasi-static range: {problem}; a scene on "
            f"{args.out} is flagged (scm_calibration_lab): calibrate again with {' or '.join(keys) or 'other tests'} "
            "changed (docs/lab.md)",
            file=sys.stderr,
        )
    for key, problem in out_of_range(calibration.parameters).items():
        print(
            f"calibrate-scm: warning: {problem}: outside what SCM takes, so a scene on {args.out} fails unless it "
            f"sets terrain.{key} itself; the tests are too small or noisy for this soil (wider and deeper plates, "
            "a larger shear box: --lab-sizes or --set plate.widths=..., shear.length=...; --replicas 3)",
            file=sys.stderr,
        )
    return EXIT_OK


def _refuse_an_input_in_work(work: str, inputs: dict[str, str | None]) -> None:
    """Refuse a --work folder that is, holds, or lies inside one of the paths the command reads (even with
    --overwrite, which empties --work: `--work STUDY --wheel-runs STUDY --overwrite` removed the slip study
    it was to fit to)."""
    from soil.errors import ArgumentError

    folder = os.path.realpath(work)
    for name, path in inputs.items():
        if not path or not os.path.exists(path):
            continue
        given = os.path.realpath(path)
        common = os.path.commonpath([folder, given])
        if common in (folder, given) and (folder != given or os.path.isdir(given)):
            how = "is" if folder == given else "holds" if common == folder else "lies in"
            raise ArgumentError(
                f"--work {work!r} {how} {name} ({path}), which the command reads and --work's tests would "
                "replace; name another folder"
            )


def _refuse_an_input_as_out(out: str, inputs: dict[str, str | None]) -> None:
    """Refuse an --out that is one of the files the command reads (even with --overwrite: the scene or
    the calibration it starts from would be lost to what it writes)."""
    from soil.errors import ArgumentError

    for name, path in inputs.items():
        if path and os.path.exists(out) and os.path.exists(path) and os.path.samefile(out, path):
            raise ArgumentError(f"--out {out!r} is {name} the command reads; write to another file")


def _check_from_wheel(args) -> None:
    """What --from-wheel needs, checked before the lab's DEM tests (an hour) rather than after them: a
    single-wheel scene, --lab and --start calibrated at its gravity, --wheel-runs a slip study of this
    wheel with two or more steady slips, or --slips two or more slips."""
    from .lab.scm_wheel import check_study_scene, wheel_targets
    from .scene import SceneError, parse_list
    from .scm_calibration import read_calibration, same_gravity
    from .study import check_slips

    plan = _plan(args)
    if plan.rover is not None:
        raise SceneError(["calibrate-scm --from-wheel: fits to the single-wheel [testbed]; the scene has a [rover]"])
    for option, path in (("--lab", args.lab), ("--start", args.start)):
        if path and not same_gravity(gravity := read_calibration(path).gravity, plan.g):
            raise SceneError([f"{option}: calibrated at |g| = {gravity:.4g} m/s^2, the scene's is {plan.g:.4g} m/s^2"])
    if args.wheel_runs:
        check_study_scene(args.wheel_runs, plan)
        wheel_targets(args.wheel_runs)  # two or more steady slips
    else:  # the slip study's own checks, two slips at least: a fit to one is no fit
        check_slips(plan, parse_list(args.slips, "--slips"), least=2)


def _relative_to_file(out: str, path: str) -> str:
    """`path` as the calibration file `out` records it: relative to the file's folder (the file and its
    runs move together, as a scene's [terrain] calibration is relative to the scene)."""
    return os.path.relpath(os.path.abspath(path), os.path.dirname(os.path.abspath(out)))


def _error_bar_note(replica_fits: dict) -> str:
    """calibrate-scm's line under its values: what its +- holds (cosim.lab.scm.combine_errors)."""
    from scipy.stats import t

    from .scm_calibration import SOIL_KEYS

    if not replica_fits:
        # two one-bed draws of the main job's soil differed by up to 7.6 of these errors (BENCHMARKS.md)
        return (
            "  (+-: each fit's standard error over its points, on one bed and one specimen; the scatter between "
            "beds and specimens is not in it and can be several times larger: --replicas 3 puts it in)"
        )
    counts = sorted({sum(math.isfinite(v) for v in values) for values in replica_fits.values()})
    left_out = [k for k in SOIL_KEYS if k not in replica_fits]
    one_bed = f"; {', '.join(left_out)}: the pooled fit's alone (one bed)" if left_out else ""
    # R < 2 leaves no scatter between replicas: the pooled fit's error alone, whose degrees of freedom
    # are its points' (not R - 1)
    multipliers = [f"+- {t.ppf(0.975, r - 1):.3g} of these at R = {r}" for r in counts if r >= 2]
    alone = "; R < 2: the pooled fit's error alone, no interval between replicas" if min(counts) < 2 else ""
    intervals = ""
    if multipliers:
        intervals = f"; with R - 1 degrees of freedom a 95 % interval is {', '.join(multipliers)}"
    return (
        "  (+-: the larger of the pooled fit's standard error and the replicas' own fits' scatter / sqrt(R), "
        f"R = {'/'.join(map(str, counts))} ([source] replica_fits){one_bed}{intervals}{alone})"
    )


def _fit_to_wheel(args, lab, work: str):
    """The lab calibration `lab` refitted to the DEM wheel runs (cosim calibrate-scm --from-wheel)."""
    from .lab.scm import combine_errors
    from .lab.scm_wheel import FITTED, fit_to_wheel, run_wheel_tests, wheel_targets
    from .scene import parse_list
    from .scm_calibration import SOIL_UNITS, ScmCalibration, read_calibration

    plan = _plan(args)  # the scene, --lab, --start and --slips were checked before the lab (_check_from_wheel)
    if args.wheel_runs:
        folder = args.wheel_runs
    else:
        slips = parse_list(args.slips, "--slips")
        replicas = args.replicas if args.replicas is not None else 3
        folder = run_wheel_tests(plan, os.path.join(work, "wheel"), slips, replicas, **_executor(args))
    runs = os.path.join(work, "wheel_scm") if args.max_runs else None
    start = dict(lab.parameters)
    if args.start:  # the fitted keys' start from another file (a former wheel fit), the held keys the lab's
        start.update({k: read_calibration(args.start).parameters[k] for k in FITTED})
    parameters, errors, report = fit_to_wheel(plan, wheel_targets(folder), start, runs=runs, max_runs=args.max_runs)
    print(
        f"calibrate-scm --from-wheel: fitted {', '.join(FITTED)} to {len(report['slips'])} slips (rms residual "
        f"{report['rms_residual']:.3g} tolerances; {report['evaluations']} held-wheel evaluations, "
        f"{report['run_evaluations']} of the runs{f' in {runs}' if runs else ''})"
    )
    for row in report["slips"]:
        load = report["wheel_load_n"]
        run = "run_" if runs else "scm_"
        sinkage = (
            f"sinkage {row['run_sinkage'] * 1e3:6.2f} mm"
            if runs
            else f"W_scm / W {row['scm_vertical_force'] / load:6.3f} at"
        )
        print(
            f"  slip {row['slip']:5.3f}: {sinkage} (DEM {row['sinkage'] * 1e3:6.2f} mm), "
            f"DP/W {row[run + 'drawbar_pull'] / load:+7.3f} (DEM {row['drawbar_pull'] / load:+7.3f}), "
            f"T {row[run + 'driving_torque']:.3g} (DEM {row['driving_torque']:.3g}) N m"
        )
    standard_errors = {k: (errors[k] if k in FITTED else lab.standard_errors.get(k, errors[k])) for k in errors}
    beds = _fit_beds(args, plan, lab, folder, parameters, work)
    if beds:
        report["standard_error_of_fit"] = {k: errors[k] for k in FITTED}
        report["units"] = {
            **report.get("units", {}),
            **{f"{name}.{k}": SOIL_UNITS[k] for name in ("replica_fits", "standard_error_of_fit") for k in FITTED},
            "replica_rms_residual": "1 (tolerances: residual_unit)",
        }
        standard_errors.update({k: v for k, v in combine_errors(errors, beds["replica_fits"]).items() if k in FITTED})
        fits = beds["replica_fits"]
        print(
            f"  each bed alone ({len(fits['k_phi'])} beds; rms residual "
            f"{', '.join(f'{r:.3g}' for r in beds['replica_rms_residual'])}): "
            + "; ".join(f"{k} {', '.join(f'{v:.4g}' for v in fits[k])}" for k in FITTED)
        )
    # the file the fit started from: the root lab file stays source['lab'] when a wheel fit is refitted
    start_file = args.start or args.lab
    started = {"start_file": _relative_to_file(args.out, start_file)} if start_file else {}
    source = {**lab.source, "wheel": {"runs": _relative_to_file(args.out, folder), **started, **report, **beds}}
    return ScmCalibration(parameters, standard_errors, plan.g, source)


def _fit_beds(args, plan, lab, folder: str, parameters: dict, work: str) -> dict:
    """The wheel fit repeated on each bed of a slip study over beds (cosim.lab.scm_wheel.fit_beds), bed k
    holding bed k's own lab values where the lab fitted its beds alone (cosim.scm_calibration.bed_soils;
    the beds paired by index: both are bed.seed + k); {} when the study's replicas shared one bed.
    Returns [source.wheel]'s replica_fits (FITTED -> a value per bed, nan where a bed's fit failed),
    replica_rms_residual and, with the lab's beds, lab_beds (how many were paired)."""
    from .lab.scm_wheel import FITTED, bed_wheel_targets, fit_beds
    from .scm_calibration import bed_soils

    bed_targets = bed_wheel_targets(folder)
    if len(bed_targets) < 2:
        return {}
    lab_beds = bed_soils(lab, args.lab or "")
    if lab_beds:  # a bed of the wheel runs is paired with the lab's bed of the same seed
        bed_targets = bed_targets[: len(lab_beds)]
    starts = [
        {**parameters, **{k: v for k, v in (lab_beds[b] if lab_beds else {}).items() if k not in FITTED}}
        for b in range(len(bed_targets))
    ]
    runs = os.path.join(work, "wheel_scm_beds") if args.max_runs else None
    print(f"calibrate-scm --from-wheel: fitting each of {len(bed_targets)} beds alone ({folder})")
    results = fit_beds(plan, bed_targets, starts, runs, args.max_runs, **_executor(args))
    for b, result in enumerate(results):
        if not result.get("ok"):
            print(f"calibrate-scm: warning: the wheel fit on bed {b} failed: {result.get('error')}", file=sys.stderr)
    if sum(bool(r.get("ok")) for r in results) < 2:
        print("calibrate-scm: warning: fewer than two beds fitted: no scatter between beds", file=sys.stderr)
        return {}
    out: dict = {
        "replica_fits": {k: [float(r["parameters"][k]) if r.get("ok") else math.nan for r in results] for k in FITTED},
        "replica_rms_residual": [float(r["rms_residual"]) if r.get("ok") else math.nan for r in results],
    }
    if lab_beds:
        out["lab_beds"] = len(bed_targets)
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cosim",
        description="regolith-cosim: DEM soil co-simulated with rovers",
        epilog="exit status: 0 ok, 1 unexpected error (or a study's run failed), 2 bad input, 3 output folder "
        "or file not free, 4 diverged, 5 OS error, 6 no steady-state result (of a run, or of one of a study's), "
        "130 interrupted, 143 stopped by SIGTERM, 129 by SIGHUP",
    )
    parser.add_argument("--verbose", "-v", action="store_true", help="debug log lines, Warp's messages, tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)

    def scene_options(p, device=True):
        p.add_argument("scene", help="scene file (TOML)")
        p.add_argument(
            "--set",
            action="append",
            metavar="KEY=VALUE",
            help="override a scene key, e.g. --set wheel.radius=0.05 (repeatable)",
        )
        if device:
            p.add_argument("--device", help="Warp device: cpu, cuda, cuda:N (overrides scene.device)")
            p.add_argument("--precision", choices=["single", "double", "mixed"], help="overrides scene.precision")

    def cluster_options(p, out=True):
        if out:
            p.add_argument("--out", help="output folder")
        p.add_argument("--workers", type=int, help="LocalCluster worker processes (default: CPU cores)")
        p.add_argument("--scheduler", help="address of a running dask scheduler (instead of a LocalCluster)")
        p.add_argument("--serial", action="store_true", help="run the tasks one after another in this process")
        p.add_argument("--overwrite", action="store_true", help="replace what the output folder holds")

    p = sub.add_parser("run", help="run a scene")
    scene_options(p)
    cluster_options(p)
    p.add_argument(
        "--replicas",
        type=int,
        default=1,
        help="K > 1: run K replicas differing only in summation order and report error bars",
    )
    p.add_argument(
        "--vary-bed",
        action="store_true",
        help="with --replicas: each replica on a bed of its own too (replica k settles bed.seed + k; its SCM "
        "wheels on the soil its calibration fitted on bed k): the scatter between beds, not only the summation "
        "order's on one bed",
    )
    p.add_argument(
        "--batched",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="replicas as worlds of one simulation on one device (default: on a GPU, when the scene allows)",
    )
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "resume", help="continue an interrupted run, set of replicas, sweep or study from its checkpoints"
    )
    p.add_argument("out", help="the run's output folder")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_resume)

    p = sub.add_parser("advise", help="stiffness (paper eq. 10), time step and validity of a scene")
    scene_options(p)
    p.set_defaults(func=cmd_advise)

    p = sub.add_parser("plot", help="PNGs of a run or a study folder")
    p.add_argument("out", help="a run folder or a study folder (runs up to 4 folders below it are plotted)")
    p.add_argument("--plot-dir", help="where to write the PNGs (default OUT/plots)")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("view", help="a movie or picture of a run's grains and wheels, no ParaView needed")
    p.add_argument("run", help="a run folder (or its results.h5)")
    p.add_argument(
        "--out",
        help="movie.mp4 (ffmpeg), movie.gif, picture.png (one frame) or a folder for PNG frames "
        "(default RUN/plots/view.mp4, view.gif without ffmpeg)",
    )
    p.add_argument("--color", choices=["speed", "displacement"], default="speed", help="what colours the grains")
    p.add_argument("--frame", type=int, help="with a .png: the snapshot to draw (default the last; -1 counts back)")
    p.add_argument(
        "--fps", type=int, default=5, help="movie frames per second, 1 to 120 (one frame per snapshot; default 5)"
    )
    p.add_argument(
        "--dpi", type=int, default=100, help="pixels per inch of the frames, 10 to 600 (10 in wide; default 100)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out picture or folder of frames")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("export", help="export a run's snapshots to another format (vtkhdf: ParaView, VTK)")
    p.add_argument("format", choices=["vtkhdf"])
    p.add_argument("run", help="a run folder (or its results.h5)")
    p.add_argument("--out", help="the .vtkhdf (or .hdf) file to write (default RUN/results.vtkhdf, made again)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("study", help="precision (replica scatter), time-step or drawbar-pull/slip studies")
    p.add_argument("kind", choices=["precision", "timestep", "slip"])
    scene_options(p)
    cluster_options(p)
    p.add_argument("--replicas", type=int, help="precision, slip: replicas per precision or slip (default 3)")
    p.add_argument("--precisions", help="precision: the precisions compared (default single,mixed,double)")
    p.add_argument("--slips", help="slip: imposed slips, comma-separated (default 0.1,0.2,0.3,0.5)")
    p.add_argument(
        "--from-runs",
        nargs="+",
        metavar="STUDY",
        help="slip: tabulate the runs these study folders hold (stopped or run in parts) instead of running",
    )
    p.add_argument(
        "--include-sinking",
        action="store_true",
        help="--from-runs: average the runs whose traction is steady and sinkage still drifts too",
    )
    p.add_argument(
        "--batched",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="precision, slip: the runs as worlds of one simulation on one device (precision: one per "
        "precision; default: on a GPU, when the scene allows)",
    )
    p.add_argument(
        "--vary-bed",
        action="store_true",
        help="slip: replica k on a bed of its own (bed.seed + k) at every slip, not all on one bed",
    )
    p.add_argument("--duration", type=float, help="timestep: simulated time of each try [s] (default 0.05)")
    p.add_argument("--max-tries", type=int, help="timestep: most runs of the search (default 8)")
    p.set_defaults(func=cmd_study)

    p = sub.add_parser("sweep", help="runs over a grid of scene values")
    scene_options(p)
    cluster_options(p)
    p.add_argument(
        "--param",
        action="append",
        required=True,
        metavar="KEY=V1,V2,...",
        help="a key and its values; list values as one TOML array of them: KEY=[[1.0, 2.0], [1.5, 2.5]]",
    )
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("scale", help="write the DEM-similar scene at another gravity (the gravity twin)")
    scene_options(p, device=False)
    p.add_argument("--gravity", required=True, help="target gravity: a preset name or a magnitude [m/s^2]")
    p.add_argument("--out", required=True, help="the twin scene file to write")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=cmd_scale)

    p = sub.add_parser("export-fmu", help="the soil as an FMI 2.0/3.0 co-simulation FMU (docs/fmu.md)")
    p.add_argument("source", metavar="SCENE_OR_RUN_DIR", help="a scene file (TOML) or a run folder")
    p.add_argument("--out", required=True, help="the .fmu file to write")
    p.add_argument("--fmi", type=int, choices=[2, 3], default=2, help="FMI version (default 2)")
    p.add_argument("--wheels", type=int, default=1, help="wheels in one FMU instance, on one bed (default 1)")
    p.add_argument("--device", help="the soil server's default Warp device (default: the scene's)")
    p.add_argument("--python", help="the soil server's default Python (default: this one)")
    p.add_argument("--bed-folder", help="where a scene's bed is settled and cached (default: a temporary folder)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=cmd_export_fmu)

    add_lab_commands(sub, scene_options, cluster_options)
    return parser


def _stop_on_signals() -> dict:
    """SIGTERM (a batch scheduler, `docker stop`) and SIGHUP (the terminal closed) stop like Ctrl-C: a run
    checkpoints and stops cleanly (cosim.runner installs its own handler while it steps); elsewhere the
    command unwinds, locks released. Returns the handlers it replaced (cosim.stop_signals.restore)."""
    import signal

    from .stop_signals import install

    def stop(signum, frame):
        raise KeyboardInterrupt(signal.Signals(signum).name)

    former = install(stop)
    if signal.SIGINT in former:  # Ctrl-C keeps Python's own KeyboardInterrupt
        signal.signal(signal.SIGINT, former.pop(signal.SIGINT))
    return former


def _say(line: str) -> None:
    """A last line on stderr, which a closed terminal no longer takes (EIO): then it is not said."""
    try:
        print(line, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


def _detach_closed_output() -> None:
    """Flush stdout and stderr now; one a closed terminal refuses is pointed at /dev/null, so Python's own
    flush at exit does not fail too (and turn the exit status into 120)."""
    for stream in (sys.stdout, sys.stderr):
        if stream is None:  # no console at all (pythonw, some services)
            continue
        try:
            stream.flush()
        except (OSError, ValueError):
            try:
                null = os.open(os.devnull, os.O_WRONLY)
                os.dup2(null, stream.fileno())
                os.close(null)
            except (OSError, ValueError):
                pass


def main(argv=None) -> int:
    from .stop_signals import restore

    previous = _stop_on_signals()  # first: warp loads below (about a second), and a stop then is answered too
    args = None
    try:
        try:
            args = build_parser().parse_args(argv)
            _setup_output(args.verbose)
        except KeyboardInterrupt as error:
            return _interrupted(error)
        return _dispatch(args)
    except Exception as error:  # noqa: BLE001 - what no rule below expected: a bug, exit 1
        if getattr(args, "verbose", False):
            log.exception("cosim: unexpected error (a bug: please report it with this traceback)")
        else:
            _say(f"cosim: unexpected error: {type(error).__name__}: {error} (a bug: --verbose shows the traceback)")
        return EXIT_ERROR
    finally:
        restore(previous)
        _detach_closed_output()


def _interrupted(error: BaseException) -> int:
    """A stop signal's one line, and its exit status: 128 + the signal's number (130 Ctrl-C, 143 SIGTERM,
    129 SIGHUP)."""
    from .stop_signals import exit_status, stop_name

    _say(f"\ncosim: interrupted. {error}".rstrip())
    return exit_status(stop_name(error))


def _dispatch(args) -> int:
    """Run the command; the project's own errors become their exit status and a one-line message
    (bad input: 2, only soil.errors.InputError; a failure the project reports that is not the
    input's: 1); anything else propagates to `main` as unexpected. A stop signal exits 128 + its number
    (cosim.stop_signals: Ctrl-C 130, SIGTERM 143, SIGHUP 129) with one line, also while the modules below
    load (seconds: warp's)."""

    def fail(code: int, error) -> int:
        _say(f"cosim: error: {error}")
        return code

    try:
        from soil.errors import InputError, RegolithError
        from soil.stability import SimulationDiverged

        from .beds import SettlingDiverged
        from .folders import OutputFolderError
        from .lab.common import LabDiverged
        from .runner import RunDiverged, RunInterrupted
        from .scene import SceneError
    except KeyboardInterrupt as error:
        return _interrupted(error)

    try:
        return args.func(args)
    except SceneError as error:
        return fail(EXIT_INPUT, error)
    except OutputFolderError as error:
        return fail(EXIT_FOLDER, error)
    except (RunDiverged, SettlingDiverged, SimulationDiverged, LabDiverged) as error:
        return fail(EXIT_DIVERGED, error)
    except (KeyboardInterrupt, RunInterrupted) as error:
        return _interrupted(error)
    except InputError as error:  # an FMU, a mesh, a bed, an argument: bad input the project recognised
        return fail(EXIT_INPUT, error)
    except RegolithError as error:  # a failure the project reports (a model refused a step, a tool is missing)
        if args.verbose:
            log.exception("cosim: %s", type(error).__name__)
        return fail(EXIT_ERROR, f"{type(error).__name__}: {error}")
    except OSError as error:
        where = f"{error.filename}: " if getattr(error, "filename", None) else ""
        return fail(EXIT_OS, f"{where}{error.strerror or error}")


if __name__ == "__main__":
    sys.exit(main())
