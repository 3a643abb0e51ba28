"""The simulation core: MuJoCo steps the arm under the joint impedance law.

LeRobot-style robot interface (connect/read/send/disconnect is the node's business;
here: ``reset``, ``read``, ``apply``, ``step``). The per-physics-step work runs inside
MuJoCo: affine actuators evaluate tau = tau_ff + kp (q_ref - q) + kd (dq_ref - dq),
saturated at the effort limits, and ``mj_step(..., nstep)`` advances many steps per call.
The latest command is held between commands.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import mujoco
import numpy as np
from mujoco import rollout

from dammrl_core.robot import RobotDescription
from dammrl_core.robot.scene import SENSOR_LAYOUT, SceneLayout, build_scene
from dammrl_core.sim.settings import SimSettings
from dammrl_core.state import JointCommand, RobotState

GOVERNOR_ENGAGES = 0.8
"""The speed governor looks at a joint from this share of its governed speed on."""
GOVERNOR_SPAN = 0.05
"""The governor's full torque acts this far (a share of the governed speed) past it."""


ROLLOUT_PERIODS = 16
"""From this many control periods on, a stretch is stepped in one MuJoCo rollout (below,
a Python loop of ``mj_step`` costs less than the rollout's own work)."""


@dataclass(frozen=True)
class Stretch:
    """Control periods stepped in one go (``Simulation.coast``): at each period's end, the
    time (m,), the sensor row as ``read`` returns it (m, nsensordata: encoder offsets and
    noise added) and the noise-free end-effector position (m, 3)."""

    times: np.ndarray
    rows: np.ndarray
    true_ee: np.ndarray
    sensordata: np.ndarray  # MuJoCo's own rows (for a rewind)


class Simulation:
    """A MuJoCo scene of the arm, a table and the goal button."""

    def __init__(
        self,
        settings: SimSettings,
        robot: RobotDescription,
        layout: SceneLayout,
        seed: int | np.random.Generator | None = None,
    ) -> None:
        """``layout.timestep_s`` is replaced by ``settings.timestep_s``; ``seed`` seeds the
        randomisation and the sensor noise (each episode reseeds ``rng``, see ``reset``)."""
        self.settings = settings
        self.robot = robot
        self.layout = replace(layout, timestep_s=settings.timestep_s)
        self.model = build_scene(self.robot, self.layout)
        self.data = mujoco.MjData(self.model)
        self.rng = np.random.default_rng(seed)
        # restored at every reset: the gains a command latches included, so the state a
        # reset reads (its torque) is the same whatever reach ran before in this process
        restored = ("body_mass", "body_inertia", "dof_damping", "dof_frictionloss", "body_pos",
                    "actuator_biasprm")  # fmt: skip
        self._nominal = {name: getattr(self.model, name).copy() for name in restored}
        self._n = len(self.robot.joint_names)
        self.joint_offset = np.zeros(self._n)  # encoder zero offsets [rad] (randomisation)
        self._button_body = self.model.body("button").id
        self._arm_bodies = np.arange(1, self.model.body("button").id)
        self._noise_std = self._sensor_noise_std()
        self._sensor_slices = tuple(
            SENSOR_LAYOUT[k] for k in ("q", "dq", "tau", "ee_pos", "ee_vel", "button")
        )
        self._last_command: JointCommand | None = None
        self._govern_speed = settings.speed_governor_fraction * robot.dq_max
        self._govern_from = GOVERNOR_ENGAGES * self._govern_speed
        self._governor_gain = robot.tau_max / (GOVERNOR_SPAN * self._govern_speed)
        self._state = np.zeros(mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_FULLPHYSICS))
        self._roller = rollout.Rollout(nthread=0)  # rollouts in this thread, checks skipped
        integration = mujoco.mjtState.mjSTATE_INTEGRATION
        self._coast_state = np.zeros(mujoco.mj_stateSize(self.model, integration))
        self._coast_noise: Mapping[str, Any] = {}  # the noise stream where a stretch began

    @property
    def timestep_s(self) -> float:
        return float(self.model.opt.timestep)

    @property
    def applied(self) -> JointCommand | None:
        """The command MuJoCo is applying (after the arm's caps), None before any."""
        return self._last_command

    @property
    def t_s(self) -> float:
        return float(self.data.time)

    def reset(
        self,
        q: np.ndarray,
        button_xy: tuple[float, float],
        rng: np.random.Generator | None = None,
    ) -> RobotState:
        """Arm at rest at ``q`` [rad], button centred under ``button_xy`` [m], time 0.

        ``rng`` (an episode's ``seed_streams(seed).sim``) draws this episode's arm and
        sensor noise: every composition reseeds here, so a seed gives the same arm.
        """
        if rng is not None:
            self.rng = rng
        mujoco.mj_resetData(self.model, self.data)
        self._last_command = None
        self._randomize()
        self.place_button(button_xy)
        self.data.qpos[: self._n] = q - self.joint_offset  # the encoders read q
        mujoco.mj_forward(self.model, self.data)
        return self.read()

    def place_button(self, button_xy: tuple[float, float]) -> None:
        """Put the button centred under ``button_xy`` [m] on the table."""
        self.model.body_pos[self._button_body, :2] = button_xy

    def apply(self, command: JointCommand) -> None:
        """Latch a joint command; MuJoCo applies it at every step until the next one."""
        last, self._last_command = self._last_command, command
        if command is last:
            return
        if last is None or command.kp is not last.kp or command.kd is not last.kd:
            self.model.actuator_biasprm[: self._n, 1] = -command.kp
            self.model.actuator_biasprm[: self._n, 2] = -command.kd
        # the servo holds the angle its encoder reports: q_ref is met at true q_ref - offset
        self.data.ctrl[: self._n] = (
            command.tau_ff
            + command.kp * (command.q_ref - self.joint_offset)
            + command.kd * command.dq_ref
        )

    def step(self, n_steps: int) -> None:
        """Advance ``n_steps`` physics steps in one MuJoCo call."""
        mujoco.mj_step(self.model, self.data, nstep=n_steps)

    def step_governed(self, n_steps: int) -> None:
        """Advance ``n_steps`` physics steps with the drives' speed governor (the bus's arm,
        which takes commands from whoever holds the controller's role): at every step a
        joint near ``speed_governor_fraction`` of its velocity limit gets no torque that
        would speed it up further, as a drive's velocity limit does (the soft limits of
        ros_control, k_v (v_max - |dq|)); below it the law is untouched (bitwise the
        same as ``step``)."""
        n = self._n
        for _ in range(n_steps):
            dq = self.data.qvel[:n]
            if np.logical_or.reduce(np.abs(dq) > self._govern_from):
                self._governed_step(dq)
            else:
                mujoco.mj_step(self.model, self.data)

    def _governed_step(self, dq: np.ndarray) -> None:
        n, ctrl = self._n, self.data.ctrl[: self._n].copy()
        q = self.data.qpos[:n]
        bias = self.model.actuator_biasprm[:n]
        force = ctrl + bias[:, 1] * q + bias[:, 2] * dq
        low = -self._governor_gain * (dq + self._govern_speed)
        high = -self._governor_gain * (dq - self._govern_speed)
        governed = np.clip(force, low, high)
        if np.array_equal(governed, force):  # far from the bound: the law untouched
            mujoco.mj_step(self.model, self.data)
            return
        self.data.ctrl[:n] = governed - bias[:, 1] * q - bias[:, 2] * dq
        mujoco.mj_step(self.model, self.data)
        self.data.ctrl[:n] = ctrl  # the command stays latched

    def read(self) -> RobotState:
        """The arm's state from MuJoCo's sensors, with sensor noise when randomisation is on.

        MuJoCo evaluates sensors before integrating, so values are one physics step old
        at most (as on hardware, where state is sampled before the command is applied).
        """
        raw = self.data.sensordata.copy()
        true_ee = raw[self._sensor_slices[3]].copy()
        raw[self._sensor_slices[0]] += self.joint_offset
        if self.settings.randomization.enabled:
            raw += self._noise_std * self.rng.standard_normal(raw.size)
        return self.state_from_sensors(float(self.data.time), raw, true_ee)

    def state_from_sensors(
        self, t_s: float, raw: np.ndarray, true_ee: np.ndarray | None = None
    ) -> RobotState:
        """A RobotState over one sensordata vector (see SENSOR_LAYOUT); no copy.
        ``true_ee``: the noise-free end-effector position, when known."""
        q, dq, tau, ee_pos, ee_vel, button = self._sensor_slices
        travel = -float(raw[button][0])
        return RobotState(
            t_s=t_s,
            q=raw[q],
            dq=raw[dq],
            tau=raw[tau],
            ee_pos=raw[ee_pos],
            ee_vel=raw[ee_vel],
            button_pressed=travel >= self.settings.button_press_travel_m,
            button_travel_m=travel,
            ee_pos_true=true_ee,
        )

    def advance(self, n_periods: int, substeps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advance ``n_periods * substeps`` steps under the latched command in one rollout.

        Returns the times (n,) and sensor vectors (n, nsensordata) at the end of each
        period: what ``read`` would have returned there; and the noise-free end-effector
        positions (n, 3). The final state is bitwise the one ``step`` would reach (same
        integrator, solver warm start carried over).
        """
        control = np.repeat(self.data.ctrl[None, :], n_periods * substeps, axis=0)
        times, rows = self._rollout(control, substeps)
        true_ee = rows[:, self._sensor_slices[3]].copy()
        rows[:, self._sensor_slices[0]] += self.joint_offset
        if self.settings.randomization.enabled:
            rows += self._noise_std * self.rng.standard_normal(rows.shape)
        return times, rows, true_ee

    def inputs_of(
        self, q_ref: np.ndarray, dq_ref: np.ndarray, tau_ff: np.ndarray, kp: np.ndarray,
        kd: np.ndarray,
    ) -> np.ndarray:  # fmt: skip
        """The actuator inputs ``apply`` writes for commands with these rows (n, n_joints)
        and gains (the same arithmetic, row by row)."""
        return np.asarray(tau_ff + kp * (q_ref - self.joint_offset) + kd * dq_ref)

    def coast(
        self,
        inputs: np.ndarray,
        substeps: int,
        near: tuple[np.ndarray, float, int] | None = None,
    ) -> Stretch:
        """Step up to ``len(inputs) + 1`` control periods of ``substeps`` steps: the first
        under the latched command, period k under ``inputs[k - 1]`` (the commands' rows,
        ``inputs_of``). With ``near`` (point, radius [m], period k): stop after the first
        period from period k on that ends with the end-effector, as ``read`` reports it
        (noise included), within the radius of the point (or a few ulps beyond): a hint
        only, where the caller expects its next event. ``rewind`` takes the physics and
        the noise back to the end of any period of the stretch: numbers bitwise those of
        ``read`` and ``step`` period by period."""
        periods = len(inputs) + 1
        noisy = self.settings.randomization.enabled
        mujoco.mj_getState(self.model, self.data, self._coast_state,
                           mujoco.mjtState.mjSTATE_INTEGRATION)  # fmt: skip
        if noisy:
            self._coast_noise = self.rng.bit_generator.state
        shape = (periods, self.model.nsensordata)
        noise = self._noise_std * self.rng.standard_normal(shape) if noisy else None
        ee = self._sensor_slices[3]
        raw = np.empty((periods, self.model.nsensordata))
        times = np.empty(periods)
        model, data, step = self.model, self.data, mujoco.mj_step
        ctrl, sensors = data.ctrl[: self._n], data.sensordata
        stepped = periods
        if near is None and periods >= ROLLOUT_PERIODS:
            control = np.repeat(data.ctrl[None, :], periods * substeps, axis=0)
            control[substeps:, : self._n] = np.repeat(inputs, substeps, axis=0)
            times, raw = self._rollout(control, substeps)
        elif near is None:
            for k in range(periods):
                if k:
                    ctrl[:] = inputs[k - 1]
                step(model, data, substeps)
                raw[k] = sensors
                times[k] = data.time
        else:  # the end-effector as read (noise included) against the sphere, in floats
            limit = near[1] ** 2 * (1 + 1e-9)  # a stop a tick early costs a tick, no more
            if noise is None:
                point_noise = [near[0].tolist()] * periods
            else:
                point_noise = (near[0] - noise[:, ee]).tolist()
            i, since = ee.start, near[2]
            for k in range(periods):
                if k:
                    ctrl[:] = inputs[k - 1]
                step(model, data, substeps)
                row = raw[k]
                row[:] = sensors
                times[k] = data.time
                x, y, z = row[i : i + 3].tolist()
                px, py, pz = point_noise[k]
                if (px - x) ** 2 + (py - y) ** 2 + (pz - z) ** 2 <= limit and k >= since:
                    stepped = k + 1
                    break
        raw, times = raw[:stepped], times[:stepped]
        if noisy and stepped < periods:
            self._redraw_noise(stepped)
        rows = raw.copy()
        true_ee = rows[:, ee].copy()
        rows[:, self._sensor_slices[0]] += self.joint_offset
        if noise is not None:
            rows += noise[:stepped]
        return Stretch(times, rows, true_ee, raw)

    def _rollout(self, control: np.ndarray, substeps: int) -> tuple[np.ndarray, np.ndarray]:
        """MuJoCo's rollout from the data's own state (warm start included), one row of
        ``control`` per step: the times and sensor rows at the end of every ``substeps``
        steps; the data is left at the last step (bitwise as ``step`` would leave it)."""
        nstep = len(control)
        mujoco.mj_getState(self.model, self.data, self._state,
                           mujoco.mjtState.mjSTATE_FULLPHYSICS)  # fmt: skip
        states = np.empty((1, nstep, self._state.size))
        sensordata = np.empty((1, nstep, self.model.nsensordata))
        self._roller.rollout(
            [self.model], [self.data], self._state[None], control[None],
            control_spec=mujoco.mjtState.mjSTATE_CTRL.value, skip_checks=True, nstep=nstep,
            initial_warmstart=self.data.qacc_warmstart[None, :].copy(), state=states,
            sensordata=sensordata,
        )  # fmt: skip
        ends = slice(substeps - 1, None, substeps)
        return states[0, ends, 0].copy(), sensordata[0, ends].copy()  # time is first

    def rewind(self, stretch: Stretch, inputs: np.ndarray, substeps: int, periods: int) -> None:
        """Put the physics and the noise stream back to the end of the stretch's period
        ``periods - 1`` (``periods`` of its periods stepped), as if it had ended there."""
        if periods == len(stretch.times):
            return
        mujoco.mj_setState(self.model, self.data, self._coast_state,
                           mujoco.mjtState.mjSTATE_INTEGRATION)  # fmt: skip
        ctrl = self.data.ctrl[: self._n]
        for k in range(periods):
            if k:
                ctrl[:] = inputs[k - 1]
            mujoco.mj_step(self.model, self.data, nstep=substeps)
        self.data.sensordata[:] = stretch.sensordata[periods - 1]
        if self.settings.randomization.enabled:
            self._redraw_noise(periods)

    def latch(self, command: JointCommand) -> None:
        """Note ``command`` as the one in force (its inputs already written by ``coast``)."""
        self._last_command = command

    def _redraw_noise(self, periods: int) -> None:
        """The noise stream as if only ``periods`` rows had been drawn since the stretch
        began (the same numbers, fewer of them)."""
        self.rng.bit_generator.state = self._coast_noise
        self.rng.standard_normal((periods, self.model.nsensordata))

    def _sensor_noise_std(self) -> np.ndarray:
        """Per-entry standard deviation of the sensordata noise (see SENSOR_LAYOUT)."""
        r = self.settings.randomization
        std = np.zeros(self.model.nsensordata)
        std[SENSOR_LAYOUT["q"]] = r.q_noise_rad
        std[SENSOR_LAYOUT["dq"]] = r.dq_noise_rad_per_s
        std[SENSOR_LAYOUT["ee_pos"]] = r.ee_noise_m
        std[SENSOR_LAYOUT["ee_vel"]] = r.ee_vel_noise_m_per_s
        return std

    def _randomize(self) -> None:
        """Restore the nominal model, then perturb it when randomisation is enabled."""
        for name, value in self._nominal.items():
            getattr(self.model, name)[:] = value
        self.joint_offset = np.zeros(self._n)
        randomization = self.settings.randomization
        if not randomization.enabled:
            return
        bodies = self._arm_bodies
        scale = self.rng.uniform(
            1 - randomization.mass_scale, 1 + randomization.mass_scale, len(bodies)
        )
        self.model.body_mass[bodies] *= scale
        self.model.body_inertia[bodies] *= scale[:, None]
        dofs = np.arange(self._n)
        self.model.dof_damping[dofs] *= self.rng.uniform(
            1 - randomization.damping_scale, 1 + randomization.damping_scale, self._n
        )
        self.model.dof_frictionloss[dofs] = self.rng.uniform(
            0, randomization.friction_max_nm, self._n
        )
        links = self._arm_bodies[1:]  # the base stays where it is mounted
        self.model.body_pos[links] *= self.rng.uniform(
            1 - randomization.link_length_scale, 1 + randomization.link_length_scale, len(links)
        )[:, None]
        self.joint_offset = self.rng.uniform(
            -randomization.joint_offset_rad, randomization.joint_offset_rad, self._n
        )
