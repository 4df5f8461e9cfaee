"""The terramechanics definitions, the steady-state window and the replica statistics on cases with
known answers (synthetic series with a known transient, samples with a known variance)."""

import math

import numpy as np
import pytest

from cosim import metrics
from cosim.contract import WheelKinematics, WheelWrench


def test_definitions_on_a_wheel_turned_about_its_axle():
    """A wheel tilted 90 deg about its axle (Y): its forward direction stays +X, the definitions do not move."""
    geometry = metrics.WheelGeometry(rim_radius=0.04, outer_radius=0.045, surface_height=0.1)
    half = math.pi / 4
    k = WheelKinematics(
        [0.3, 0.0, 0.13], [math.cos(half), 0.0, math.sin(half), 0.0], [0.006, 0.0, 0.0], [0.0, 0.25, 0.0]
    )
    w = WheelWrench(force=[1.5, 0.2, 30.0], torque=[0.0, -0.8, 0.0])
    q = metrics.wheel_quantities(k, w, geometry, drive_start_position=np.array([0.25, 0.0, 0.13]))
    assert q["travel"] == pytest.approx(0.05)
    assert q["slip"] == pytest.approx(1 - 0.006 / (0.25 * 0.04))  # 0.4
    assert q["sinkage"] == pytest.approx(0.1 - (0.13 - 0.04))
    assert q["sinkage_tips"] == pytest.approx(0.1 - (0.13 - 0.045))
    assert q["drawbar_pull"] == pytest.approx(1.5) and q["normal_force"] == pytest.approx(30.0)
    assert q["driving_torque"] == pytest.approx(0.8)
    assert math.isnan(metrics.slip_of(0.01, 0.0, 0.04))  # a wheel that does not turn has no slip


def _transient(n, tau, amplitude, sigma, seed):
    rng = np.random.default_rng(seed)
    return amplitude * np.exp(-np.arange(n) / tau) + sigma * rng.standard_normal(n)


@pytest.mark.parametrize("seed", range(5))
def test_mser_removes_the_transient_bias(seed):
    """x = A exp(-k / tau) + noise, steady value 0: the mean after the MSER-5 truncation is unbiased
    (within 3 standard errors of 0), the mean of everything is not."""
    x = _transient(600, tau=40.0, amplitude=5.0, sigma=0.5, seed=seed)
    cut = metrics.mser_truncation(x)
    assert cut is not None and 40 <= cut <= 300
    rest = x[cut:]
    assert abs(rest.mean()) < 3 * 0.5 / math.sqrt(len(rest))
    assert abs(x.mean()) > 3 * 0.5 / math.sqrt(len(x))


def test_mser_finds_no_steady_state_in_a_drift():
    x = np.linspace(0.0, 1.0, 400) + 0.01 * np.random.default_rng(0).standard_normal(400)
    assert metrics.mser_truncation(x) is None


def _series(n_landing=60, n_drive=400, v_ss=0.006, omega=0.25, r=0.04, contacts=5, seed=0):
    """Records of a single wheel: it lands (not turning), then its speed and sinkage approach steady values."""
    rng = np.random.default_rng(seed)
    n = n_landing + n_drive
    time = 0.05 * np.arange(1, n + 1)
    phase = np.r_[np.zeros(n_landing, int), np.ones(n_drive, int)]
    k = np.arange(n_drive)
    v = np.r_[np.zeros(n_landing), v_ss * (1 - np.exp(-k / 30.0)) + 2e-4 * rng.standard_normal(n_drive)]
    sink = np.r_[
        np.full(n_landing, 0.004), 0.004 + 0.003 * (1 - np.exp(-k / 30.0)) + 1e-4 * rng.standard_normal(n_drive)
    ]
    spin = np.r_[np.zeros(n_landing), np.full(n_drive, omega)]
    velocity = np.zeros((n, 1, 3))
    velocity[:, 0, 0] = v
    angular = np.zeros((n, 1, 3))
    angular[:, 0, 1] = spin
    orientation = np.zeros((n, 1, 4))
    orientation[:, 0, 0] = 1.0
    travel = np.r_[np.zeros(n_landing), np.cumsum(v[n_landing:]) * 0.05][:, None]
    pull = 0.5 + 0.01 * rng.standard_normal(n)
    return {
        "time": time,
        "phase": phase,
        "linear_velocity": velocity,
        "angular_velocity": angular,
        "orientation": orientation,
        "sinkage": sink[:, None],
        "sinkage_tips": sink[:, None] + 0.004,
        "drawbar_pull": pull[:, None],
        "driving_torque": np.full((n, 1), 0.1),
        "normal_force": np.full((n, 1), 10.0),
        "travel": travel,
        "contact_count": np.full((n, 1), contacts),
    }


def test_landing_then_a_steady_state_window_with_its_metrics():
    s = _series()
    out = metrics.summarize(s, rim_radius=0.04, wheel_load=10.0)
    assert out["steady_state"] == metrics.STEADY
    assert out["landing_time"] == pytest.approx(60 * 0.05)  # 60 landing steps of 0.05 s
    drive_start = s["time"][60]
    assert out["window"][0] >= drive_start + 3 * 30 * 0.05 * 0.5  # past most of the speed transient
    assert out["slip"] == pytest.approx(1 - 0.006 / (0.25 * 0.04), abs=0.01)  # 0.4
    assert out["sinkage"] == pytest.approx(0.007, abs=2e-4)
    assert out["sinkage_tips"] == pytest.approx(0.011, abs=2e-4)
    assert out["dp_over_w"] == pytest.approx(0.05, abs=0.005) and out["contact_fraction"] == 1.0


def test_the_window_starts_once_the_sinkage_has_settled_too():
    """At an imposed slip the pull may be steady from the drive's start while the wheel still sinks (the
    main job: the pull steady from 5.7 s, the sinkage from 11.4 s). A window from the pull's start alone
    mixes the settling into the mean (8.16 against the plateau's 8.79 mm there): the window moves on from
    the traction's MSER-5 start to the sinkage's over the rest (metrics.drive_window, as a rover's), and its
    mean sinkage is the plateau's."""
    s = _series()  # the pull steady throughout; the sinkage rises to 7 mm with a time constant of 30 samples
    out = metrics.summarize(s, rim_radius=0.04, wheel_load=10.0, mode="slip")
    drive = s["time"][60:]
    cut = metrics.mser_truncation(s["sinkage"][60:, 0])
    assert cut is not None and cut >= 30  # the sinkage's own start: past one time constant of its settling
    assert metrics.mser_truncation(s["drawbar_pull"][60:, 0]) == 0  # the pull's: the drive's start
    assert out["steady_state"] == metrics.STEADY and out["window"][0] == drive[cut]
    assert out["sinkage"] == pytest.approx(0.007, abs=1e-4)  # the plateau (the whole drive's mean: 6.8 mm)
    assert np.mean(s["sinkage"][60:, 0]) < 0.007 - 1.5e-4
    assert out["dp_over_w"] == pytest.approx(0.05, abs=0.002)
    # the pull ramps over the first 100 samples and the sinkage settles slowly (80 samples): over the whole
    # drive MSER-5 finds no start for the sinkage (past half of it), over the rest after the pull's it does
    late = _series()
    late["drawbar_pull"][60:160, 0] = np.linspace(0.0, 0.5, 100)
    late["sinkage"][60:, 0] = 0.004 + 0.003 * (1 - np.exp(-np.arange(400) / 80.0))
    late["sinkage"][60:, 0] += 1e-4 * np.random.default_rng(3).standard_normal(400)
    pull_cut = metrics.mser_truncation(late["drawbar_pull"][60:, 0])
    assert pull_cut >= 100 and metrics.mser_truncation(late["sinkage"][60:, 0]) is None
    rest_cut = metrics.mser_truncation(late["sinkage"][60 + pull_cut :, 0])
    assert rest_cut >= 80
    out = metrics.summarize(late, rim_radius=0.04, wheel_load=10.0, mode="slip", grain_radius=1e-3)
    assert out["steady_state"] == metrics.STEADY and out["window"][0] == drive[pull_cut + rest_cut]
    assert out["sinkage"] > np.mean(late["sinkage"][60 + pull_cut :, 0]) + 1e-4  # not the settling's mean
    # free mode: the speed settles with a time constant of 30 samples, the sinkage with 60
    free = _series()
    free["sinkage"][60:, 0] = 0.004 + 0.003 * (1 - np.exp(-np.arange(400) / 60.0))
    free["sinkage"][60:, 0] += 1e-4 * np.random.default_rng(4).standard_normal(400)
    speed_cut = metrics.mser_truncation(free["linear_velocity"][60:, 0, 0])
    rest_cut = metrics.mser_truncation(free["sinkage"][60 + speed_cut :, 0])
    assert rest_cut > 0
    assert metrics.summarize(free, rim_radius=0.04, wheel_load=10.0)["window"][0] == drive[speed_cut + rest_cut]
    # a sinkage that never settles by MSER-5 leaves the traction's window, judged by its drift
    sinking = _series()
    sinking["sinkage"][60:, 0] = 0.004 + np.linspace(0.0, 0.003, 400)
    out = metrics.summarize(sinking, rim_radius=0.04, wheel_load=10.0, mode="slip", grain_radius=1e-3)
    assert out["window"][0] == drive[0] and out["steady_state"] == metrics.SINKING
    # a settling that leaves a window too short for its grousers: 'too short' (drive longer), where the
    # traction's window alone (the whole drive) passes 1.6 grousers of 2 and was called steady
    slow = _series()
    slow["sinkage"][60:, 0] = 0.004 + 0.003 * (1 - np.exp(-np.arange(400) / 50.0))
    slow["sinkage"][60:, 0] += 1e-4 * np.random.default_rng(3).standard_normal(400)
    out = metrics.summarize(slow, rim_radius=0.04, wheel_load=10.0, mode="slip", grouser_count=2)
    assert out["window"][0] == drive[metrics.mser_truncation(slow["sinkage"][60:, 0])] > drive[100]
    assert out["steady_state"] == metrics.TOO_SHORT and out["grouser_passages"] < 1.0
    assert metrics.grouser_passages(0.25 * (drive[-1] - s["time"][59]), 2) > 1.5


def test_runs_without_a_steady_state_say_why():
    assert (
        metrics.summarize(_series(contacts=0), rim_radius=0.04, wheel_load=10.0)["steady_state"]
        == metrics.NEVER_TOUCHED
    )
    hopping = _series()
    hopping["contact_count"][::2] = 0  # in the air half of the time
    assert metrics.summarize(hopping, rim_radius=0.04, wheel_load=10.0)["steady_state"] == metrics.AIRBORNE
    assert metrics.summarize(_series(v_ss=1e-6), rim_radius=0.04, wheel_load=10.0)["steady_state"] == metrics.STUCK
    drifting = _series()
    drifting["sinkage"][60:, 0] = np.linspace(0.004, 0.03, 400)  # digging in without end
    assert (
        metrics.summarize(drifting, rim_radius=0.04, wheel_load=10.0, grain_radius=0.002)["steady_state"]
        == metrics.SINKING
    )
    creeping = _series()  # 0.5 mm over the whole drive: less than half a 2 mm grain radius over the window
    creeping["sinkage"][60:, 0] += np.linspace(0.0, 0.0005, 400)
    steady = metrics.summarize(creeping, rim_radius=0.04, wheel_load=10.0, grain_radius=0.002)
    assert steady["steady_state"] == metrics.STEADY and 0 < steady["sinkage_rate"]
    # a drawbar load ramped over the drive (free mode): MSER cut a noisy climb's start and the run read
    # "steady" at a slip still climbing (a probe's: 0.44 to 0.80 across its window); no steady state by design
    ramp = _series(seed=4)
    ramp["linear_velocity"][60:, 0, 0] = (
        0.006 - np.linspace(0.0, 0.003, 400) + 1e-3 * np.random.default_rng(4).standard_normal(400)
    )
    ramped = metrics.summarize(ramp, rim_radius=0.04, wheel_load=10.0, ramped=True)
    assert metrics.summarize(_series(), rim_radius=0.04, wheel_load=10.0, ramped=True)["steady_state"] == metrics.RAMPED
    assert ramped["steady_state"] == metrics.RAMPED, ramped["steady_state"]  # not "too short": drive longer
    sinking = _series(seed=4)
    sinking["sinkage"][60:, 0] = np.linspace(0.004, 0.03, 400)  # and digging in as the load grows
    assert (
        metrics.summarize(sinking, rim_radius=0.04, wheel_load=10.0, grain_radius=0.002, ramped=True)["steady_state"]
        == metrics.RAMPED
    )
    unsettled = _series()  # the traction itself never settles: the speed keeps rising
    unsettled["linear_velocity"][60:, 0, 0] = np.linspace(0.001, 0.02, 400)
    assert metrics.summarize(unsettled, rim_radius=0.04, wheel_load=10.0)["steady_state"] == metrics.TOO_SHORT
    assert (
        metrics.summarize(_series(), rim_radius=0.04, wheel_load=10.0, landed=False)["steady_state"]
        == metrics.NO_LANDING
    )


def test_the_95_percent_interval_covers_the_mean_95_percent_of_the_time():
    """4000 synthetic ensembles of 5 replicas from N(3, 0.2^2): the Student-t interval covers 3 in
    95 % of them (binomial 3-sigma band: +-1.0 %), and the standard deviation estimates 0.2."""
    rng = np.random.default_rng(1)
    covered, stds = 0, []
    for _ in range(4000):
        stats = metrics.ensemble(rng.normal(3.0, 0.2, 5))
        covered += abs(stats["mean"] - 3.0) <= stats["ci95"]
        stds.append(stats["std"])
    assert covered / 4000 == pytest.approx(0.95, abs=0.01)
    assert np.sqrt(np.mean(np.square(stds))) == pytest.approx(0.2, rel=0.03)  # s^2 is unbiased


def test_deterministic_means_the_scatter_is_within_the_tolerance():
    tight = metrics.ensemble([1.00, 1.01, 0.99, 1.00], relative_tolerance=0.05)
    loose = metrics.ensemble([1.0, 1.3, 0.7, 1.1], relative_tolerance=0.05)
    floor = metrics.ensemble([0.001, -0.002, 0.0], relative_tolerance=0.05, absolute_tolerance=0.02)
    assert tight["deterministic"] and not loose["deterministic"] and floor["deterministic"]
    # one run says nothing about scatter: neither yes nor no (ensemble.csv wrote False, read as "NO")
    assert metrics.ensemble([2.0])["deterministic"] is None
    assert metrics.ensemble([np.nan, None])["n"] == 0


def _ar1(phi: float, n: int, count: int, seed: int) -> np.ndarray:
    """`count` stationary AR(1) series x_k = phi x_(k-1) + e_k, e ~ N(0, 1), of n samples each, mean 0:
    integrated correlation time (1 + phi) / (1 - phi) samples."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((count, n + 2000))  # 2000 samples of burn-in: stationary from the start
    return lfilter([1.0], [1.0, -phi], noise, axis=1)[:, 2000:]


def test_a_nan_or_an_inf_is_no_steady_state():
    """A non-finite sample made every MSER score nan, and the series counted as steady from its start."""
    x = _transient(600, tau=40.0, amplitude=5.0, sigma=0.5, seed=0)
    x[500] = math.nan
    assert metrics.mser_truncation(x) is None and metrics.drive_window(x, np.zeros(600)) == (600, False)
    x[500] = math.inf
    assert metrics.mser_truncation(x) is None
    assert metrics.mser_truncation(np.full(100, math.nan)) is None
    # nor is a wheel's sinkage with one: its drift is not known (a rate of 0 read it as settled)
    s = _series()
    s["sinkage"][400, 0] = math.nan
    out = metrics.summarize(s, rim_radius=0.04, wheel_load=10.0, grain_radius=0.001)
    assert out["steady_state"] == metrics.SINKING and math.isnan(out["sinkage_rate"])
    s = _series()  # before the window too (a sinkage with a nan has no MSER-5 start: the speed's window)
    s["sinkage"][65, 0] = math.nan
    out = metrics.summarize(s, rim_radius=0.04, wheel_load=10.0, grain_radius=0.001)
    assert out["window"][0] > s["time"][65] and out["steady_state"] == metrics.SINKING
    series, radii = _rover([0.06, 0.0, 0.0], 1.0)  # and a rover's
    series["sinkage"][45, 2] = math.nan
    out = _rover_summary(series, radii)
    assert out["window"][0] > series["time"][45] and out["steady_state"] == metrics.SINKING


def test_batch_means_count_every_sample():
    """15 samples in 8 batches (2 x 7 and 1): the last 7 samples were left out (a standard error of 0 for
    a window whose mean is 46.7); batch means 0, 0, 0, 0, 100, 100, 100, 100: s = 53.45, / sqrt(8)."""
    values = np.r_[np.zeros(8), np.full(7, 100.0)]
    assert metrics.batch_standard_error(values) == pytest.approx(math.sqrt(8 * 50.0**2 / 7) / math.sqrt(8))


def test_correlation_time_and_the_coverage_of_the_batch_means_interval_on_ar1_series():
    """AR(1) with phi = 0.9: correlation time (1 + phi) / (1 - phi) = 19 samples. Over 800 windows of
    2000 samples (105 correlation times) the batch-means 95 % interval (t with 7 degrees of freedom)
    covers the true mean 0 in 95 % of them (binomial 3-sigma band +-2.3 %), and few windows are flagged
    short (2 % measured: the estimate of the correlation time scatters). Over windows of 100 samples
    (5 correlation times) the interval covers far less (82 % measured) and `short_window` flags nearly
    every one (its estimate of the correlation time is low there too, but well under 50 windows)."""
    from scipy import stats

    t7 = stats.t.ppf(0.975, 7)
    long = _ar1(0.9, 2000, 800, seed=3)
    assert metrics.correlation_time(_ar1(0.9, 40000, 1, seed=4)[0]) == pytest.approx(19.0, rel=0.15)
    covered = flagged = 0
    for x in long:
        sem = metrics.batch_standard_error(x)
        covered += abs(x.mean()) <= t7 * sem
        summary = {"window": [0.0, (len(x) - 1) * 0.1], "v_correlation_time": metrics.correlation_time(x) * 0.1}
        flagged += metrics.short_window(summary, "v") is not None
    assert covered / len(long) == pytest.approx(0.95, abs=0.023) and flagged / len(long) < 0.05
    short = _ar1(0.9, 100, 800, seed=5)
    covered = flagged = 0
    for x in short:
        covered += abs(x.mean()) <= t7 * metrics.batch_standard_error(x)
        summary = {"window": [0.0, (len(x) - 1) * 0.1], "v_correlation_time": metrics.correlation_time(x) * 0.1}
        flagged += metrics.short_window(summary, "v") is not None
    assert covered / len(short) < 0.9 and flagged / len(short) > 0.95
    assert math.isnan(metrics.correlation_time(np.ones(50)))  # constant: no correlation time, nothing flagged
    assert metrics.short_window({"window": [0.0, 1.0], "v_correlation_time": math.nan}, "v") is None


def test_a_run_summary_prints_a_window_too_short_for_its_error_bar(capsys):
    """The summary of a run whose steady window spans few correlation times of the drawbar pull says its
    within-run standard error is too small (a slowly wandering pull: AR(1) with phi = 0.99)."""
    from types import SimpleNamespace

    from cosim.cli import _print_summary

    s = _series()
    s["drawbar_pull"][:, 0] = 0.5 + 0.01 * _ar1(0.99, len(s["time"]), 1, seed=6)[0]
    out = metrics.summarize(s, rim_radius=0.04, wheel_load=10.0)
    spans = (out["window"][1] - out["window"][0]) / out["drawbar_pull_correlation_time"]
    assert spans < metrics.MIN_CORRELATION_TIMES
    assert metrics.summary_units(out)["drawbar_pull_correlation_time"] == "s"
    _print_summary(SimpleNamespace(summary=out, status="done", out_dir="run"))
    printed = capsys.readouterr().out
    named = f"{spans:.0f} correlation times of drawbar_pull, {spans:.0f} of dp_over_w (< 50)"  # the pull's, per weight
    assert f"! the window spans only {named}" in printed, printed
    # each +- is the 95 % interval, t with 7 degrees of freedom (one s.e. covers the mean 65 % of the time)
    half = 2.3646 * out["dp_over_w_sem"]
    assert f"dp_over_w                  {out['dp_over_w']:.4g} +- {half:.2g} (95 %, within run)" in printed, printed
    assert "their within-run intervals are too narrow" in printed and "of sinkage" not in printed, printed
    # the error bar it points to first is over beds: the sinkage's scatter over orders understates it
    assert out["steady_state"] == metrics.STEADY and "error bars: cosim run SCENE --replicas 5 --vary-bed" in printed
    # a value the drive holds (the carriage's speed at an imposed slip) scatters by its rounding only: the
    # main job printed 'forward_speed 3.24 +- 2.4e-16 (95 %, within run) mm/s'
    held = {**out, "forward_speed": 0.00324, "forward_speed_sem": 1e-19, "forward_speed_correlation_time": 0.1}
    _print_summary(SimpleNamespace(summary=held, status="done", out_dir="run"))
    printed = capsys.readouterr().out
    assert "  forward_speed              3.24 mm/s\n" in printed and "of forward_speed" not in printed, printed
    # a run without a window (never landed) printed 'window nan .. nan s'; run.json's null reads the same
    for window in ([math.nan, math.nan], [None, None]):
        _print_summary(SimpleNamespace(summary={"steady_state": "no landing", "window": window}, status="", out_dir=""))
        assert "  window                     none (no steady state: no landing)\n" in capsys.readouterr().out


def test_an_ensemble_of_one_replica_is_not_judged():
    """One steady replica has no scatter: its row said "NO (std > tol)" beside a nan std."""
    from cosim.study import _ensemble_text

    stats = {"steady": 1, "replicas": 3, "metrics": {"slip": metrics.ensemble([0.21, None, math.nan])}}
    row = _ensemble_text(stats, "replicas").splitlines()[-1]
    assert "n/a (one replica)" in row and "NO" not in row and row.split()[1] == "1"


def _rover(
    velocity, spins, *, yaw=0.0, sinkage=None, contacts=None, power=0.0, torque=None, n_land=40, n_drive=400, seed=0
):
    """Records of a 4-wheel rover (rim radii 0.1 m, macro step 0.05 s): it lands, then drives with body velocity
    `velocity` [m/s] ((3,) or (S, 3), world frame) and wheel spins `spins` [rad/s] (W,) or (S, W) about its axles,
    heading `yaw` [rad] ((S,) or scalar); the rover series made by metrics.rover_quantities as a run makes them.
    The drive commands the spins as speeds, or `torque` [N m] ((W,) or (S, W)) when given."""
    from soil.control import quaternion_to_matrix

    rng = np.random.default_rng(seed)
    n, wheels, dt = n_land + n_drive, 4, 0.05
    radii = np.full(wheels, 0.1)
    time = dt * np.arange(1, n + 1)
    phase = np.r_[np.zeros(n_land, int), np.ones(n_drive, int)]
    velocity = np.array(np.broadcast_to(velocity, (n, 3)), dtype=float)
    spins = np.array(np.broadcast_to(spins, (n, wheels)), dtype=float)
    velocity[:n_land], spins[:n_land] = 0.0, 0.0
    yaw = np.broadcast_to(yaw, (n,))
    orientation = np.array([[math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)] for a in yaw])
    position = np.zeros((n, 3))
    position[:, 2] = 0.3
    for k in range(1, n):
        position[k] = position[k - 1] + velocity[k] * dt
    axle = np.array([np.asarray(quaternion_to_matrix(q))[:, 1] for q in orientation])  # the body's +y in the world
    angular = spins[:, :, None] * axle[:, None, :]
    linear = np.repeat(velocity[:, None, :], wheels, axis=1)
    sinkage = 0.01 + 1e-4 * rng.standard_normal((n, wheels)) if sinkage is None else sinkage
    contacts = np.full((n, wheels), 5) if contacts is None else contacts
    rows, previous, travel = [], None, 0.0
    for k in range(n):
        body = WheelKinematics(position[k], orientation[k], velocity[k], np.zeros(3))
        wrenches = [WheelWrench(force=[0.0, 0.0, 50.0], torque=[0.0, 0.0, 0.0])] * wheels
        row = metrics.rover_quantities(
            body, [{"power": power}] * wheels, wrenches, radii, spins[k], previous if phase[k] else None, travel
        )
        previous, travel = position[k], row["travel"]
        rows.append(row)
    series = {
        "time": time,
        "phase": phase,
        "contact_count": contacts,
        "rover_position": position,
        "rover_orientation": orientation,
        "sinkage": sinkage,
        "sinkage_tips": sinkage + 0.005,
        "drawbar_pull": np.zeros((n, wheels)),
        "driving_torque": np.zeros((n, wheels)),
        "normal_force": np.full((n, wheels), 50.0),
        "power": np.full((n, wheels), power),
        "orientation": np.repeat(orientation[:, None, :], wheels, axis=1),
        "angular_velocity": angular,
        "linear_velocity": linear,
        "speed_command": spins.copy() if torque is None else np.full((n, wheels), np.nan),
        "torque_command": np.full((n, wheels), np.nan) if torque is None else np.broadcast_to(torque, (n, wheels)),
    }
    series.update({f"rover_{name}": np.array([row[name] for row in rows]) for name in rows[0]})
    return series, radii


def _rover_summary(series, radii, **options):
    return metrics.summarize_rover(series, rim_radii=radii, weight=200.0, grain_radius=0.001, **options)


def test_a_rover_s_window_is_found_as_a_wheel_s():
    """One rule for both (metrics.drive_window): the window starts at the later of the traction's and the
    sinkage's MSER-5 starts; a sinkage drifting steadily (MSER-5 finds no start) by less than half a grain
    radius leaves the traction's window and is steady, where a rover's was called 'too short' (drive longer,
    which only drifts on) and a wheel's steady."""
    k = np.arange(400)
    rng = np.random.default_rng(5)
    drift = np.r_[np.full(40, 0.01), 0.01 + 2e-4 * k / 400][:, None] + 2e-6 * rng.standard_normal((440, 4))
    series, radii = _rover([0.06, 0.0, 0.0], 1.0, sinkage=drift)
    assert metrics.mser_truncation(drift[40:].mean(axis=1)) is None  # a steady drift: no start
    out = _rover_summary(series, radii)
    speed_cut = metrics.mser_truncation(series["rover_forward_speed"][40:])
    assert out["steady_state"] == metrics.STEADY and out["window"][0] == pytest.approx(series["time"][40 + speed_cut])
    wheel = _series()
    wheel["sinkage"][60:, 0] = 0.004 + 2e-4 * np.arange(400) / 400 + 2e-6 * rng.standard_normal(400)
    alone = metrics.summarize(wheel, rim_radius=0.04, wheel_load=10.0, mode="slip", grain_radius=0.001)
    assert alone["steady_state"] == metrics.STEADY and alone["window"][0] == pytest.approx(wheel["time"][60])
    # a settling: from the sinkage's start, for both
    settling = np.r_[np.full(40, 0.01), 0.01 + 0.003 * (1 - np.exp(-k / 30.0))][:, None] + 1e-4 * rng.standard_normal(
        (440, 4)
    )
    series, radii = _rover([0.06, 0.0, 0.0], 1.0, sinkage=settling)
    cut = metrics.mser_truncation(settling[40:].mean(axis=1))
    assert cut >= 30 and _rover_summary(series, radii)["window"][0] == pytest.approx(series["time"][40 + cut])


def test_a_rover_in_reverse_or_turning_in_place_is_not_stuck():
    """Backwards at 0.06 m/s on wheels turning backwards at rim speed 0.1 m/s: slip 0.4 as forwards, but it
    was judged immobile all the drive ('stuck', 19 s of 20) as its advance was taken along +x only. A turn
    in place (wheels against each other) has no rover slip and no drive to be stuck in."""
    out = _rover_summary(*_rover([-0.06, 0.0, 0.0], -1.0))
    assert out["steady_state"] == metrics.STEADY and not out["stuck"] and out["time_immobile"] == 0.0
    assert out["slip"] == pytest.approx(0.4) and out["wheel_slip"] == pytest.approx([0.4] * 4)
    forward = _rover_summary(*_rover([0.06, 0.0, 0.0], 1.0))
    assert forward["slip"] == pytest.approx(0.4) and forward["steady_state"] == metrics.STEADY
    turning = _rover_summary(*_rover([0.0, 0.0, 0.0], [-1.0, 1.0, -1.0, 1.0], yaw=0.5 * 0.05 * np.arange(440)))
    assert not turning["stuck"] and math.isnan(turning["slip"]), turning


def test_a_parked_rover_has_no_slip_only_a_driven_one_has():
    """A rover parked on its speed servos (speed commands 0) whose hinges jitter about their axles (1 Hz,
    0.02 rad/s, with a small mean left over from the jitter's noise) while its body creeps 1 mm/s: it
    reported slips of noise (the probe's MMX rover: rover -6.37, wheels 2.58 to -14.1), as 1 - v / (omega r)
    divides by the jitter's mean. Slip is undefined there: nan for the rover and each wheel. Unheld
    wheels (a zero-torque drive) that only jitter: nan too (a mean spin within two standard errors of 0).
    One wheel held and three driving: that wheel's slip nan, the others' and the rover's measured."""
    rng = np.random.default_rng(3)
    jitter = 0.02 * np.sin(2.0 * np.pi * 0.05 * np.arange(440))[:, None] + 1e-4 * rng.standard_normal((440, 4))
    jittering = _rover_summary(*_rover([0.001, 0.0, 0.0], jitter))  # speeds asked as they came: not held
    assert math.isnan(jittering["slip"]) and all(math.isnan(v) for v in jittering["wheel_slip"]), jittering
    series, radii = _rover([0.001, 0.0, 0.0], jitter)
    series["speed_command"][:] = 0.0  # held at 0: the jitter was the servo's
    held = _rover_summary(series, radii)
    assert math.isnan(held["slip"]) and all(math.isnan(v) for v in held["wheel_slip"]), held
    unheld = _rover_summary(*_rover([0.001, 0.0, 0.0], jitter, torque=0.0))
    assert math.isnan(unheld["slip"]) and all(math.isnan(v) for v in unheld["wheel_slip"]), unheld
    series, radii = _rover([0.045, 0.0, 0.0], [0.0, 0.5, 0.5, 0.5])
    one_held = _rover_summary(series, radii)  # rims 0.05 m/s on three wheels, the mean 0.0375: slip 0.4 of it
    assert math.isnan(one_held["wheel_slip"][0]) and one_held["wheel_slip"][1:] == pytest.approx([0.1] * 3)
    assert one_held["slip"] == pytest.approx(1.0 - 0.045 / 0.0375)


def test_a_rover_that_stopped_is_stuck_whatever_its_wheels_do_after():
    """The body stops after 5 s of drive while the wheels keep turning (stuck), or slow to 0.02 rad/s: the
    last radian of wheel turn then reached back 15 s to when it moved, and the rover was 'steady' at a slip
    of 1. A nan spin (a lost wheel) switched the check off."""
    k = np.arange(440) - 40
    moving = (k < 100)[:, None]
    stopped = _rover_summary(*_rover(0.06 * moving * [1.0, 0.0, 0.0], 1.0))
    assert stopped["stuck"] and stopped["steady_state"] == metrics.STUCK
    slowed = _rover_summary(*_rover(0.06 * moving * [1.0, 0.0, 0.0], np.where(moving, 1.0, 0.02) * np.ones(4)))
    assert slowed["slip"] == pytest.approx(1.0) and slowed["stuck"] and slowed["steady_state"] == metrics.STUCK
    series, radii = _rover(0.06 * (k < 300)[:, None] * [1.0, 0.0, 0.0], 1.0)
    series["angular_velocity"][100, 2] = math.nan
    assert _rover_summary(series, radii)["stuck"]


def test_a_stalled_drive_is_stuck_not_steady():
    """A torque drive too weak to turn the wheels: they jitter at 0.02 rad/s about their axles, creep back
    and forth at 1e-4 rad/s of noise (rims about 10 um/s) or stop entirely, and the body stays within a
    grain diameter (2 mm) or slides back: the rover was 'steady' at a slip of noise (or nan), not stuck, as
    the stuck criterion waits for a radian of wheel turn. The SCM rover (examples/phobos_rover_scm_traverse
    .toml) on 1e-4 N m a wheel jittered at 0.02 rad/s, its rims 1.3-2.3 mm on and its body 1 mm over its
    100 s window, and was 'too short'. Wheels driven backwards, the rover with them, were 'steady' at slip
    0.4. A drive whose wheels do not turn with it, and that advances under a grain diameter, has stalled:
    stuck. Not stalled: a parked rover (zero commands), wheels turning with their commands however slowly
    (a short window, on a torque or at a fraction of the speed asked), speeds or torques that reverse and
    are followed, locked wheels the body slides forward on, a run whose file holds no commands."""
    rng = np.random.default_rng(5)
    creep = 1e-4 * rng.standard_normal((440, 4))
    jitter = 0.02 * np.sin(2.0 * np.pi * 0.05 * np.arange(440))[:, None] * np.ones(4)  # 1 Hz about the axles
    stalls = {
        "jitter": _rover([0.0, 0.0, 0.0], jitter, torque=1e-4),
        "creep": _rover(np.c_[0.1 * creep.mean(axis=1), np.zeros((440, 2))], creep, torque=0.5),
        "stopped": _rover([0.0, 0.0, 0.0], 0.0, torque=[0.5, 0.5, -0.2, 0.0]),
        "sliding back": _rover([-0.01, 0.0, 0.0], 0.0, torque=0.5),  # 0.2 m back, downhill
        "driven backwards": _rover([-0.006, 0.0, 0.0], -0.1, torque=0.5),
        "jitter asked 0.06 rad/s": _rover([0.0, 0.0, 0.0], jitter),
        "jitter asked 0.012 rad/s": _rover([0.0, 0.0, 0.0], jitter),
        "jitter asked -0.012 rad/s": _rover([0.0, 0.0, 0.0], jitter),
    }
    for name, speed in (("jitter asked 0.06 rad/s", 0.06), ("jitter asked 0.012 rad/s", 0.012)):
        stalls[name][0]["speed_command"][:] = speed
    stalls["jitter asked -0.012 rad/s"][0]["speed_command"][:] = -0.012
    for name, (series, radii) in stalls.items():
        out = _rover_summary(series, radii)
        assert out["stalled"] and out["stuck"] and out["steady_state"] == metrics.STUCK, (name, out)
    parked = _rover_summary(*_rover([0.0, 0.0, 0.0], 0.0))
    assert not parked["stalled"] and not parked["stuck"] and parked["steady_state"] == metrics.STEADY
    unheld = _rover_summary(*_rover([0.0, 0.0, 0.0], 0.0, torque=0.0))
    assert not unheld["stalled"] and unheld["steady_state"] == metrics.STEADY
    slow = _rover_summary(*_rover([0.0006, 0.0, 0.0], 0.01, torque=0.5))  # rims 1 mm/s: 10 mm over the window
    assert not slow["stalled"] and slow["steady_state"] == metrics.STEADY and slow["slip"] == pytest.approx(0.4)
    slower = _rover_summary(*_rover([3e-5, 0.0, 0.0], 5e-4, torque=0.5))  # rims 0.05 mm/s: under 1 mm
    assert not slower["stalled"] and slower["slip"] == pytest.approx(0.4)
    series, radii = _rover([0.0, 0.0, 0.0], 1e-3)
    series["speed_command"][:] = 0.06  # turning on at 1/60 of the speed asked: slow, not stalled
    assert not _rover_summary(series, radii)["stalled"]
    reversing = np.sign(np.sin(2.0 * np.pi * np.arange(440) / 20.0 + 0.1))[:, None] * np.ones(4)
    assert not _rover_summary(*_rover([0.0, 0.0, 0.0], 0.05 * reversing))["stalled"]  # speeds asked and followed
    assert not _rover_summary(*_rover([0.0, 0.0, 0.0], 0.5 * reversing, torque=0.5 * reversing))["stalled"]
    sliding = _rover_summary(*_rover([0.01, 0.0, 0.0], 0.0, torque=0.5))  # locked wheels, the body slides on
    assert not sliding["stalled"] and sliding["steady_state"] == metrics.STEADY
    series, radii = stalls["stopped"]
    del series["speed_command"], series["torque_command"]
    assert not _rover_summary(series, radii)["stalled"]
    held, still, x = np.full((3, 4), 0.5), np.zeros((3, 4)), np.array([1.0, 0.0, 0.0])
    no_speed = np.full((3, 4), np.nan)
    for moved, stalled in ((0.001, True), (0.003, False), (-0.003, True), (np.nan, False)):
        assert metrics.drive_stalled((no_speed, held), still, radii, np.ones(3), moved * x, x, 0.001) == stalled
    ratchet = np.array([0.3, 0.3, -0.2, -0.2])[:, None] * np.ones(4)  # 0.2 rad on of 1 rad turned: 20 mm of rim
    assert not metrics.drive_stalled(
        (no_speed[:1].repeat(4, 0), held[:1].repeat(4, 0)), ratchet, radii, np.ones(4), 0 * x, x, 0.001
    )
    assert not metrics.drive_stalled((no_speed, None), still, radii, np.ones(3), 0 * x, x, 0.001)
    assert not metrics.drive_stalled((no_speed, held), still, radii, np.zeros(3), 0 * x, x, 0.001)  # no time
    rolling = np.full((3, 4), 0.01)  # one wheel driven, three free, all rolling on at 1 mm/s of rim
    one = np.where([True, False, False, False], 0.5, 0.0) * np.ones((3, 1))
    assert not metrics.drive_stalled((no_speed, one), rolling, radii, np.ones(3), 0.0018 * x, x, 0.001)
    pulsed = np.where(np.arange(3)[:, None] == 0, 0.5, 0.0) * np.ones(4)  # a torque one step in three
    assert not metrics.drive_stalled((no_speed, pulsed), rolling, radii, np.ones(3), 0.0018 * x, x, 0.001)
    assert not metrics.drive_stalled((no_speed, held), still, radii, np.ones(3), 0 * x, x, None)
    lost = still.copy()
    lost[1, 2] = np.nan  # a lost wheel: not judged
    assert not metrics.drive_stalled((no_speed, held), lost, radii, np.ones(3), 0 * x, x, 0.001)


def test_a_rover_with_one_wheel_sinking_or_lifted():
    """One wheel digging in 20 mm over the drive while the others rest: the mean sinkage's MSER said 'too
    short'; with another wheel rising as much the mean was flat and the rover 'steady'. Each wheel's
    sinkage is now judged: 'still sinking'. One wheel in the air the whole drive made the rover
    'airborne' (every wheel had to touch); three wheels hold it up."""
    rng = np.random.default_rng(3)
    sinkage = 0.01 + 1e-4 * rng.standard_normal((440, 4))
    sinkage[40:, 3] += np.linspace(0.0, 0.02, 400)
    sinkage[40:, 2] -= np.linspace(0.0, 0.02, 400)
    assert _rover_summary(*_rover([0.06, 0.0, 0.0], 1.0, sinkage=sinkage))["steady_state"] == metrics.SINKING
    contacts = np.full((440, 4), 5)
    contacts[40:, 3] = 0
    lifted = _rover_summary(*_rover([0.06, 0.0, 0.0], 1.0, contacts=contacts))
    assert lifted["steady_state"] == metrics.STEADY and lifted["contact_fraction"] == 1.0
    assert lifted["wheel_contact_fraction"] == [1.0, 1.0, 1.0, 0.0]
    contacts[40::2, :2] = 0  # two wheels off every other step: half the time on two wheels
    assert _rover_summary(*_rover([0.06, 0.0, 0.0], 1.0, contacts=contacts))["steady_state"] == metrics.AIRBORNE


def test_a_rovers_displacement_and_energy_per_metre():
    """A straight drive of 400 steps of 3 mm: displacement = travel = 1.2 m (it missed the first step). A
    parked rover spending energy: -inf or +inf J/m by the energy's sign, nan when it spends none (both were
    +inf)."""
    out = _rover_summary(*_rover([0.06, 0.0, 0.0], 1.0, power=10.0))
    assert out["displacement"] == pytest.approx(1.2) and out["travel"] == pytest.approx(1.2)
    assert out["energy_per_metre"] == pytest.approx(4 * 10.0 * 20.0 / 1.2)
    assert _rover_summary(*_rover([0.0, 0.0, 0.0], 0.0, power=-5.0))["energy_per_metre"] == -math.inf
    assert math.isnan(_rover_summary(*_rover([0.0, 0.0, 0.0], 0.0))["energy_per_metre"])


def test_a_window_shorter_than_one_grouser_passage_is_too_short():
    """A mean over part of a grouser's passage depends on where in it the window starts (a 1 s SCM run
    printed DP/W 0.25 'steady' where the wheel settles at 0.37, its rim having turned a fifth of a grouser
    pitch over the window). A grousered wheel's window must pass one grouser at least: the rim's turn
    over it (0.25 rad/s here) times the grouser count over 2 pi; a smooth wheel has nothing periodic."""
    s = _series()
    smooth = metrics.summarize(s, rim_radius=0.04, wheel_load=10.0)
    assert smooth["steady_state"] == metrics.STEADY and "grouser_passages" not in smooth
    turn = 0.25 * (smooth["window"][1] - smooth["window"][0] + 0.05)  # over the window's steps, its first too
    enough = math.ceil(2 * math.pi / turn)  # the fewest grousers of which one passes over the window
    grousered = metrics.summarize(s, rim_radius=0.04, wheel_load=10.0, grouser_count=enough)
    assert grousered["steady_state"] == metrics.STEADY
    assert grousered["grouser_passages"] == pytest.approx(turn * enough / (2 * math.pi))
    assert 1 <= grousered["grouser_passages"] < 1 + turn / (2 * math.pi)
    lost = _series()
    lost["angular_velocity"][-3, 0, 1] = np.nan  # a spin that is not a number turns no judged grouser
    assert metrics.summarize(lost, rim_radius=0.04, wheel_load=10.0, grouser_count=enough)["steady_state"] == (
        metrics.TOO_SHORT
    )
    short = metrics.summarize(s, rim_radius=0.04, wheel_load=10.0, grouser_count=enough - 1)
    assert short["steady_state"] == metrics.TOO_SHORT and short["grouser_passages"] < 1
    assert short["slip"] == pytest.approx(grousered["slip"])  # the numbers stay, labelled
    # dp_over_w carries its error bar: the pull's over the load
    assert grousered["dp_over_w_sem"] == pytest.approx(grousered["drawbar_pull_sem"] / 10.0)


def test_a_rising_wheel_is_still_rising_and_a_wheel_that_never_landed_has_its_deepest_sinkage():
    """A wheel climbing out of a rut deeper than its steady one (a landing's) drifts upwards: it was
    labelled 'still sinking'. A run without a landing (a wheel sinking on under its load) reports the
    deepest its rim reached, which the calibration-depth check then judges."""
    rising = _series()
    rising["sinkage"][60:, 0] = np.linspace(0.03, 0.004, 400)
    out = metrics.summarize(rising, rim_radius=0.04, wheel_load=10.0, grain_radius=0.002)
    assert out["steady_state"] == metrics.RISING and out["sinkage_rate"] < 0
    sinking = _series()
    sinking["sinkage"][60:, 0] = np.linspace(0.004, 0.03, 400)
    assert metrics.summarize(sinking, rim_radius=0.04, wheel_load=10.0, grain_radius=0.002)["steady_state"] == (
        metrics.SINKING
    )
    deep = _series()
    deep["sinkage"][:, 0] = np.linspace(0.0, 0.3, 460)
    deep["sinkage"][5, 0] = np.nan
    unlanded = metrics.summarize(deep, rim_radius=0.04, wheel_load=10.0, landed=False)
    assert unlanded["steady_state"] == metrics.NO_LANDING and unlanded["deepest_sinkage"] == pytest.approx(0.3)


def test_a_rover_window_shorter_than_one_grouser_passage_is_too_short():
    """As for a wheel, on the fewest passages among a rover's grousered wheels (the rims turn 0.05 rad/s
    here); smooth wheels are not counted; its net traction over its weight carries its error bar."""
    series, radii = _rover([0.003, 0.0, 0.0], 0.05)
    smooth = _rover_summary(series, radii)
    assert smooth["steady_state"] == metrics.STEADY and "grouser_passages" not in smooth
    turn = 0.05 * (smooth["window"][1] - smooth["window"][0] + 0.05)  # over the window's steps, its first too
    enough = math.ceil(2 * math.pi / turn)
    assert enough > 2
    grousered = _rover_summary(series, radii, grouser_counts=[0, enough, enough + 3, 0])
    assert grousered["steady_state"] == metrics.STEADY
    assert grousered["grouser_passages"] == pytest.approx(turn * enough / (2 * math.pi))
    short = _rover_summary(series, radii, grouser_counts=[0, enough - 1, enough + 3, 0])
    assert short["steady_state"] == metrics.TOO_SHORT and short["grouser_passages"] < 1
    braked, radii = _rover([0.003, 0.0, 0.0], [0.05, 0.0, 0.05, 0.05])  # a grousered wheel held still
    held = _rover_summary(braked, radii, grouser_counts=[enough, enough, enough, enough])
    assert held["grouser_passages"] == pytest.approx(turn * enough / (2 * math.pi)), held
    with pytest.raises(ValueError, match="one per wheel"):
        _rover_summary(series, radii, grouser_counts=[enough])
    assert grousered["net_traction_over_weight_sem"] == pytest.approx(grousered["net_traction_sem"] / 200.0)
    assert grousered["dp_over_w_sem"] == grousered["net_traction_over_weight_sem"]
    # one wheel climbs 1.5 mm out of its landing rut while the others settle 0.5 mm (under half the 1 mm grain
    # radius: steady), the mean flat
    rising = 0.01 + 1e-4 * np.random.default_rng(4).standard_normal((440, 4))
    rising[40:, 2] -= np.linspace(0.0, 0.0015, 400)
    rising[40:, [0, 1, 3]] += np.linspace(0.0, 0.0005, 400)[:, None]
    assert _rover_summary(*_rover([0.06, 0.0, 0.0], 1.0, sinkage=rising))["steady_state"] == metrics.RISING
    rising[40:, 0] += np.linspace(0.0, 0.0015, 400)  # and another digs in
    rising[40:, 1] -= np.linspace(0.0, 0.0015, 400)  # (the mean flat)
    assert _rover_summary(*_rover([0.06, 0.0, 0.0], 1.0, sinkage=rising))["steady_state"] == metrics.SINKING
    landing = _rover_summary(*_rover([0.06, 0.0, 0.0], 1.0, sinkage=rising), landed=False)
    assert landing["steady_state"] == metrics.NO_LANDING
    assert landing["wheel_deepest_sinkage"] == pytest.approx(np.max(rising, axis=0).tolist())


def test_a_run_is_summarized_as_ramped_only_under_a_ramped_free_carriage(tiny_run, monkeypatch):
    """The run's summary (cosim.records.run_summary) tells metrics.summarize that the load ramps exactly
    when the carriage is free and testbed.drawbar_ramp > 0 (a slip-mode carriage takes no drawbar load)."""
    from cosim import records
    from cosim.plan import load_plan

    class Seen(Exception):
        pass

    seen: dict = {}

    def summarize(series, **kwargs):
        seen.update(kwargs)
        raise Seen  # before the system is read: only the call's arguments are looked at

    monkeypatch.setattr(metrics, "summarize", summarize)
    for changes, ramped in (
        (["testbed.drawbar_ramp=0.05"], True),
        (["testbed.drawbar_ramp=0.0"], False),
        (['testbed.mode="slip"', "testbed.slip=0.2"], False),
    ):
        plan = load_plan(str(tiny_run / "scene.toml"), changes)
        with pytest.raises(Seen):
            records.run_summary(plan, None, str(tiny_run / "results.h5"), True, 1.0, 1.0, 1)
        assert seen["ramped"] is ramped, changes
