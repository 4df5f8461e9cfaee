"""Coupler + SpringDamperTerrain + controllers, with MuJoCo rovers, against theory."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

pytest.importorskip("mujoco")

from cosim.contract import SoilSide, WheelKinematics, WheelWrench  # noqa: E402
from cosim.controllers import ConstantSpeed, DriveCommand, SlipController  # noqa: E402
from cosim.coupler import Coupler, CouplingEnergyWarning, CouplingTimeError, stack_records  # noqa: E402
from cosim.terrain import SpringDamperTerrain  # noqa: E402
from rover_models.mjcf import MMX_WHEELS, mmx_rover_xml, single_wheel_rig_xml  # noqa: E402
from rover_models.mujoco_rover import MujocoRover  # noqa: E402

# --- the analytic terrain on its own ---------------------------------------------------


def _kin(p=(0, 0, 0.1), q=(1, 0, 0, 0), v=(0, 0, 0), w=(0, 0, 0)):
    return WheelKinematics(position=p, orientation=q, linear_velocity=v, angular_velocity=w)


def test_terrain_normal_and_coulomb_forces():
    soil = SpringDamperTerrain(0.1, 1, stiffness=1e4, damping=100.0, friction=0.5, slip_velocity=1e-3, substeps=1)
    assert isinstance(soil, SoilSide)
    # Hub 2 mm low, sinking at 1 cm/s, sliding at 1 m/s along +x without spin.
    (w,) = soil.advance(1e-9, [_kin(p=(0, 0, 0.098), v=(1.0, 0, -0.01))])
    f_n = 1e4 * 0.002 + 100.0 * 0.01
    np.testing.assert_allclose(w.force, [-0.5 * f_n / np.sqrt(1 + 1e-6), 0, f_n], rtol=1e-6)
    # Torque about the hub of a force at the rim's lowest point (0, 0, -r).
    np.testing.assert_allclose(w.torque, np.cross([0, 0, -0.1], w.force), rtol=1e-9)
    assert w.sinkage == pytest.approx(0.002, rel=1e-6) and w.contact_count == 1
    # Rolling without slip at the same speed: no tangential force.
    soil.time = 0.0
    (w,) = soil.advance(1e-9, [_kin(p=(0, 0, 0.098), v=(1.0, 0, 0), w=(0, 10.0, 0))])
    assert abs(w.force[0]) < 1e-9 * w.force[2]
    # Above ground: nothing.
    soil.time = 0.0
    (w,) = soil.advance(1e-3, [_kin(p=(0, 0, 0.2))])
    assert not w.force.any() and w.sinkage == 0.0


def test_terrain_slip_law_gives_the_traction_of_the_slip():
    soil = SpringDamperTerrain(0.1, 1, traction="slip", friction=0.6, slip_scale=0.1, substeps=1)
    omega, s = 20.0, 0.25
    v = (1 - s) * omega * 0.1
    (w,) = soil.advance(1e-9, [_kin(p=(0, 0, 0.099), v=(v, 0, 0), w=(0, omega, 0))])
    assert w.force[0] / w.force[2] == pytest.approx(0.6 * (1 - np.exp(-s / 0.1)), rel=1e-9)


# --- helpers ---------------------------------------------------------------------------------


def _rig(**kw):
    return MujocoRover(single_wheel_rig_xml(**kw), ["wheel"])


def _mmx():
    return MujocoRover(mmx_rover_xml(), list(MMX_WHEELS))


def test_gravity_is_pushed_to_both_sides():
    rover, soil = _rig(), SpringDamperTerrain(0.1, 1)
    Coupler(soil, rover, 1e-3, gravity=(0.1, 0, -3.7))
    np.testing.assert_array_equal(rover.model.opt.gravity, [0.1, 0, -3.7])
    np.testing.assert_array_equal(soil.gravity, [0.1, 0, -3.7])


@pytest.mark.parametrize("g", [9.81, 5.7e-3])
def test_rover_standing_carries_its_weight(g):
    """MMX-like rover (25 kg) set down touching the ground: after settling the vertical
    terrain forces sum to m g within 1%, each wheel sinks m g / (4 k) (symmetric rover),
    every wheel keeps contact (F_z > 0) from the first macro step on, no energy warning."""
    rover = _mmx()
    k = 2.0e4
    soil = SpringDamperTerrain(0.1, 4, stiffness=k, damping=500.0, slip_velocity=0.05, substeps=2)
    coupler = Coupler(soil, rover, 2e-3, gravity=(0, 0, -g), controller=ConstantSpeed(0.0, 4))
    with warnings.catch_warnings():
        warnings.simplefilter("error", CouplingEnergyWarning)
        records = coupler.run(0.6)
    rec = stack_records(records)
    mg = rover.total_mass * g
    fz = rec["force"][:, :, 2]
    settled = rec["time"] > 0.4
    np.testing.assert_allclose(fz[settled].sum(axis=1), mg, rtol=0.01)
    np.testing.assert_allclose(rec["sinkage"][-1], mg / (4 * k), rtol=0.01)
    assert (fz[1:] > 0).all(), "a wheel left the ground"
    assert (rec["contact_count"][1:] == 1).all()


def _drop_and_roll(H, scheme="gauss-seidel", t_end=0.3):
    """Single-wheel rig dropped 5 mm onto the terrain while driven at 5 rad/s."""
    rover = _rig(hub_height=0.105, timestep=1e-4)
    soil = SpringDamperTerrain(0.1, 1, slip_velocity=0.05, substeps=2)
    coupler = Coupler(soil, rover, H, scheme=scheme, controller=ConstantSpeed(5.0, 1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CouplingEnergyWarning)
        records = coupler.run(t_end)
    return stack_records(records)


@pytest.fixture(scope="module")
def fine_reference():
    return _drop_and_roll(1e-4)


@pytest.mark.parametrize("scheme", ["gauss-seidel", "jacobi"])
def test_coupled_result_converges_as_macro_step_shrinks(fine_reference, scheme):
    """Error of the hub trajectory against a fine-H reference falls monotonically with H,
    at about first order (explicit coupling: the wrench is held or lagged over H)."""
    errors = []
    for H in (4e-3, 2e-3, 1e-3, 5e-4):
        rec = _drop_and_roll(H, scheme)
        stride = int(round(H / 1e-4))
        ref = fine_reference["position"][stride - 1 :: stride]
        np.testing.assert_allclose(rec["time"], fine_reference["time"][stride - 1 :: stride], atol=1e-12)
        errors.append(np.abs(rec["position"] - ref).max())
    errors = np.array(errors)
    assert (np.diff(errors) < 0).all(), errors
    ratios = errors[:-1] / errors[1:]
    assert (ratios > 1.5).all() and (ratios < 3.0).all(), ratios


def test_energy_bookkeeping_matches_the_rover_energy_and_warns_for_jacobi():
    """Undamped, frictionless ground (conservative): any change of the rig's mechanical
    energy is created by the coupling. Jacobi's one-step lag gains energy on every
    bounce; the coupler's bookkeeping must equal the energy gain measured on the rover."""
    m, g, H = 10.0, 9.81, 2e-3  # ballast + wheel: the vertically moving mass
    # MuJoCo's own step is small: its semi-implicit Euler loses m a^2 h^2 / 2 per step
    # under a held force, which would blur the comparison (7% at h = 2.5e-4 s).
    rover = _rig(hub_height=0.11, timestep=2.5e-5)
    soil = SpringDamperTerrain(0.1, 1, damping=0.0, friction=0.0, substeps=4)
    coupler = Coupler(soil, rover, H, scheme="jacobi")
    with pytest.warns(CouplingEnergyWarning):
        records = coupler.run(0.5)
    rec = stack_records(records)
    flight = np.nonzero(rec["sinkage"][:, 0] == 0.0)[0][-1]  # last step with no contact
    z, vz = rec["position"][flight, 0, 2], rec["linear_velocity"][flight, 0, 2]
    gained = m * g * (z - 0.11) + 0.5 * m * vz**2
    created = np.cumsum((rec["work_on_rover"] + rec["work_on_soil"]).sum(axis=1))[flight]
    assert gained > 0.5  # J: a real gain, about 1.5 J here
    assert created == pytest.approx(gained, rel=0.02)
    # the warning went to the log once; a run's summary keeps it and prints it as a `!` line
    import contextlib
    import io
    from types import SimpleNamespace

    from cosim.cli import _print_summary

    assert coupler.energy_over_tolerance
    summary = {"coupling_energy_created": coupler.energy_created, "coupling_energy_exchanged": coupler.energy_exchanged}
    printed = []
    for over in (True, False):
        out = io.StringIO()
        result = SimpleNamespace(summary={**summary, "coupling_energy_over_tolerance": over}, status="x", out_dir="r")
        with contextlib.redirect_stdout(out):
            _print_summary(result)
        printed.append(out.getvalue())
    assert f"! the coupling created {coupler.energy_created:.3g} J of energy (over its tolerance" in printed[0]
    assert "the coupling created" not in printed[1]

    # Gauss-Seidel at a smaller H keeps the same bounce within tolerance.
    rover = _rig(hub_height=0.11, timestep=2.5e-4)
    soil = SpringDamperTerrain(0.1, 1, damping=0.0, friction=0.0, substeps=4)
    coupler = Coupler(soil, rover, 1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CouplingEnergyWarning)
        coupler.run(0.5)
    assert abs(coupler.energy_created) < 0.01 * coupler.energy_exchanged


def test_slip_controller_holds_target_slip():
    """Rig on the slip-law terrain: the controller holds s* = 0.2 within +-0.01 after
    0.3 s, so the traction is mu (1 - exp(-s*/s0)) F_z and the rig accelerates at
    a = that traction / total mass (15 kg, load from 10 kg)."""
    g, mu, s0, s_star = 9.81, 0.6, 0.1, 0.2
    rover = _rig()
    soil = SpringDamperTerrain(0.1, 1, traction="slip", friction=mu, slip_scale=s0, slip_velocity=0.05, substeps=2)
    controller = SlipController(s_star, 0.1, 1, kp=1.0, ki=20.0, omega_min=2.0)
    coupler = Coupler(soil, rover, 1e-3, gravity=(0, 0, -g), controller=controller)
    slips = []
    rec = stack_records(coupler.run(1.0, callback=lambda c: slips.append(controller.slip[0])))
    late = rec["time"] > 0.3
    # Slip measured from the rover's kinematics (not the controller's own number).
    v = rec["linear_velocity"][:, 0, 0]
    rim = rec["angular_velocity"][:, 0, 1] * 0.1
    slip = 1 - v / rim
    assert np.abs(slip[late] - s_star).max() < 0.01
    a_theory = mu * (1 - np.exp(-s_star / s0)) * 10.0 * g / 15.0
    a_fit = np.polyfit(rec["time"][late], v[late], 1)[0]
    assert a_fit == pytest.approx(a_theory, rel=0.01)


class _WrongTimeSoil(SpringDamperTerrain):
    def advance(self, t_end, start, end=None):
        out = super().advance(t_end, start, end)
        self.time = t_end + 1e-6  # a soil that overshoots
        return out


def test_sides_must_reach_the_same_time():
    coupler = Coupler(_WrongTimeSoil(0.1, 1), _rig(), 1e-3)
    with pytest.raises(CouplingTimeError, match="soil at t="):
        coupler.step()
    soil = SpringDamperTerrain(0.1, 1, time=0.5)
    with pytest.raises(CouplingTimeError):
        Coupler(soil, _rig(), 1e-3)


def test_wheel_count_mismatch_and_bad_arguments():
    with pytest.raises(ValueError, match="4 wheels"):
        Coupler(SpringDamperTerrain(0.1, 4), _rig(), 1e-3)
    with pytest.raises(ValueError, match="scheme"):
        Coupler(SpringDamperTerrain(0.1, 1), _rig(), 1e-3, scheme="newton")
    with pytest.raises(ValueError, match="mode"):
        DriveCommand("power", [1.0])


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda: Coupler(SpringDamperTerrain(0.1, 1), _rig(), float("inf")), "macro_step must be a finite number"),
        (lambda: Coupler(SpringDamperTerrain(0.1, 1), _rig(), "0.01"), "macro_step must be a finite number"),
        (lambda: Coupler(SpringDamperTerrain(0.1, 1), _rig(), 1e-3, scheme=None), "scheme must be"),
        (lambda: Coupler(SpringDamperTerrain(0.1, 1), _rig(), 1e-3).run(float("nan")), "t_end must be a finite"),
        (lambda: Coupler(SpringDamperTerrain(0.1, 1), _rig(), 1e-3).run(-1.0), "not before the coupler's"),
        (lambda: SpringDamperTerrain(0.1, 1, stiffness=-2e4), "stiffness must be a finite number > 0"),
        (lambda: SpringDamperTerrain(0.1, 1, friction=-1.0), "friction must be a finite number >= 0"),
        (lambda: SpringDamperTerrain(0.1, 1, substeps=0), "substeps must be a whole number >= 1"),
        (lambda: _rig().advance(float("nan")), "t_end must be a finite time"),
        (lambda: _rig().advance(float("inf")), "t_end must be a finite time"),
        (lambda: MujocoRover(mmx_rover_xml(), ["wheel_fl", "wheel_fl"]), r"names \['wheel_fl'\] more than once"),
        (lambda: MujocoRover(mmx_rover_xml(), "wheel_fl"), r"must be a list of body names: \['wheel_fl'\]"),
        (lambda: mmx_rover_xml(body_mass=-17.0), "body_mass must be a finite number > 0"),
        (lambda: mmx_rover_xml(timestep=float("nan")), "timestep must be a finite number > 0"),
        (
            lambda: MujocoRover(mmx_rover_xml().replace('timestep="0.001"', 'timestep="0"'), list(MMX_WHEELS)),
            "the MJCF's option timestep must be > 0",
        ),
        (lambda: _rig().set_gravity([0.0, 0.0, float("nan")]), "gravity must be 3 finite numbers"),
        (lambda: WheelWrench(force="abc"), "WheelWrench.force must be 3 numbers"),
        (lambda: WheelWrench(torque=(1.0, 2.0)), "WheelWrench.torque must be 3 numbers"),
    ],
    ids=[
        "infinite macro step",
        "macro step as text",
        "no scheme",
        "run to nan",
        "run backwards",
        "negative stiffness",
        "negative friction",
        "no substeps",
        "rover to nan",
        "rover to inf",
        "a wheel twice",
        "a name for the list",
        "negative mass",
        "nan timestep",
        "an MJCF's zero timestep",
        "nan gravity",
        "a text force",
        "a 2-vector torque",
    ],
)
def test_the_coupling_apis_refuse_what_would_hang_or_run_wrong(make, words):
    """An infinite macro step or rover time looped for ever; nan times turned the clocks nan; run(-1) gave
    no records silently; a negative ground stiffness let the rover fall through it and a negative friction
    pushed it on; a wheel named twice dropped one wrench; a negative mass or a nan timestep compiled into
    another rover. Each is an ArgumentError naming the argument."""
    with pytest.raises(ValueError, match=words):
        make()


def test_a_controller_that_returns_no_drive_command_is_named():
    from cosim.controllers import apply_command

    with pytest.raises(ValueError, match="a drive controller must return a DriveCommand, got str"):
        apply_command(_rig(), "fast")


def test_records_and_schemes():
    """Records have documented shapes; Jacobi's first step holds a zero wrench (lag)
    while Gauss-Seidel's already holds the soil's answer for that step."""
    for scheme in ("gauss-seidel", "jacobi"):
        rover = _mmx()
        soil = SpringDamperTerrain(0.1, 4, slip_velocity=0.05, substeps=2)
        rover.advance(0.0)
        coupler = Coupler(soil, rover, 1e-3, scheme=scheme)
        # Start 1 mm deep so the first step already has contact.
        coupler.rover.data.qpos[2] -= 0.001
        import mujoco

        mujoco.mj_forward(coupler.rover.model, coupler.rover.data)
        rec = stack_records(coupler.run(0.005))
        assert rec["time"].shape == (5,) and np.allclose(rec["time"], np.arange(1, 6) * 1e-3)
        assert rec["position"].shape == (5, 4, 3) and rec["orientation"].shape == (5, 4, 4)
        assert rec["force"].shape == (5, 4, 3) and rec["sinkage"].shape == (5, 4)
        assert rec["work_on_rover"].shape == (5, 4)
        first = np.abs(rec["force"][0]).max()
        assert (first == 0.0) if scheme == "jacobi" else (first > 1.0)
        assert rover.time == coupler.time == soil.time == pytest.approx(0.005, abs=1e-15)


def test_constant_drives_name_a_speed_or_torque_that_is_not_one_per_wheel():
    """ConstantSpeed([0.1, 0.2], 4) was numpy's "operands could not be broadcast" (no argument named); a nan
    speed was taken. Each names its argument, the wheel count and the unit."""
    from cosim.controllers import ConstantTorque

    for make, name, values in (
        (ConstantSpeed, "speed", [0.1, 0.2]),
        (ConstantSpeed, "speed", float("nan")),
        (ConstantTorque, "torque", [[1.0]] * 4),
        (ConstantSpeed, "speed", "fast"),
    ):
        with pytest.raises(ValueError, match=rf"{name} must be one finite number \[.*\] or one per wheel \(4\)"):
            make(values, 4)
    assert ConstantSpeed(0.5, 3).speed.tolist() == [0.5] * 3 and ConstantTorque([1, 2], 2).torque.tolist() == [1, 2]


@pytest.mark.parametrize("phase", [1.9, 2.1])
def test_an_explicit_exchange_of_a_mass_on_a_spring_is_stable_to_two_radians_a_step(phase):
    """A wheel of mass m on a linear spring k (no damping, no friction), exchanged Gauss-Seidel: the soil
    averages -k z over the wheel's constant-velocity path, the rig moves exactly under that held force. With
    w = omega H (omega^2 = k / m), the step maps (dz, dv H) by A = [[1 - w^2/2, 1 - w^2/4], [-w^2, 1 - w^2/2]]
    (derived in docs/coupling.md): det A = 1, trace 2 - w^2, so its eigenvalues stay on the unit circle up to
    w = 2 and beyond it one grows as |lambda| = (w^2 - 2 + w sqrt(w^2 - 4)) / 2 a step. The coupled sides
    follow A to rounding; the DEM's coupling_step check (cosim.advice.DEM_BOUNCE_LIMIT) holds 2 rad for it."""
    from cosim.single_wheel import SingleWheelRig

    mass, k, r, g = 1.0, 1.0e4, 0.1, 9.81
    omega = math.sqrt(k / mass)
    h = phase / omega
    rest, nudge = mass * g / k, 1e-9  # the rest sinkage [m] and a nudge that grows to 1/3 of it at most
    soil = SpringDamperTerrain(r, 1, stiffness=k, damping=0.0, friction=0.0, substeps=4)
    rig = SingleWheelRig(mass, r, 0.0, (0.0, 0.0, r - rest - nudge), gravity=(0.0, 0.0, -g))
    coupler = Coupler(soil, rig, h, gravity=(0.0, 0.0, -g))
    steps = 20
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CouplingEnergyWarning)  # the unstable case creates energy, as it should
        records = coupler.run(steps * h)
    rec = stack_records(records)
    deviation = np.c_[rec["position"][:, 0, 2] - (r - rest), rec["linear_velocity"][:, 0, 2] * h]
    w2 = phase**2
    step_map = np.array([[1 - w2 / 2, 1 - w2 / 4], [-w2, 1 - w2 / 2]])
    expected = [np.array([-nudge, 0.0])]
    for _ in range(steps):
        expected.append(step_map @ expected[-1])
    expected = np.array(expected[1:])
    scale = np.abs(expected).max()
    np.testing.assert_allclose(deviation, expected, atol=1e-6 * scale)
    assert (rec["contact_count"] == 1).all()
    growth = (np.abs(expected[-1]).max() / np.abs(expected[-3]).max()) ** 0.5  # two steps: A's sign flips
    if phase < 2.0:
        assert np.abs(deviation[:, 0]).max() < 20 * nudge  # bounded: det 1, eigenvalues on the unit circle
    else:
        lam = (w2 - 2 + phase * math.sqrt(w2 - 4)) / 2
        assert growth == pytest.approx(lam, rel=0.02) and np.abs(deviation[-1, 0]) > 1e4 * nudge
