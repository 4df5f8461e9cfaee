"""The terramechanics quantities, defined once, for the product and the tests alike.

Per wheel and macro step (`wheel_quantities`), in the wheel's own frame (axle = the body's
+Y axis, forward = axle x up, so a wheel turning about +Y rolls towards +X):

    travel          distance the hub moved forward since the drive started [m]
    slip            s = 1 - v / (omega r): v the hub speed forward, omega the spin about the
                    axle, r the rim radius [-] (nan while the wheel does not turn)
    sinkage         undisturbed surface height - lowest point of the rim (hub z - r) [m]
    sinkage_tips    the same for the grouser tips (hub z - outer radius) [m]
    drawbar_pull    soil force on the wheel along the forward direction [N] (the net traction)
    driving_torque  torque the drive supplies against the soil, -(soil torque . axle) [N m]
    normal_force    soil force along the bed normal, up (+z) [N] (carries the wheel load at rest;
                    m |g| cos(slope) summed over a rover's wheels)
    power           power the drive delivers against the soil's torque, driving_torque x spin [W]

Over a run (`summarize`): a steady-state window is found in the driving phase by the MSER-5
rule (White 1997: the truncation that minimises the standard error of the mean of what
remains): the traction's start (the forward speed, or at imposed slip the drawbar pull), moved
on to the sinkage's start over the rest where MSER-5 finds one (`drive_window`), the sinkage
steady over that window too (MSER-5, or a drift under half a grain radius); over it
slip = 1 - mean(v) / (mean(omega) r) from mean speeds, and sinkage, drawbar pull, DP/W and
torque are means. A run with no steady state gets a status saying
why: 'never touched the soil', 'no landing', 'airborne', 'stuck', 'too short' (also a grousered
wheel's window over which its rim turned less than one grouser pitch, 2 pi / grouser count: a mean over
part of a grouser's passage depends on where in it the window starts), 'still sinking' or 'still
rising' (the sinkage drifts downwards or upwards across the window), or 'ramped load' (free mode with a
drawbar load that grows over the drive: no steady state by design).

For a rover (`rover_quantities` per macro step, `summarize_rover` over a run), in the rover's
frame (forward = its body's +x axis turned into the horizontal plane, up = +z):

    forward_speed   body velocity along forward [m/s]
    slip            1 - forward_speed / (mean over the wheels of spin x rim radius) [-] (nan
                    while the wheels turn against each other: TURNING_IN_PLACE)
    net_traction    sum over the wheels of the soil force along forward [N] (what a drawbar
                    would feel; on a slope it carries the weight's downhill part)
    power           sum of the wheels' power [W]
    travel          horizontal path length of the body since the drive started [m]

and over the driving phase: energy = integral of the power [J], energy_per_metre = energy /
travel [J/m], and the time immobile [s] under the stuck criterion: the rover is immobile at a
macro step when, over the last radian of (mean) wheel turn before it, its body advanced along
its wheels' rim travel no more than (1 - stuck_slip) of it (with the default stuck_slip 0.9: its
slip over the window is at least 0.9, or it moved against its wheels); it is stuck when it is
immobile at the end of the drive, its slip over the steady window is at least stuck_slip, or its
drive stalled: the drive commands the wheels (a speed or a torque) while over the window they do
not turn with it (still, jittering about their axles, or turned backwards), and their rims and the
body (along the drive) advance less than one grain diameter (a torque too weak to turn them, a
motor at its limit, or a torque holding the rover still; its slip would be a ratio of noise, nan
when they stop entirely). A stall adds no time immobile; a parked rover (zero commands, or zero
speeds: a brake) is not judged.
Steps before the wheels have turned one radian are not judged, nor steps while they turn against
each other. The steady-state window is found as for a wheel (`drive_window` on the forward speed and the
mean sinkage; each wheel's sinkage steady over it, else 'still sinking' or 'still rising'; one grouser
passage at least over it for the grousered wheels that turn, else 'too short'); slip, sinkage, drawbar
pull, torque, normal force and power per wheel and the rover's slip, net traction and power are
means over it. A wheel's slip over the window is nan where the drive held it still (speed 0 at every
step: parked or braked) or where its mean spin lies within two batch-means standard errors of zero (a
hinge jittering about its axle: the ratio would divide by noise); the rover's, where every wheel was
held or the wheels' mean rim speed is so lost in its scatter.

Across replicas (`ensemble`): mean, standard deviation, a 95 % Student-t interval, and
whether the metric is macroscopically deterministic (replica std within its tolerance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from soil.control import quaternion_to_matrix

from .contract import WheelKinematics, WheelWrench, wheel_frame
from .single_wheel import PHASE_DRIVING

STEADY = "steady"
NEVER_TOUCHED = "never touched the soil"
NO_LANDING = "no landing"
AIRBORNE = "airborne"
STUCK = "stuck"
TOO_SHORT = "too short"
SINKING = "still sinking"
RISING = "still rising"
"""The sinkage drifts (as SINKING) but upwards: the wheel climbs out of a rut deeper than its steady one."""
RAMPED = "ramped load"
"""Free mode with a drawbar load growing over the drive (testbed.drawbar_ramp): no steady state by design,
its slip climbing with the load (a drawbar pull-slip curve in one run: read its series)."""

WHEEL_UNITS = {
    "travel": "m",
    "slip": "1",
    "sinkage": "m",
    "sinkage_tips": "m",
    "drawbar_pull": "N",
    "driving_torque": "N m",
    "normal_force": "N",
    "power": "W",
}
"""Units of the per-wheel quantities."""


@dataclass(frozen=True)
class WheelGeometry:
    """What the definitions need to know of a wheel and the ground."""

    rim_radius: float
    """r for slip and rim sinkage [m]."""
    outer_radius: float
    """Radius over the grouser tips [m]."""
    surface_height: float
    """Undisturbed soil surface z [m]."""
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """Unit vector against gravity [-]."""
    axis_local: tuple[float, float, float] = (0.0, 1.0, 0.0)
    """Spin axis in the wheel body frame [-]."""


def slip_of(forward_speed, spin, rim_radius: float):
    """Slip s = 1 - v / (omega r) [-]; nan where the wheel does not turn."""
    rim = np.asarray(spin, dtype=float) * rim_radius
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(rim) > 0, 1.0 - np.asarray(forward_speed, dtype=float) / rim, np.nan)


DRIVE_COMMANDS = ("speed_command", "torque_command")
"""The series of the drive's commands per wheel (cosim.output): a stall is judged against them."""

TURNING_IN_PLACE = 0.5
"""The wheels' mean rim speed below this fraction of their mean rim speed's magnitude: they turn
against each other (a turn in place, skid steering), and the rover has no slip along its forward
direction (1 - v / mean(omega r) divides by nearly nothing) nor a drive to be stuck in."""


def rover_slip(forward_speed: float, spins, rim_radii) -> float:
    """The rover's slip 1 - v / mean(omega r) [-] (module docstring); nan where the wheels do not turn or
    turn against each other (TURNING_IN_PLACE)."""
    rim = np.asarray(spins, dtype=float) * np.asarray(rim_radii, dtype=float)
    mean, magnitude = float(np.mean(rim)), float(np.mean(np.abs(rim)))
    if not abs(mean) >= TURNING_IN_PLACE * magnitude:
        return math.nan
    return float(slip_of(forward_speed, mean, 1.0))


def wheels_held(speed_commands) -> np.ndarray:
    """Per wheel, whether a drive held it still over a window: its speed command 0 at every step (a parked
    or braked wheel; its slip is no traction's). speed_commands [rad/s] (S, W), nan where a torque was
    commanded. Returns bool (W,)."""
    return np.all(np.asarray(speed_commands, dtype=float) == 0.0, axis=0)


def spin_unresolved(spins) -> np.ndarray:
    """Per column of `spins` over a window (S, W) [rad/s, or any speed]: whether its mean lies within
    two batch-means standard errors of zero, so that 1 - v / (omega r) would divide by noise (a hinge
    jittering about its axle). A constant series has no scatter: resolved unless exactly 0 (slip_of's nan).
    Returns bool (W,)."""
    spins = np.asarray(spins, dtype=float)
    means = spins.mean(axis=0)
    errors = np.array([batch_standard_error(column) for column in spins.T])
    return np.abs(means) <= 2.0 * np.nan_to_num(errors, nan=0.0)


def sinkage_steady(
    sinkage: np.ndarray, time: np.ndarray, min_fraction: float, grain_radius: float | None
) -> tuple[bool, float]:
    """(steady, rate [m/s]) of a sinkage series [m] over a window at times [s]: stationary by MSER-5, or
    drifting by less than half of `grain_radius` [m] across it (the grain-scale roughness of the surface
    it is measured from); rate is its fitted slope."""
    sinkage, time = np.asarray(sinkage, dtype=float), np.asarray(time, dtype=float)
    if not np.all(np.isfinite(sinkage)):  # no steady state, and no rate, from a nan or an inf
        return False, math.nan
    rate = float(np.polyfit(time - time[0], sinkage, 1)[0]) if len(time) > 1 else 0.0
    cut = mser_truncation(sinkage)
    steady = (cut is not None and len(sinkage) - cut >= max(min_fraction * len(sinkage), 4)) or (
        grain_radius is not None and abs(rate) * (time[-1] - time[0]) < 0.5 * grain_radius
    )
    return bool(steady), rate


def wheel_quantities(
    kinematics: WheelKinematics, wrench: WheelWrench, geometry: WheelGeometry, drive_start_position: np.ndarray | None
) -> dict[str, float]:
    """The quantities of the module docstring for one wheel at one instant (units: WHEEL_UNITS)."""
    axis, forward = wheel_frame(kinematics.orientation, geometry.axis_local)
    up = np.asarray(geometry.up)
    v = float(kinematics.linear_velocity @ forward)
    spin = float(kinematics.angular_velocity @ axis)
    height = float(kinematics.position @ up)
    travel = 0.0 if drive_start_position is None else float((kinematics.position - drive_start_position) @ forward)
    return {
        "travel": travel,
        "slip": float(slip_of(v, spin, geometry.rim_radius)),
        "sinkage": geometry.surface_height - (height - geometry.rim_radius),
        "sinkage_tips": geometry.surface_height - (height - geometry.outer_radius),
        "drawbar_pull": float(wrench.force @ forward),
        "driving_torque": -float(wrench.torque @ axis),
        "normal_force": float(wrench.force @ up),
        "power": -float(wrench.torque @ axis) * spin,
    }


# ------------------------------------------------------------------------------------
# steady state


def mser_truncation(values: np.ndarray, batch: int = 5) -> int | None:
    """MSER-5: the number of leading samples to drop so that the rest has the smallest
    standard error of its mean, sum (Y_j - mean)^2 / (k - d)^2 over batch means Y_j.

    None when the best truncation is past half the data (no steady state in the series).
    """
    values = np.asarray(values, dtype=float)
    k = len(values) // batch
    if k < 4 or not np.all(np.isfinite(values)):  # a nan made every score nan: "steady from the start"
        return None
    means = values[: k * batch].reshape(k, batch).mean(axis=1)
    best, best_d = math.inf, 0
    for d in range(k // 2 + 1):
        rest = means[d:]
        score = float(np.sum((rest - rest.mean()) ** 2)) / (k - d) ** 2
        if score < best:
            best, best_d = score, d
    if best_d >= k // 2:
        return None
    return best_d * batch


SUMMARY_RULE = 2
"""The version of the steady-window rule a summary was made under: run.json's summary['summary_rule'], and
the same key in a table's study.json or ensemble.json. 2 since 2026-12-07 (`drive_window`: the traction's
start moved on to the sinkage's over the rest); none recorded: made before, a wheel's window the traction's
alone, whose means mixed its settling in (the main job's sinkage 8.16 mm against 8.79 mm), a rover's from
the later of the two starts over the whole drive. `cosim resume` of a run, or of a set of runs, makes a
stale summary again from its results and checkpoint; a slip table, a wheel fit and the SCM-DEM trade
refuse one."""


def summary_is_current(summary) -> bool:
    """Whether a run's (or a table's) recorded summary_rule is this code's SUMMARY_RULE."""
    return isinstance(summary, dict) and summary.get("summary_rule") == SUMMARY_RULE


def drive_window(traction: np.ndarray, sinkage: np.ndarray, min_fraction: float = 0.25) -> tuple[int, bool]:
    """(first sample of the steady window, found) over a drive: the traction's MSER-5 start (forward speed,
    or drawbar pull at an imposed slip), moved on to the sinkage's MSER-5 start over the rest where it has
    one (a pull steady from the drive's start while the wheel still sinks would mix the settling into every
    mean). Where the rest of the sinkage has none (a steady drift, a settling past half of it, a noise-free
    approach, a nan) the traction's start stands and the sinkage is judged over the window apart
    (`sinkage_steady`); found is False when the traction has no start or the window would be shorter than
    min_fraction of the drive."""
    n = len(traction)
    start = mser_truncation(traction)
    if start is None:
        return n, False
    start += mser_truncation(np.asarray(sinkage)[start:]) or 0
    return start, (n - start) >= max(min_fraction * n, 4)


BATCHES = 8
"""Batch means a window's standard error is taken over [count] (`batch_standard_error`)."""


def within_run_interval(sem: float) -> float:
    """The 95 % half-width of a window's mean from its batch-means standard error `sem` [its unit]:
    Student's t with BATCHES - 1 degrees of freedom (2.36 x sem), what a run's summary prints as its
    `+-` (one s.e. alone covers the mean about 65 % of the time)."""
    from scipy import stats

    return float(stats.t.ppf(0.975, BATCHES - 1) * sem)


def batch_standard_error(values: np.ndarray, batches: int = BATCHES) -> float:
    """Standard error of the mean of a correlated series from batch means [unit of values]: every
    sample in one of `batches` consecutive batches (sizes differing by one at most). Too small when
    the series spans fewer than MIN_CORRELATION_TIMES of its correlation times (`correlation_time`)."""
    values = np.asarray(values, dtype=float)
    if len(values) < batches or batches < 2:
        return math.nan
    means = np.array([part.mean() for part in np.array_split(values, batches)])
    return float(np.std(means, ddof=1) / math.sqrt(batches))


MIN_CORRELATION_TIMES = 50
"""A series shorter than this many of its integrated correlation times has a batch-means standard
error that is too small: a 95 % interval from it covered the mean of AR(1) series 93 % of the time
at 26 correlation times, 88 % at 10, 82 % at 5 (tests/test_metrics.py), and the correlation time
itself is then underestimated (Sokal; emcee's `integrated_time` asks for 50 by default)."""


def correlation_time(values: np.ndarray) -> float:
    """Integrated autocorrelation time of a series [samples] (Sokal's automatic window, c = 5, as
    emcee computes it); nan for fewer than 8 samples, a non-finite sample or a constant series."""
    from emcee.autocorr import integrated_time

    values = np.asarray(values, dtype=float)
    if len(values) < 8 or not np.all(np.isfinite(values)) or np.ptp(values) == 0:
        return math.nan
    return float(integrated_time(values, c=5, tol=0, quiet=True)[0])


def window_mean(out: dict, name: str, values: np.ndarray, sample_interval: float) -> None:
    """out[name] = the mean of `values` over a steady window, with `name_sem` (batch-means standard
    error) and `name_correlation_time` [s] (`correlation_time` x the samples' spacing [s])."""
    out[name] = float(np.mean(values))
    out[f"{name}_sem"] = batch_standard_error(values)
    out[f"{name}_correlation_time"] = correlation_time(values) * sample_interval


def short_window(summary: dict, name: str) -> float | None:
    """The steady window of `summary` in correlation times of `name`, when fewer than
    MIN_CORRELATION_TIMES (its `name_sem` is then too small); else None."""
    tau, window = summary.get(f"{name}_correlation_time"), summary.get("window")
    if tau is None or not math.isfinite(tau) or tau <= 0 or not window or None in window:
        return None
    spans = (window[1] - window[0]) / tau
    return spans if spans < MIN_CORRELATION_TIMES else None


def summarize(
    series: dict,
    *,
    rim_radius: float,
    wheel_load: float,
    mode: str = "free",
    landed: bool = True,
    min_fraction: float = 0.25,
    grain_radius: float | None = None,
    grouser_count: int = 0,
    ramped: bool = False,
) -> dict:
    """Steady-state metrics of one wheel from written series (cosim.output.read_series keys:
    time, phase, linear_velocity, angular_velocity, slip, sinkage, sinkage_tips, drawbar_pull,
    driving_torque, normal_force, travel, contact_count; per-wheel arrays (S, W)), wheel 0.

    Returns {'steady_state': status, 'window': [t0, t1] [s], and over the window: 'slip' [-],
    'sinkage', 'sinkage_tips' [m], 'drawbar_pull' [N], 'dp_over_w' [-], 'driving_torque' [N m],
    'normal_force' [N], 'forward_speed' [m/s], 'contact_fraction' [-], with '<name>_sem'
    (batch-means standard error within the window) and '<name>_correlation_time' [s] (a window of
    fewer than MIN_CORRELATION_TIMES of them makes the _sem too small); 'dp_over_w_sem'; 'sinkage_rate'
    [m/s] (slope of the sinkage over the window); 'grouser_passages' [-] (grousers that passed over the
    window: the rim's turn x grouser_count / 2 pi); 'travel' [m] over the drive, 'landing_time' [s],
    'landing_sinkage' [m] (the rim's sinkage as the drive starts: the wheel's static sinkage under its
    load), 'deepest_sinkage' [m] (the rim's deepest over the landing and the drive: what a run without a
    window reached)}.

    The window is `drive_window`'s, as a rover's: the traction's MSER-5 start (forward speed, or drawbar
    pull at an imposed slip), moved on to the sinkage's over the rest where it has one. The sinkage must be
    steady over the window as well: stationary by MSER-5, or drifting by less than half of `grain_radius`
    [m] over it, and finite over the drive; else 'still sinking' (or 'still rising'). A grousered wheel
    (grouser_count > 0) must pass at least one grouser over it; else 'too short'.
    ramped: the drawbar load grows over the drive (testbed.drawbar_ramp): 'ramped load' unless airborne or
    stuck (its window means are of a load and a slip still changing, and a longer drive only climbs on).
    """
    time = np.asarray(series["time"], dtype=float)
    phase = np.asarray(series["phase"])
    contacts = np.asarray(series["contact_count"])[:, 0]
    out: dict = {"steady_state": STEADY, "window": [math.nan, math.nan]}
    driving = phase == PHASE_DRIVING
    out["landing_time"] = float(time[np.argmax(driving)] - time[0]) if driving.any() else math.nan
    if len(time) == 0 or not np.any(contacts > 0):
        out["steady_state"] = NEVER_TOUCHED
        return out
    out["deepest_sinkage"] = _deepest(np.asarray(series["sinkage"])[:, 0])
    if not landed or not driving.any():
        out["steady_state"] = NO_LANDING
        return out
    index = np.flatnonzero(driving)
    forward = forward_speed(series)[index]
    spin = np.asarray(series["angular_velocity"])[index, 0, 1]
    sinkage = np.asarray(series["sinkage"])[index, 0]
    pull = np.asarray(series["drawbar_pull"])[index, 0]
    out["travel"] = float(np.asarray(series["travel"])[index[-1], 0])
    if index[0] > 0:  # the last landing sample; none when the run started landed
        out["landing_sinkage"] = float(np.asarray(series["sinkage"])[index[0] - 1, 0])
    key = pull if mode == "slip" else forward
    start, found = drive_window(key, sinkage, min_fraction)
    window = index[start:] if found else index[len(index) // 2 :]
    out["window"] = [float(time[window[0]]), float(time[window[-1]])]
    # the sinkage over the window: stationary, or drifting by less than half a grain radius
    window_time = time[window]
    settled, out["sinkage_rate"] = sinkage_steady(sinkage[window - index[0]], window_time, min_fraction, grain_radius)
    if not np.all(np.isfinite(sinkage)):  # a nan or an inf before the window too: no steady state
        settled, out["sinkage_rate"] = False, math.nan
    quantities = {
        "forward_speed": forward[window - index[0]],
        "sinkage": sinkage[window - index[0]],
        "sinkage_tips": np.asarray(series["sinkage_tips"])[window, 0],
        "drawbar_pull": pull[window - index[0]],
        "driving_torque": np.asarray(series["driving_torque"])[window, 0],
        "normal_force": np.asarray(series["normal_force"])[window, 0],
    }
    spacing = float(np.mean(np.diff(window_time))) if len(window) > 1 else math.nan
    for name, values in quantities.items():
        window_mean(out, name, values, spacing)
    mean_spin = float(np.mean(spin[window - index[0]]))
    out["slip"] = float(slip_of(out["forward_speed"], mean_spin, rim_radius))
    out["dp_over_w"] = out["drawbar_pull"] / wheel_load if wheel_load > 0 else math.nan
    out["dp_over_w_sem"] = out["drawbar_pull_sem"] / wheel_load if wheel_load > 0 else math.nan
    out["dp_over_w_correlation_time"] = out["drawbar_pull_correlation_time"]  # the pull's, over a constant load
    # over the window's own steps, its first one's too (as a rover's)
    span = time[window[-1]] - (time[window[0] - 1] if window[0] > 0 else time[window[0]])
    passed = grouser_passages(abs(mean_spin) * span, grouser_count)
    if grouser_count > 0:
        out["grouser_passages"] = passed
    out["contact_fraction"] = float(np.mean(contacts[window] > 0))
    if out["contact_fraction"] < 0.9:
        out["steady_state"] = AIRBORNE
    elif mode == "free" and abs(mean_spin) * rim_radius > 0 and out["forward_speed"] < 0.01 * mean_spin * rim_radius:
        out["steady_state"] = STUCK
    elif ramped:  # no steady state by design: neither too short nor still sinking (a longer drive climbs on)
        out["steady_state"] = RAMPED
    elif not found or not passed >= 1.0:  # a nan spin passes no judged grouser either
        out["steady_state"] = TOO_SHORT
    elif not settled:
        out["steady_state"] = RISING if out["sinkage_rate"] < 0 else SINKING
    return out


def grouser_passages(turn: float, grouser_count: int) -> float:
    """Grousers that pass a point of the soil as the rim turns by `turn` [rad] (inf for a wheel without
    grousers: nothing periodic to average over)."""
    return turn * grouser_count / (2.0 * math.pi) if grouser_count > 0 else math.inf


def _deepest(sinkage: np.ndarray) -> float:
    """The deepest finite value of a sinkage series [m] (nan when none is finite)."""
    finite = sinkage[np.isfinite(sinkage)]
    return float(finite.max()) if len(finite) else math.nan


def forward_speed(series: dict) -> np.ndarray:
    """Hub speed along the wheel's forward direction [m/s], shape (S,), wheel 0."""
    orientation = np.asarray(series["orientation"])[:, 0]
    velocity = np.asarray(series["linear_velocity"])[:, 0]
    speeds = np.empty(len(orientation))
    for i, (q, v) in enumerate(zip(orientation, velocity)):
        speeds[i] = v @ wheel_frame(q, (0.0, 1.0, 0.0))[1]
    return speeds


# ------------------------------------------------------------------------------------
# rovers

ROVER_UNITS = {"forward_speed": "m/s", "slip": "1", "net_traction": "N", "power": "W", "travel": "m"}
"""Units of the rover quantities (per macro step)."""


SUMMARY_UNITS = {
    **WHEEL_UNITS,
    **ROVER_UNITS,
    "window": "s",
    "landing_time": "s",
    "landing_sinkage": "m",
    "sinkage_rate": "m/s",
    "deepest_sinkage": "m",
    "wheel_deepest_sinkage": "m",
    "grouser_passages": "1",
    "dp_over_w": "1",
    "contact_fraction": "1",
    "displacement": "m",
    "energy": "J",
    "energy_per_metre": "J/m",
    "net_traction_over_weight": "1",
    "stuck": "1",
    "stalled": "1",
    "time_immobile": "s",
    "wheel_slip": "1",
    "wheel_sinkage": "m",
    "wheel_sinkage_tips": "m",
    "wheel_drawbar_pull": "N",
    "wheel_driving_torque": "N m",
    "wheel_normal_force": "N",
    "wheel_power": "W",
    "wheel_contact_fraction": "1",
    "wheel_spin": "rad/s",
    "patch_moves": "count",
    "soil_mass": "kg",
    "soil_mass_initial": "kg",
    "soil_mass_added": "kg",
    "soil_mass_removed": "kg",
    "particle_count_max": "count",
    "simulated_time": "s",
    "last_good_time": "s",
    "diverged_elsewhere": "1",
    "macro_steps": "count",
    "wall_time": "s",
    "particle_count": "count",
    "dt": "s",
    "dem_steps": "count",
    "dem_steps_rejected": "count",
    "dem_steps_forced": "count",
    "force_evaluations": "count",
    "dt_min": "s",
    "dt_mean": "s",
    "dt_max": "s",
    "macro_step": "s",
    "froude_number": "1",
    "coupling_energy_created": "J",
    "coupling_energy_exchanged": "J",
    "coupling_energy_over_tolerance": "1",
    "particle_steps_per_second": "1/s",
    "summary_rule": "1",
}
"""The unit of each number a run's summary may hold (a `_sem` value: its quantity's, a
`_correlation_time`: s; "1": dimensionless, "count"); its words (steady_state, validity, step_control,
stuck_criterion, findings) have none."""


def summary_units(summary: dict) -> dict[str, str]:
    """The unit of each number (or list of numbers) in `summary`: what run.json and results.h5 write beside it."""
    units = {}
    for key, value in summary.items():
        if isinstance(value, (str, dict)) or (isinstance(value, list) and value and isinstance(value[0], dict)):
            continue  # words and findings
        base = key.removesuffix("_sem")
        if key.endswith("_correlation_time"):
            units[key] = "s"
        elif base in SUMMARY_UNITS:
            units[key] = SUMMARY_UNITS[base]
    return units


def rover_forward(orientation: np.ndarray) -> np.ndarray:
    """The rover's forward direction: its body +x axis in the horizontal plane, unit [-], shape (3,)."""
    x_axis = np.asarray(quaternion_to_matrix(orientation))[:, 0]
    horizontal = np.array([x_axis[0], x_axis[1], 0.0])
    norm = np.linalg.norm(horizontal)
    return horizontal / norm if norm > 1e-9 else np.zeros(3)


def rover_quantities(
    body: WheelKinematics,
    wheels: list[dict],
    wrenches: list[WheelWrench],
    rim_radii,
    spins,
    previous_position: np.ndarray | None,
    previous_travel: float,
) -> dict:
    """The rover quantities of the module docstring at one macro step (units: ROVER_UNITS).

    wheels: wheel_quantities of each wheel; spins: each wheel's spin about its axle [rad/s];
    previous_position: the body position at the previous record [m] (None: the drive has not
    started, travel stays 0); previous_travel [m]."""
    forward = rover_forward(body.orientation)
    speed = float(body.linear_velocity @ forward)
    travel = previous_travel
    if previous_position is not None:
        step = body.position - previous_position
        travel += float(np.hypot(step[0], step[1]))
    return {
        "forward_speed": speed,
        "slip": rover_slip(speed, spins, rim_radii),
        "net_traction": float(sum(w.force @ forward for w in wrenches)),
        "power": float(sum(q["power"] for q in wheels)),
        "travel": travel,
    }


def immobile_steps(
    time: np.ndarray,
    position: np.ndarray,
    orientation: np.ndarray,
    spin: np.ndarray,
    rim_radius: np.ndarray,
    stuck_slip: float,
) -> np.ndarray:
    """The stuck criterion (module docstring) at every record of a drive: bool, shape (S,).

    time [s] (S,); position: body positions [m] (S, 3); orientation: body quaternions (S, 4);
    spin: the wheels' spins about their axles [rad/s] (S, W); rim_radius [m] (W,). A record
    whose window reaches back before the first one is judged over what there is (at least one
    macro step)."""
    time = np.asarray(time, dtype=float)
    n = len(time)
    out = np.zeros(n, dtype=bool)
    if n < 2:
        return out
    spin = np.nan_to_num(np.asarray(spin, dtype=float), nan=0.0)  # a nan spin (a lost wheel): not turning
    rim = spin * np.asarray(rim_radius, dtype=float)
    dt = np.diff(time, prepend=time[0])
    rim_travel = np.cumsum(np.mean(rim, axis=1) * dt)  # signed: a drive in reverse travels backwards
    rim_path = np.cumsum(np.mean(np.abs(rim), axis=1) * dt)
    turned = np.cumsum(np.mean(np.abs(spin), axis=1) * dt)  # mean wheel turn since the first record [rad]
    for k in range(1, n):
        if turned[k] < 1.0:  # not yet a radian of turn to judge over
            continue
        start = min(int(np.searchsorted(turned, turned[k] - 1.0, side="right")) - 1, k - 1)
        travel, path = rim_travel[k] - rim_travel[start], rim_path[k] - rim_path[start]
        if not abs(travel) >= TURNING_IN_PLACE * path:  # the wheels turned against each other: no drive to judge
            continue
        advance = float((np.asarray(position[k]) - np.asarray(position[start])) @ rover_forward(orientation[k]))
        # along the wheels' travel (backwards in reverse); a body position that is not finite: not judged
        out[k] = bool(advance * math.copysign(1.0, travel) <= (1.0 - stuck_slip) * abs(travel))
    return out


def drive_stalled(commands, spins, rim_radii, dt, displacement, forward, grain_radius: float | None) -> bool:
    """Whether a drive stalled over a window (module docstring): it commands the wheels (a speed or a
    torque whose mean magnitude over the window is not 0 on some wheel: the driven wheels), yet they do
    not turn with it (their mean turn along their commands' sense, taken step by step, is under half
    their mean gross turn while commanded: still, jittering about their axles, or turned backwards; a
    free wheel rolling along is no sign of a stall), their rims advanced (each its turn along its commands
    times its rim radius, the mean over the driven wheels) less than one grain diameter (2
    `grain_radius` [m]), and the body advanced less than that along the drive (its forward direction in
    the commands' overall sense; horizontally either way when they cancel, as in a turn in place): the
    wheels sheared no grain's width of soil, so a slip over the window would be a ratio of noise. Wheels
    that turn with their commands, however slowly (a short window), or reverse as they do, have not
    stalled.

    commands: the speed [rad/s] and torque [N m] commands over the window, each (S, W), nan where the
    other kind was commanded (or None: not recorded, not judged); spins [rad/s] (S, W); rim_radii [m]
    (W,); dt [s] (S,); displacement: the body's over the window [m] (3,); forward: the rover's forward
    direction, unit (3,). Not judged without a grain radius, over no elapsed time, or where a spin or the
    displacement is not finite (a lost wheel or body)."""
    spins = np.asarray(spins, dtype=float)
    moved = np.asarray(displacement, dtype=float)
    dt = np.asarray(dt, dtype=float)
    if grain_radius is None or any(c is None for c in commands) or not np.sum(dt) > 0:  # nothing seen
        return False
    if not (np.all(np.isfinite(spins)) and np.all(np.isfinite(moved))):
        return False
    speed, torque = (np.nan_to_num(np.asarray(c, dtype=float), nan=0.0) for c in commands)
    driven = (np.mean(np.abs(speed), axis=0) > 0) | (np.mean(np.abs(torque), axis=0) > 0)  # (W,)
    if not np.any(driven):
        return False
    sense = np.sign(speed + torque)  # each step's command sense per wheel (one kind is 0 there)
    # over the driven wheels, at the steps they are commanded: a free wheel rolls along, no sign of a stall
    along = ((spins * sense).T @ dt)[driven]  # each wheel's turn along its commands [rad]
    gross = ((np.abs(spins) * (sense != 0)).T @ dt)[driven]
    turning = bool(np.mean(gross) > 0 and np.mean(along) >= 0.5 * np.mean(gross))
    diameter = 2.0 * grain_radius
    rim_advance = float(np.mean(np.clip(along, 0.0, None) * np.asarray(rim_radii, dtype=float)[driven]))
    drive = np.sign(np.sum(sense.T @ dt))  # the commands' overall sense: forwards, backwards, or a turn in place
    advance = drive * float(moved @ np.asarray(forward, dtype=float)) if drive else float(np.linalg.norm(moved[:2]))
    return bool(not turning and rim_advance < diameter and advance < diameter)


def summarize_rover(
    series: dict,
    *,
    rim_radii,
    weight: float,
    stuck_slip: float = 0.9,
    landed: bool = True,
    min_fraction: float = 0.25,
    grain_radius: float | None = None,
    grouser_counts=None,
) -> dict:
    """Metrics of a rover run from its written series (cosim.output.read_series: the wheel series (S, W),
    'rover/...' series (S, ...)); over the driving phase only.

    Returns {'steady_state', 'window' [s], 'landing_time' [s]; over the window: 'slip' [-] (the rover's;
    nan, as each 'wheel_slip', where the drive held the wheels still or their mean spin is lost in its
    scatter: wheels_held, spin_unresolved),
    'forward_speed' [m/s], 'net_traction' [N], 'net_traction_over_weight' [-], 'power' [W], 'sinkage',
    'sinkage_tips' [m] (mean over the wheels), 'drawbar_pull' [N] (= net_traction), 'dp_over_w' [-],
    'driving_torque' [N m] (summed), 'normal_force' [N] (summed), 'contact_fraction' [-], and per wheel
    lists 'wheel_slip', 'wheel_sinkage', 'wheel_drawbar_pull', 'wheel_driving_torque', 'wheel_normal_force',
    'wheel_power', 'wheel_contact_fraction', 'wheel_spin' [rad/s] (|omega| about the axle: the validity's
    Froude number where the drive sets the speeds as it goes); over the drive: 'travel' [m] (path), 'displacement' [m],
    'energy' [J], 'energy_per_metre' [J/m], 'time_immobile' [s], 'stuck' (bool), 'stalled' (bool: the
    drive stalled, drive_stalled), 'stuck_criterion' (text), 'grouser_passages' [-] (the fewest grousers a
    grousered wheel passed over the window, among the wheels that turned a tenth of the most-turned one's
    turn at least: `grouser_counts`, one per wheel, 0 for a smooth one),
    'wheel_deepest_sinkage' [m] (each rim's deepest over the landing and the drive), and the `_sem` of
    'net_traction_over_weight' and 'dp_over_w'}.

    Statuses as `summarize`'s, for the rover: 'stuck' (immobile at the end, a slip of at least
    stuck_slip over the window, or a stalled drive), 'airborne' (at least min(3, wheels) wheels touch
    the soil in fewer than 90 % of the window's macro steps: the stance lost, not one wheel lifted),
    'too short' (also fewer than one grouser passage over the window), 'still sinking' (a wheel's sinkage
    neither stationary nor drifting by less than half of `grain_radius` [m] over the window; 'still rising'
    when every such wheel drifts upwards)."""
    time = np.asarray(series["time"], dtype=float)
    phase = np.asarray(series["phase"])
    contacts = np.asarray(series["contact_count"])
    driving = phase == PHASE_DRIVING
    out: dict = {
        "steady_state": STEADY,
        "window": [math.nan, math.nan],
        "stuck_criterion": f"immobile while the body advances less than {1 - stuck_slip:.3g} x the wheels' "
        "rim travel over the last radian of wheel turn; stuck when immobile at the end, when the slip over "
        f"the steady window is at least {stuck_slip:.3g}, or when the drive stalled: commanded, its "
        "wheels did not turn with it, and they and its body advanced less than one grain diameter over the "
        "window",
    }
    out["landing_time"] = float(time[np.argmax(driving)] - time[0]) if driving.any() else math.nan
    if len(time) == 0 or not np.any(contacts > 0):
        out["steady_state"] = NEVER_TOUCHED
        return out
    out["wheel_deepest_sinkage"] = [_deepest(column) for column in np.asarray(series["sinkage"]).T]
    if not landed or not driving.any():
        out["steady_state"] = NO_LANDING
        return out
    index = np.flatnonzero(driving)
    rim_radii = np.asarray(rim_radii, dtype=float)
    position = np.asarray(series["rover_position"])[index]
    orientation = np.asarray(series["rover_orientation"])[index]
    speed = np.asarray(series["rover_forward_speed"])[index]
    power = np.asarray(series["rover_power"])[index]
    sinkage = np.asarray(series["sinkage"])[index]
    spins = np.array(
        [
            [v @ wheel_frame(q, (0.0, 1.0, 0.0))[0] for q, v in zip(qs, ws)]
            for qs, ws in zip(np.asarray(series["orientation"])[index], np.asarray(series["angular_velocity"])[index])
        ]
    )
    times = time[index]
    dt = np.diff(np.r_[time[index[0] - 1] if index[0] > 0 else times[0], times])
    out["travel"] = float(np.asarray(series["rover_travel"])[index[-1]])
    # from where the drive started: the last landing record (the travel counts the first step too)
    origin = np.asarray(series["rover_position"])[index[0] - 1] if index[0] > 0 else position[0]
    out["displacement"] = float(np.linalg.norm((position[-1] - origin)[:2]))
    out["energy"] = float(np.sum(power * dt))
    if out["travel"] > 0:
        out["energy_per_metre"] = out["energy"] / out["travel"]
    else:  # no travel: the energy's sign, or nothing spent
        out["energy_per_metre"] = math.copysign(math.inf, out["energy"]) if out["energy"] != 0 else math.nan
    immobile = immobile_steps(times, position, orientation, spins, rim_radii, stuck_slip)
    out["time_immobile"] = float(np.sum(dt[immobile]))
    out["stuck"] = bool(immobile[-1])
    start, found = drive_window(speed, sinkage.mean(axis=1), min_fraction)
    window = np.arange(start, len(index)) if found else np.arange(len(index) // 2, len(index))
    rows = index[window]
    out["window"] = [float(time[rows[0]]), float(time[rows[-1]])]
    spacing = float(np.mean(np.diff(time[rows]))) if len(rows) > 1 else math.nan
    window_mean(out, "forward_speed", speed[window], spacing)
    mean_spins = np.mean(spins[window], axis=0)
    out["slip"] = rover_slip(out["forward_speed"], mean_spins, rim_radii)
    # a file without the commands (written before they were recorded): no wheel is taken as held
    held = wheels_held(series["speed_command"][rows]) if "speed_command" in series else np.zeros(len(rim_radii), bool)
    noise = spin_unresolved(spins[window])  # (W,)
    if np.all(held) or spin_unresolved((spins[window] * rim_radii).mean(axis=1, keepdims=True))[0]:
        out["slip"] = math.nan  # parked, braked, or the wheels' mean rim speed lost in its own scatter
    traction = np.asarray(series["rover_net_traction"])[rows]
    window_mean(out, "net_traction", traction, spacing)
    out["net_traction_over_weight"] = out["net_traction"] / weight if weight > 0 else math.nan
    out["net_traction_over_weight_sem"] = out["net_traction_sem"] / weight if weight > 0 else math.nan
    out["net_traction_over_weight_correlation_time"] = out["net_traction_correlation_time"]
    out["power"] = float(np.mean(power[window]))
    for name in ("sinkage", "sinkage_tips", "drawbar_pull", "driving_torque", "normal_force", "power"):
        values = np.asarray(series[name])[rows]
        out[f"wheel_{name}"] = [float(v) for v in values.mean(axis=0)]
    wheel_speed = np.array(
        [
            [v @ wheel_frame(q, (0.0, 1.0, 0.0))[1] for q, v in zip(qs, vs)]
            for qs, vs in zip(np.asarray(series["orientation"])[rows], np.asarray(series["linear_velocity"])[rows])
        ]
    )
    out["wheel_slip"] = [
        math.nan if held[i] or noise[i] else float(slip_of(np.mean(wheel_speed[:, i]), mean_spins[i], rim_radii[i]))
        for i in range(len(rim_radii))
    ]
    out["wheel_spin"] = [float(np.mean(np.abs(spins[window, i]))) for i in range(len(rim_radii))]
    window_mean(out, "sinkage", np.asarray(series["sinkage"])[rows].mean(axis=1), spacing)
    out["sinkage_tips"] = float(np.mean(out["wheel_sinkage_tips"]))
    out["drawbar_pull"] = out["net_traction"]
    out["dp_over_w"] = out["net_traction_over_weight"]
    out["dp_over_w_sem"] = out["net_traction_over_weight_sem"]
    out["dp_over_w_correlation_time"] = out["net_traction_correlation_time"]
    counts = [0] * len(rim_radii) if grouser_counts is None else [int(c) for c in grouser_counts]
    if len(counts) != len(rim_radii):
        raise ValueError(f"grouser_counts: one per wheel ({len(rim_radii)}), got {len(counts)}")
    turns = np.abs(np.sum(spins[window] * dt[window, None], axis=0))  # each rim's turn over the window [rad]
    # a wheel held still (a brake, one side stopped) passes no grousers and forces nothing periodic
    most = float(np.max(turns)) if len(turns) else 0.0  # nan when a spin is (a lost wheel): judged too short
    turning = turns >= 0.1 * most if most > 0 else np.zeros(len(turns), bool)
    passed = (
        min((grouser_passages(float(t), c) for t, c, on in zip(turns, counts, turning) if on), default=math.inf)
        if math.isfinite(most) or not any(counts)
        else math.nan
    )
    if any(counts):
        out["grouser_passages"] = passed
    out["driving_torque"] = float(np.sum(out["wheel_driving_torque"]))
    out["normal_force"] = float(np.sum(out["wheel_normal_force"]))
    touching = contacts[rows] > 0
    out["wheel_contact_fraction"] = [float(v) for v in np.mean(touching, axis=0)]
    stance = min(3, touching.shape[1])  # three wheels hold a rover up; one lifted wheel is no flight
    out["contact_fraction"] = float(np.mean(np.sum(touching, axis=1) >= stance))
    # a slip of stuck_slip or more over the window is the stuck criterion's own (wheels that slowed after
    # the rover stopped made its last radian of turn reach back to when it moved)
    out["stuck"] = out["stuck"] or bool(out["slip"] >= stuck_slip)
    commands = tuple(np.asarray(series[key])[rows] if key in series else None for key in DRIVE_COMMANDS)
    before = position[window[0] - 1] if window[0] > 0 else origin  # where the window's first step started
    out["stalled"] = drive_stalled(
        commands,
        spins[window],
        rim_radii,
        dt[window],
        position[window[-1]] - before,
        rover_forward(orientation[window[-1]]),
        grain_radius,
    )
    out["stuck"] = out["stuck"] or out["stalled"]
    drifts = [  # a nan or an inf before the window too: no steady state
        sinkage_steady(sinkage[window, w], times[window], min_fraction, grain_radius)
        if np.all(np.isfinite(sinkage[:, w]))
        else (False, math.nan)
        for w in range(sinkage.shape[1])
    ]
    settled = [steady for steady, _ in drifts]
    rising = all(rate < 0 for steady, rate in drifts if not steady)
    if out["stuck"]:
        out["steady_state"] = STUCK
    elif out["contact_fraction"] < 0.9:
        out["steady_state"] = AIRBORNE
    elif not found or not passed >= 1.0:
        out["steady_state"] = TOO_SHORT
    elif not all(settled):
        out["steady_state"] = RISING if rising else SINKING
    return out


# ------------------------------------------------------------------------------------
# replicas


REPLICA_METRICS = (
    "slip",
    "sinkage",
    "landing_sinkage",
    "sinkage_tips",
    "drawbar_pull",
    "dp_over_w",
    "driving_torque",
    "travel",
    "forward_speed",
)
"""Metrics an ensemble reports (a rover's summary has them too: rover-level values)."""


def ensemble(values, relative_tolerance: float = 0.05, absolute_tolerance: float = 0.0) -> dict:
    """Replica statistics of one metric: n, mean, std (ddof 1), ci95 (half-width of the 95 %
    Student-t interval of the mean), min, max, and 'deterministic': the replica std is within
    max(relative_tolerance |mean|, absolute_tolerance), i.e. the summation order does not
    change the macroscopic result by more than that (None for one replica: no scatter to judge)."""
    from scipy import stats

    values = np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=float)
    n = len(values)
    if n == 0:
        return {"n": 0}
    mean = float(np.mean(values))
    std = float(np.std(values, ddof=1)) if n > 1 else math.nan
    ci95 = float(stats.t.ppf(0.975, n - 1) * std / math.sqrt(n)) if n > 1 else math.nan
    tolerance = max(relative_tolerance * abs(mean), absolute_tolerance)
    return {
        "n": n,
        "mean": mean,
        "std": std,
        "ci95": ci95,
        "min": float(values.min()),
        "max": float(values.max()),
        "tolerance": tolerance,
        "deterministic": bool(std <= tolerance) if n > 1 else None,  # one replica: no scatter to judge
    }
