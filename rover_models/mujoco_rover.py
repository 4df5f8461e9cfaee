"""MuJoCo rover adapter: a RoverSide (cosim.contract) around an MJCF model.

Frames and conventions:
- a wheel is a MuJoCo body; its hub is the body frame origin (data.xpos), its
  orientation data.xquat (w, x, y, z, body -> world);
- velocities come from mj_objectVelocity(mjOBJ_XBODY, flg_local=0): the 6D velocity at
  the body frame origin with world orientation (mjOBJ_BODY would give it at the CoM). cvel
  is NOT used directly: its linear part is the velocity of the point coinciding with the
  subtree CoM of the root, not of the hub;
- data.xfrc_applied holds a world-frame wrench at the body CoM (data.xipos), so the soil
  torque about the hub is shifted: tau_com = tau_hub + (p_hub - p_com) x F. The shift is
  redone at every MuJoCo step (between mj_step1 and mj_step2) because p_hub - p_com
  turns with the body when the CoM is off the hub.

MuJoCo versions: 3.1 to 4.0 give the same physics for everything used here (the
semi-implicit step with implicit actuator damping of 'implicitfast', xfrc_applied,
mj_objectVelocity, mj_step1/mj_step2, velocity actuators); tests/test_rover_mujoco.py
checks it against closed-form answers. 4.0 rounds the rotation matrices (xmat, ximat)
differently in the last bit, so a rover on a granular bed follows another, equally
valid, trajectory: compare coupled runs statistically, never bit for bit across releases.
Keep actuatorfrcrange off the wheel joints: from 4.0 an actuator saturated by it loses
its implicit damping, so a stiff motor then needs a smaller timestep.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import mujoco
import numpy as np
from numpy.typing import ArrayLike

from cosim.contract import RoverDiverged, WheelKinematics, WheelWrench
from soil.errors import ArgumentError


def load_model(model: str | os.PathLike | mujoco.MjModel) -> mujoco.MjModel:
    """An MjModel from an MjModel, an MJCF file path or an MJCF string."""
    if isinstance(model, mujoco.MjModel):
        return model
    text = os.fspath(model)
    inline = text.lstrip().startswith("<")
    if not inline and not os.path.exists(text):
        raise FileNotFoundError(f"MJCF file not found: {text}")
    try:
        return mujoco.MjModel.from_xml_string(text) if inline else mujoco.MjModel.from_xml_path(text)
    except ValueError as error:  # MuJoCo's message spans lines (error, element, line): one line, the file named
        where = "the MJCF text" if inline else text
        raise ArgumentError(
            f"{where}: {'; '.join(filter(None, (line.strip() for line in str(error).splitlines())))}"
        ) from error


class MujocoRover:
    """A RoverSide backed by MuJoCo.

    Args:
        model: MjModel, MJCF path or MJCF string.
        wheel_bodies: body names of the wheels; their order is the wheel order everywhere.
        gravity: optional gravity [m/s^2], shape (3,), written to model.opt.gravity.
        wheel_actuators: names of the velocity actuators driving the wheels, one per
            wheel (None entries allowed); None finds, for each wheel, the actuator acting
            on the wheel body's hinge joint.

    Drive modes: `set_wheel_speeds` writes the velocity actuators' ctrl [rad/s];
    `set_wheel_torques` switches to torque mode: the velocity actuators' gains are set to
    zero and the torque [N m] is applied on the wheel hinge (data.qfrc_applied).
    """

    def __init__(
        self,
        model,
        wheel_bodies: Sequence[str],
        gravity: Sequence[float] | None = None,
        wheel_actuators: Sequence[str | None] | None = None,
    ):
        self.model = load_model(model)
        self.data = mujoco.MjData(self.model)
        if isinstance(wheel_bodies, str):  # a name where the list goes would be read letter by letter
            raise ArgumentError(f"wheel_bodies must be a list of body names: [{wheel_bodies!r}]")
        self.wheel_names = list(wheel_bodies)
        """Wheel body names, in wheel order."""
        if not self.wheel_names:
            raise ArgumentError("wheel_bodies is empty: name at least one wheel body")
        twice = sorted({n for n in self.wheel_names if self.wheel_names.count(n) > 1})
        if twice:  # one body's wrench would be written once per name, the last one kept
            raise ArgumentError(f"wheel_bodies names {twice} more than once; each wheel body once")
        if not (math.isfinite(self.model.opt.timestep) and self.model.opt.timestep > 0):
            raise ArgumentError(f"the MJCF's option timestep must be > 0 [s], got {self.model.opt.timestep}")
        bodies = [self.model.body(i).name for i in range(self.model.nbody)]
        missing = [n for n in self.wheel_names if n not in bodies]
        if missing:
            raise KeyError(f"wheel bodies {missing} not in the model; its bodies are: {bodies}")
        self.wheel_body_ids = np.array([bodies.index(n) for n in self.wheel_names])
        """MuJoCo body ids of the wheels [-], shape (wheel_count,)."""
        self.timestep = float(self.model.opt.timestep)
        """MuJoCo's own time step [s]."""

        self._hinge_dof = [self._find_hinge_dof(b) for b in self.wheel_body_ids]
        self._actuators = self._find_actuators(wheel_actuators)
        self._actuator_gains = {
            a: (self.model.actuator_gainprm[a].copy(), self.model.actuator_biasprm[a].copy())
            for a in self._actuators
            if a is not None
        }
        self.drive_mode = "speed"
        """'speed' (velocity actuators) or 'torque' (hinge torques)."""
        self.wheel_torques = np.zeros(len(self.wheel_names))
        """Commanded hinge torques in torque mode [N m], shape (wheel_count,)."""
        self.hub_wrenches = np.zeros((len(self.wheel_names), 6))
        """Held soil wrench per wheel, world frame: force [N] then torque about the hub [N m],
        shape (wheel_count, 6)."""

        if gravity is not None:
            self.set_gravity(gravity)
        mujoco.mj_forward(self.model, self.data)

    # --- lookups ------------------------------------------------------------------

    def _find_hinge_dof(self, body: int) -> int | None:
        """Dof index of the (single) hinge joint of a wheel body, None if it has none."""
        for j in range(self.model.body_jntadr[body], self.model.body_jntadr[body] + self.model.body_jntnum[body]):
            if self.model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                return int(self.model.jnt_dofadr[j])
        return None

    def _find_actuators(self, names) -> list[int | None]:
        actuators = [self.model.actuator(i).name for i in range(self.model.nu)]
        if names is not None:
            if len(names) != len(self.wheel_names):
                raise ArgumentError(f"{len(names)} wheel_actuators for {len(self.wheel_names)} wheels")
            out = []
            for n in names:
                if n is not None and n not in actuators:
                    raise KeyError(f"actuator {n!r} not in the model; its actuators are: {actuators}")
                out.append(None if n is None else actuators.index(n))
            return out
        out = []
        for body in self.wheel_body_ids:
            joints = range(self.model.body_jntadr[body], self.model.body_jntadr[body] + self.model.body_jntnum[body])
            found = [
                a
                for a in range(self.model.nu)
                if self.model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
                and self.model.actuator_trnid[a, 0] in joints
                # a wheel turns about its hinge: an actuator on a slide joint of the wheel body drives no wheel
                and self.model.jnt_type[self.model.actuator_trnid[a, 0]] == mujoco.mjtJoint.mjJNT_HINGE
            ]
            out.append(found[0] if found else None)
        return out

    # --- RoverSide ---------------------------------------------------------------------

    @property
    def time(self) -> float:
        """Rover time [s]."""
        return float(self.data.time)

    def set_gravity(self, gravity: Sequence[float]) -> None:
        vector = np.asarray(gravity, dtype=np.float64).reshape(-1)
        if vector.shape != (3,) or not np.all(np.isfinite(vector)):  # nan read later as "became unstable"
            raise ArgumentError(f"gravity must be 3 finite numbers [m/s^2], got {gravity!r}")
        self.model.opt.gravity[:] = vector

    def wheel_kinematics(self) -> list[WheelKinematics]:
        out = []
        vel = np.zeros(6)
        for b in self.wheel_body_ids:
            # [angular(3), linear(3)] at the body frame origin (the hub), world orientation.
            # mjOBJ_XBODY, not mjOBJ_BODY: the latter is centred on the CoM (xipos).
            mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_XBODY, int(b), vel, 0)
            out.append(
                WheelKinematics(
                    position=self.data.xpos[b].copy(),
                    orientation=self.data.xquat[b].copy(),
                    linear_velocity=vel[3:].copy(),
                    angular_velocity=vel[:3].copy(),
                )
            )
        return out

    def apply_wheel_wrenches(self, wrenches: Sequence[WheelWrench]) -> None:
        if len(wrenches) != len(self.wheel_names):
            raise ArgumentError(f"{len(wrenches)} wrenches for {len(self.wheel_names)} wheels")
        for i, w in enumerate(wrenches):
            self.hub_wrenches[i, :3] = w.force
            self.hub_wrenches[i, 3:] = w.torque
        self._write_xfrc()

    def _write_xfrc(self) -> None:
        """Hub wrenches -> data.xfrc_applied (at the CoM) using the current xpos/xipos. Every wheel at
        once, the cross product written out (np.cross's own products and differences, in its order:
        the same bits; np.cross costs more than a MuJoCo step of a small rover)."""
        bodies = self.wheel_body_ids
        force = self.hub_wrenches[:, :3]
        arm = self.data.xpos[bodies] - self.data.xipos[bodies]  # p_hub - p_com
        moment = np.empty_like(arm)
        moment[:, 0] = arm[:, 1] * force[:, 2] - arm[:, 2] * force[:, 1]
        moment[:, 1] = arm[:, 2] * force[:, 0] - arm[:, 0] * force[:, 2]
        moment[:, 2] = arm[:, 0] * force[:, 1] - arm[:, 1] * force[:, 0]
        self.data.xfrc_applied[bodies, :3] = force
        self.data.xfrc_applied[bodies, 3:] = self.hub_wrenches[:, 3:] + moment
        if self.drive_mode == "torque":
            for i, dof in enumerate(self._hinge_dof):
                if dof is not None:
                    self.data.qfrc_applied[dof] = self.wheel_torques[i]

    def advance(self, t_end: float) -> None:
        """Step MuJoCo with its own timestep until exactly t_end [s] (the last step shortened)."""
        t_end = float(t_end)
        if not math.isfinite(t_end):  # nan set the time to nan, inf stepped for ever
            raise ArgumentError(f"t_end must be a finite time [s], got {t_end}")
        if t_end < self.data.time - 1e-12:
            raise ArgumentError(f"cannot advance backwards: rover time {self.data.time}, t_end {t_end}")
        # A remainder below this is rounding, not a step worth taking.
        eps = 1e-9 * self.timestep
        split = self.model.opt.integrator != mujoco.mjtIntegrator.mjINT_RK4
        try:
            while t_end - self.data.time > eps:
                dt = min(self.timestep, t_end - self.data.time)
                if t_end - self.data.time - dt <= eps:
                    dt = t_end - self.data.time  # land on t_end, not one rounding error short
                self.model.opt.timestep = dt
                before = self.data.time
                if split:
                    mujoco.mj_step1(self.model, self.data)  # positions/velocities -> xpos, xipos
                    self._write_xfrc()
                    mujoco.mj_step2(self.model, self.data)
                else:
                    self._write_xfrc()
                    mujoco.mj_step(self.model, self.data)
                if not self.data.time > before:  # MuJoCo resets an unstable model to its start, time 0 too
                    raise RoverDiverged(
                        f"the MuJoCo model became unstable at t = {before:.6g} s (accelerations not finite or "
                        f"huge: MuJoCo reset it); its step {self.timestep:g} s, or the commands or wrenches on it, "
                        "are too large for it"
                    )
        finally:
            self.model.opt.timestep = self.timestep
        self.data.time = t_end
        # After mj_step, xpos & co describe the state before the step: refresh them so
        # wheel_kinematics() reads the state at t_end.
        mujoco.mj_forward(self.model, self.data)

    # --- drive commands --------------------------------------------------------------------

    def set_wheel_speeds(self, speeds: ArrayLike) -> None:
        """Velocity-actuator targets [rad/s], shape (wheel_count,); switches to speed mode."""
        targets = np.asarray(speeds, dtype=np.float64).reshape(-1)
        if targets.shape != (len(self.wheel_names),):
            raise ArgumentError(f"{targets.size} speeds for {len(self.wheel_names)} wheels")
        if any(a is None for a in self._actuators):
            raise ArgumentError(
                f"no velocity actuator found for wheels "
                f"{[n for n, a in zip(self.wheel_names, self._actuators) if a is None]}"
            )
        if self.drive_mode != "speed":
            for a, (gain, bias) in self._actuator_gains.items():
                self.model.actuator_gainprm[a] = gain
                self.model.actuator_biasprm[a] = bias
            for dof in self._hinge_dof:
                if dof is not None:
                    self.data.qfrc_applied[dof] = 0.0
            self.drive_mode = "speed"
        for actuator, s in zip(self._actuators, targets):
            self.data.ctrl[actuator] = s

    def set_wheel_torques(self, torques: ArrayLike) -> None:
        """Hinge torques [N m], shape (wheel_count,); switches to torque mode (motors off)."""
        commands = np.asarray(torques, dtype=np.float64).reshape(-1)
        if commands.shape != (len(self.wheel_names),):
            raise ArgumentError(f"{commands.size} torques for {len(self.wheel_names)} wheels")
        missing = [n for n, d in zip(self.wheel_names, self._hinge_dof) if d is None]
        if missing:
            raise ArgumentError(f"wheels {missing} have no hinge joint to apply a torque on")
        if self.drive_mode != "torque":
            for a in self._actuator_gains:
                # A velocity actuator is kv (ctrl - qvel): zero gain and bias switch it off.
                self.model.actuator_gainprm[a] = 0.0
                self.model.actuator_biasprm[a] = 0.0
            self.drive_mode = "torque"
        self.wheel_torques[:] = commands
        self._write_xfrc()

    # --- the rover body, placement and checkpoints -------------------------------------

    def body_id(self, name: str | None = None) -> int:
        """MuJoCo id of body `name`; None: the rover's base, the child of the world that carries the first wheel."""
        if name is not None:
            bodies = [self.model.body(i).name for i in range(self.model.nbody)]
            if name not in bodies:
                raise KeyError(f"body {name!r} not in the model; its bodies are: {bodies}")
            return bodies.index(name)
        body = int(self.wheel_body_ids[0])
        while self.model.body_parentid[body] != 0:
            body = int(self.model.body_parentid[body])
        return body

    @property
    def fixed_to_world(self) -> bool:
        """Whether some wheel hangs from the world with no joint to move it but its spin: none on the bodies
        between it and the world, and none on its own body besides hinges. Such a wheel could only spin in
        place, and the rover never drive."""

        def moves(wheel: int) -> bool:
            own = range(self.model.body_jntadr[wheel], self.model.body_jntadr[wheel] + self.model.body_jntnum[wheel])
            if any(self.model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE for j in own):
                return True  # a slide or free joint of the wheel body itself (a compact rig)
            body = int(self.model.body_parentid[wheel])
            while body != 0:
                if self.model.body_jntnum[body] > 0:
                    return True
                body = int(self.model.body_parentid[body])
            return False

        return not all(moves(int(wheel)) for wheel in self.wheel_body_ids)

    def body_kinematics(self, body: int) -> WheelKinematics:
        """Pose and velocity of body `body` (an id) at its frame origin, world frame (as wheel_kinematics)."""
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_XBODY, int(body), vel, 0)
        return WheelKinematics(
            self.data.xpos[body].copy(), self.data.xquat[body].copy(), vel[3:].copy(), vel[:3].copy()
        )

    def move_base(self, translation: ArrayLike, yaw: float = 0.0, pivot: ArrayLike | None = None) -> None:
        """Move the whole rover rigidly before it starts: turn it by `yaw` [rad] about the vertical through
        `pivot` [m] (default: the base body), then shift it by `translation` [m], shape (3,).

        Free-floating bases move through their joint position (qpos); a base mounted on the world
        by other joints (a test rig on slides) moves through its body frame (model.body_pos)."""
        shift = np.asarray(translation, dtype=np.float64).reshape(3)
        base = self.body_id()
        centre = self.data.xpos[base].copy() if pivot is None else np.asarray(pivot, dtype=np.float64).reshape(3)
        turn = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
        rotation = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        for body in range(1, self.model.nbody):
            if self.model.body_parentid[body] != 0:
                continue
            free = [
                j
                for j in range(
                    self.model.body_jntadr[body], self.model.body_jntadr[body] + self.model.body_jntnum[body]
                )
                if self.model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
            ]
            if free:
                adr = int(self.model.jnt_qposadr[free[0]])
                position, quaternion = self.data.qpos[adr : adr + 3], self.data.qpos[adr + 3 : adr + 7]
            else:
                position, quaternion = self.model.body_pos[body], self.model.body_quat[body]
            position[:] = centre + rotation @ (position - centre) + shift
            out = np.zeros(4)
            mujoco.mju_mulQuat(out, turn, np.array(quaternion, dtype=np.float64))
            quaternion[:] = out
        mujoco.mj_forward(self.model, self.data)

    def state_dict(self) -> dict:
        """The rover's checkpoint state: MuJoCo's integration state (mj_getState, mjSTATE_INTEGRATION:
        time, qpos, qvel, act, ctrl, warm start, applied forces), the drive mode and the held wrenches."""
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        state = np.empty(mujoco.mj_stateSize(self.model, spec))
        mujoco.mj_getState(self.model, self.data, state, spec)
        return {
            "mujoco_state": state,
            "torque_mode": self.drive_mode == "torque",
            "wheel_torques": self.wheel_torques.copy(),
            "hub_wrenches": self.hub_wrenches.copy(),
        }

    def state_dict_units(self) -> dict[str, str]:
        """{key of state_dict(): its unit}."""
        return {
            "mujoco_state": "MuJoCo's mjSTATE_INTEGRATION vector: time [s], qpos, qvel, act, ctrl, ... in SI",
            "torque_mode": "1",
            "wheel_torques": "N m",
            "hub_wrenches": "by column: N (3), N m (3)",
        }

    def load_state_dict(self, state: dict) -> None:
        if bool(state["torque_mode"]):
            self.set_wheel_torques(np.asarray(state["wheel_torques"]))
        elif self.drive_mode != "speed":
            self.set_wheel_speeds(np.zeros(len(self.wheel_names)))
        self.hub_wrenches[:] = np.asarray(state["hub_wrenches"])
        mujoco.mj_setState(
            self.model,
            self.data,
            np.asarray(state["mujoco_state"], dtype=np.float64),
            mujoco.mjtState.mjSTATE_INTEGRATION,
        )
        mujoco.mj_forward(self.model, self.data)

    # --- conveniences ---------------------------------------------------------------

    @property
    def drives(self) -> dict:
        """{'speed': every wheel has a velocity actuator, 'torque': every wheel has a hinge}."""
        return {
            "speed": all(a is not None for a in self._actuators),
            "torque": all(d is not None for d in self._hinge_dof),
        }

    @property
    def total_mass(self) -> float:
        """Mass of all bodies [kg]."""
        return float(self.model.body_mass.sum())

    def wheel_spin_rates(self) -> np.ndarray:
        """Hinge rates of the wheels [rad/s], shape (wheel_count,) (NaN without a hinge)."""
        return np.array([np.nan if d is None else self.data.qvel[d] for d in self._hinge_dof])
