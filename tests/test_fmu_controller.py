"""FmuController with a proportional slip-controller FMU built here (pythonfmu, FMI 2.0)."""

from __future__ import annotations

import textwrap
import zipfile

import numpy as np
import pytest

pytest.importorskip("fmpy")
pytest.importorskip("pythonfmu")

from cosim.contract import WheelKinematics, WheelWrench  # noqa: E402
from cosim.controllers import Controller, DriveCommand  # noqa: E402
from cosim.fmu_controller import FmuController  # noqa: E402
from rover_models.fmu_rover import FmuVariableError  # noqa: E402

# The controller FMU: per wheel i, with v = wheel_i.velocity.x, omega = wheel_i.angular_velocity.y
# and parameters s* (target_slip), r (wheel_radius), k (gain):
#     speed_command  = v / ((1 - s*) r) + k (v - (1 - s*) omega r) / r
#     torque_command = -r force.x          (only with torque=True; checks the wrench inputs)
# Direct feedthrough, no state. A distinct module/class name per build: pythonfmu imports
# the slave module by name into this (shared) interpreter.
_SOURCE = """
from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real

WHEELS = {wheels}
TORQUE = {torque}


class {name}(Fmi2Slave):
    author = "regolith-cosim tests"
    description = "Proportional slip controller"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.p = {{"target_slip": 0.2, "wheel_radius": 0.1, "gain": 1.0}}
        self.u = {{}}
        for i in range(WHEELS):
            self.u[f"wheel_{{i}}.velocity.x"] = 0.0
            self.u[f"wheel_{{i}}.angular_velocity.y"] = 0.0
            if TORQUE:
                self.u[f"wheel_{{i}}.force.x"] = 0.0

        def reg(name, store, causality, variability):
            self.register_variable(Real(name, causality=causality, variability=variability,
                                        getter=lambda: store[name], setter=lambda v: store.__setitem__(name, v)),
                                   nested=False)

        for name in self.p:
            reg(name, self.p, Fmi2Causality.parameter, Fmi2Variability.fixed)
        for name in self.u:
            reg(name, self.u, Fmi2Causality.input, Fmi2Variability.continuous)
        for i in range(WHEELS):
            self.register_variable(Real(f"wheel_{{i}}.speed_command", causality=Fmi2Causality.output,
                                        variability=Fmi2Variability.continuous,
                                        getter=lambda i=i: self._speed(i)), nested=False)
            if TORQUE:
                self.register_variable(Real(f"wheel_{{i}}.torque_command", causality=Fmi2Causality.output,
                                            variability=Fmi2Variability.continuous,
                                            getter=lambda i=i: (-self.p["wheel_radius"]
                                                                * self.u[f"wheel_{{i}}.force.x"])),
                                       nested=False)

    def _speed(self, i):
        s, r, k = self.p["target_slip"], self.p["wheel_radius"], self.p["gain"]
        v, omega = self.u[f"wheel_{{i}}.velocity.x"], self.u[f"wheel_{{i}}.angular_velocity.y"]
        return v / ((1 - s) * r) + k * (v - (1 - s) * omega * r) / r

    def do_step(self, current_time, step_size):
        return True
"""


def _build(folder, name, wheels, torque):
    from pythonfmu.builder import FmuBuilder

    script = folder / f"{name}.py"
    script.write_text(textwrap.dedent(_SOURCE.format(name=name, wheels=wheels, torque=torque)))
    return FmuBuilder.build_FMU(script, dest=folder, needsExecutionTool=False)


def _rename_in_model_description(src, dst, old, new):
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                assert old.encode() in data
                data = data.replace(old.encode(), new.encode())
            zout.writestr(item, data)
    return dst


@pytest.fixture(scope="module")
def fmus(tmp_path_factory):
    folder = tmp_path_factory.mktemp("controller_fmus")
    one = _build(folder, "SlipFmuOne", wheels=1, torque=False)
    return {
        "one": one,
        "two": _build(folder, "SlipFmuTwo", wheels=2, torque=True),
        # Same FMU, command output renamed: the controller finds no wheel_0.speed_command.
        "no_command": _rename_in_model_description(
            one, folder / "NoCommand.fmu", '"wheel_0.speed_command"', '"wheel_0.speed_cmd"'
        ),
    }


def _slip_formula(v, omega, s_star, r, k):
    """The proportional slip controller, written out here independently of the FMU."""
    return v / ((1 - s_star) * r) + k * (v - (1 - s_star) * omega * r) / r


def _kin(v, w):
    return WheelKinematics(position=(0.3, -0.1, 0.09), orientation=(1, 0, 0, 0), linear_velocity=v, angular_velocity=w)


def test_fmu_controller_returns_the_formula(fmus):
    """Two wheels, parameters overridden: the commands equal the formula per wheel, the
    off-axis components of the states do not leak in, and the wrench inputs arrive."""
    s_star, r, k = 0.3, 0.12, 2.5
    start = {"target_slip": s_star, "wheel_radius": r, "gain": k}
    states = [  # (t, [(v, omega) per wheel]) with off-axis components that must be ignored
        (0.0, [((0.5, 0.2, -0.1), (0.4, 6.0, -1.0)), ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))]),
        (0.01, [((1.25, -0.3, 0.05), (0.1, 14.0, 0.2)), ((-0.4, 0.0, 0.0), (0.0, -3.0, 0.0))]),
        (0.02, [((2.0, 0.0, 0.0), (0.0, 20.0, 0.0)), ((0.7, 1.0, 1.0), (1.0, 9.5, 1.0))]),
        (0.02, [((0.3, 0.0, 0.0), (0.0, 5.0, 0.0)), ((0.7, 0.0, 0.0), (0.0, 0.0, 0.0))]),  # same t: no step
    ]
    with FmuController(fmus["two"], 2, mode="speed", start_values=start) as controller:
        assert isinstance(controller, Controller)
        assert controller.input_names == [
            "wheel_0.velocity.x",
            "wheel_0.angular_velocity.y",
            "wheel_0.force.x",
            "wheel_1.velocity.x",
            "wheel_1.angular_velocity.y",
            "wheel_1.force.x",
        ]
        for t, wheels in states:
            kin = [_kin(v, w) for v, w in wheels]
            command = controller(t, kin, [WheelWrench(), WheelWrench()])
            assert isinstance(command, DriveCommand) and command.mode == "speed"
            expected = [_slip_formula(v[0], w[1], s_star, r, k) for v, w in wheels]
            np.testing.assert_allclose(command.values, expected, rtol=1e-14, atol=1e-14)
            assert controller.time == t
        with pytest.raises(ValueError, match="backwards"):
            controller(0.01, kin, [WheelWrench(), WheelWrench()])
    assert controller.fmu is None  # closed by the with block

    # Torque mode on the same FMU: torque_command = -r force.x, from the wrenches.
    with FmuController(fmus["two"], 2, mode="torque", start_values={"wheel_radius": r}) as controller:
        kin = [_kin((0, 0, 0), (0, 0, 0))] * 2
        wrenches = [WheelWrench(force=[12.0, 1, 50]), WheelWrench(force=[-3.5, 0, 40])]
        command = controller(0.0, kin, wrenches)
        assert command.mode == "torque"
        np.testing.assert_allclose(command.values, [-r * 12.0, r * 3.5], rtol=1e-14)
    with pytest.raises(ValueError, match="choose mode"):
        FmuController(fmus["two"], 2)  # both command kinds: ambiguous


def test_missing_command_outputs_are_a_clear_error(fmus):
    with pytest.raises(FmuVariableError) as err:
        FmuController(fmus["no_command"], 1)
    message = str(err.value)
    # Names what is missing and lists the FMU's variables (the renamed one among them).
    assert "missing wheel_0.speed_command" in message
    assert "wheel_0.speed_cmd (output, Real)" in message and "wheel_0.velocity.x (input, Real)" in message
    # Wheel count mismatch: the scene has 3 wheels, the FMU commands 2.
    with pytest.raises(
        FmuVariableError, match=r"missing wheel_2\.speed_command.*the FMU has: .*wheel_1\.speed_command"
    ):
        FmuController(fmus["two"], 3, mode="speed")
    # ... or 1 wheel while the FMU commands 2.
    with pytest.raises(FmuVariableError, match=r"unexpected wheel_1\.speed_command"):
        FmuController(fmus["two"], 1, mode="speed")
    # Wrong number of wheel states at call time.
    controller = FmuController(fmus["one"])
    assert controller.wheel_count == 1 and controller.mode == "speed"
    with pytest.raises(ValueError, match="for a controller of 1 wheel"):
        controller(0.0, [_kin((0, 0, 0), (0, 0, 0))] * 2, [WheelWrench()] * 2)
    controller.close()


def test_fmu_slip_controller_holds_target_slip_on_the_rig(fmus):
    """Single-wheel MuJoCo rig on the slip-law terrain (as test_coupler's SlipController
    test), driven by the FMU's proportional slip controller, s* = 0.2.

    The rig starts rolling at v0 = 0.5 m/s at the target slip (the formula commands 0 at
    rest). A P controller keeps a steady error: the velocity motor lags its command by
    the traction torque / kv (about 0.25 rad/s) and the hub gains a H per step, so the
    slip sits slightly below s*, the offset shrinking as 1/v. Band: |s - s*| < 0.01 after
    0.3 s; the traction is then mu (1 - exp(-s/s0)) F_z with s within that band."""
    pytest.importorskip("mujoco")
    import mujoco

    from cosim.coupler import Coupler, stack_records
    from cosim.terrain import SpringDamperTerrain
    from rover_models.mjcf import single_wheel_rig_xml
    from rover_models.mujoco_rover import MujocoRover

    g, mu, s0, s_star, r, v0 = 9.81, 0.6, 0.1, 0.2, 0.1, 0.5
    rover = MujocoRover(single_wheel_rig_xml(wheel_radius=r), ["wheel"])
    rover.data.qvel[rover.model.joint("carriage_x").dofadr[0]] = v0
    rover.data.qvel[rover.model.joint("wheel_hinge").dofadr[0]] = v0 / ((1 - s_star) * r)
    mujoco.mj_forward(rover.model, rover.data)
    soil = SpringDamperTerrain(r, 1, traction="slip", friction=mu, slip_scale=s0, slip_velocity=0.05, substeps=2)
    with FmuController(fmus["one"], 1, start_values={"target_slip": s_star, "wheel_radius": r, "gain": 1.0}) as ctl:
        coupler = Coupler(soil, rover, 1e-3, gravity=(0, 0, -g), controller=ctl)
        rec = stack_records(coupler.run(1.0))
    late = rec["time"] > 0.3
    # Slip measured from the rover's kinematics.
    v = rec["linear_velocity"][:, 0, 0]
    slip = 1 - v / (rec["angular_velocity"][:, 0, 1] * r)
    assert np.abs(slip[late] - s_star).max() < 0.01
    assert v[-1] > v0 + 2.0  # it did drive: about 3.4 m/s^2 for 1 s
    traction = rec["force"][late, 0, 0] / rec["force"][late, 0, 2]
    np.testing.assert_allclose(traction, mu * (1 - np.exp(-slip[late] / s0)), rtol=1e-3)
