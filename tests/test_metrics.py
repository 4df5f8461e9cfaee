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
    assert metrics.ensemble([2.0])["deterministic"] is False  # one run says nothing about scatter
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
    assert metrics.mser_truncation(x) is None and metrics.steady_window({"v": x}) == (600, False)
    x[500] = math.inf
    assert metrics.mser_truncation(x) is None
    assert metrics.mser_truncation(np.full(100, math.nan)) is None


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
    assert f"! the window spans only {spans:.0f} correlation times of drawbar_pull (< 50)" in printed, printed
    assert "their within-run s.e. are too small" in printed and "of sinkage" not in printed, printed


def test_an_ensemble_of_one_replica_is_not_judged():
    """One steady replica has no scatter: its row said "NO (std > tol)" beside a nan std."""
    from cosim.study import _ensemble_text

    stats = {"steady": 1, "replicas": 3, "metrics": {"slip": metrics.ensemble([0.21, None, math.nan])}}
    row = _ensemble_text(stats, "replicas").splitlines()[-1]
    assert "n/a (one replica)" in row and "NO" not in row and row.split()[1] == "1"
