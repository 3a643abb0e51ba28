"""The in-process episode runner: sim, simulated human, policy and controller cores,
composed without a bus and run as fast as the machine allows.

This is what ``dammrl reach`` uses, and what training and the comparison study use.
One control tick: read the state, deliver a due human decision, ask for a new one if the
controller wants it, tick the controller, latch its command, advance the physics by one
control period inside MuJoCo.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict

from dammrl.errors import IKError
from dammrl.metrics import GoalMonitor, ReachMetrics, reach_metrics
from dammrl.robot.scene import SENSOR_LAYOUT
from dammrl.state import RobotState, StepEvent
from dammrl.task import ReachTask, TaskSettings, seed_streams, task_for_seed
from services.controller.config import ControllerSettings
from services.controller.core import Controller
from services.controller.dynamics import ArmModel
from services.controller.ik import DampedLeastSquaresIK, IKSolver, make_ik_solver
from services.intent.config import HumanSettings
from services.intent.core import Decision, SimulatedHuman
from services.policy.core import FixedPolicy, ModelChoice
from services.sim.config import SimSettings
from services.sim.core import Simulation

HOLD_OBSERVATION_S = 0.5  # after a hold, keep simulating this long to record the arm at rest


class ReachSettings(BaseModel):
    """Everything one in-process reach needs."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    fast_forward: bool = True
    """Step idle stretches (controller waiting for the human) in one MuJoCo rollout."""
    sim: SimSettings = SimSettings()
    controller: ControllerSettings = ControllerSettings()
    human: HumanSettings = HumanSettings()
    task: TaskSettings = TaskSettings()


class Policy(Protocol):
    def choose(self) -> ModelChoice: ...


@dataclass
class Trajectory:
    """Uniformly sampled log of one reach (control rate)."""

    t: np.ndarray  # (N,) [s]
    x: np.ndarray  # end-effector position (N, 3) [m]
    v: np.ndarray  # end-effector velocity (N, 3) [m/s]
    q: np.ndarray  # joint positions (N, 6) [rad]
    tau: np.ndarray  # applied torques (N, 6) [N m]
    subgoal: np.ndarray  # active subgoal (N, 3) [m], NaN before the first step
    radius: np.ndarray  # active admission radius (N,) [m]


@dataclass
class ReachResult:
    seed: int
    trigger: str
    model: tuple[int, int]
    task: ReachTask
    metrics: ReachMetrics
    trajectory: Trajectory
    steps: list[StepEvent] = field(default_factory=list)
    decisions: list[Decision] = field(default_factory=list)

    def summary(self) -> dict[str, object]:
        """The metrics plus what identifies the run (the ``--json`` object)."""
        return {
            **self.metrics.as_dict(),
            "trigger": self.trigger,
            "model": list(self.model),
            "seed": self.seed,
            "start_m": self.task.start.round(4).tolist(),
            "goal_m": self.task.goal.round(4).tolist(),
        }


class ReachRunner:
    """Builds the cores once (MuJoCo compile, IK chain) and runs reaches on demand."""

    def __init__(self, settings: ReachSettings | None = None) -> None:
        self.settings = settings or ReachSettings()
        self.sim = Simulation(self.settings.sim)
        self.robot = self.sim.robot
        self.arm = ArmModel(self.robot)
        margin = self.settings.controller.joint_limit_margin_rad
        self._solvers: dict[str, IKSolver] = {}
        self._start_ik = DampedLeastSquaresIK(self.arm, limit_margin_rad=margin)
        rate = self.settings.controller.control_rate_hz
        self.substeps = max(1, round(1.0 / (rate * self.sim.timestep_s)))
        self.control_dt_s = self.substeps * self.sim.timestep_s

    def solver(self, controller: ControllerSettings) -> IKSolver:
        if controller.ik_solver not in self._solvers:
            self._solvers[controller.ik_solver] = make_ik_solver(
                controller.ik_solver,
                self.arm,
                controller.joint_limit_margin_rad,
                controller.max_joint_step_rad,
            )
        return self._solvers[controller.ik_solver]

    def sample(self, seed: int) -> ReachTask:
        """The start and goal a given seed draws."""
        return task_for_seed(self.settings.task, self.sim.layout.goal_z_m, seed)

    def run(
        self,
        seed: int,
        model: tuple[int, int] = (1, 1),
        trigger: str | None = None,
        task: ReachTask | None = None,
        policy: Policy | None = None,
    ) -> ReachResult:
        """One reach. ``trigger`` overrides the controller setting ('event' or 'fixed')."""
        policy = policy or FixedPolicy(self.settings.human.models, *model)
        episode = self.episode(seed, trigger, task)
        episode.policy = policy
        metrics, trajectory = episode.run()
        choice = policy.choose()
        return ReachResult(
            seed=seed,
            trigger=episode.controller.settings.trigger,
            model=(choice.human_model, choice.robot_model),
            task=episode.task,
            metrics=metrics,
            trajectory=trajectory,
            steps=episode.steps,
            decisions=episode.decisions,
        )

    def episode(
        self, seed: int, trigger: str | None = None, task: ReachTask | None = None
    ) -> Episode:
        """A fresh episode of ``seed``, ready to run (or to be stepped, see Episode.loop)."""
        controller_settings = self.settings.controller
        if trigger is not None:
            controller_settings = controller_settings.model_copy(update={"trigger": trigger})
        _, human_rng, latency_rng, sim_rng = seed_streams(seed)  # the first one draws the task
        task = task or self.sample(seed)
        controller = Controller(
            self.robot, controller_settings, latency_rng, self.arm, self.solver(controller_settings)
        )
        self.sim.rng = sim_rng
        human = SimulatedHuman(self.settings.human, human_rng)
        return Episode(self, controller, human, task)

    def start_posture(self, start: np.ndarray) -> np.ndarray:
        """Joint positions placing the end-effector at ``start``, solved from home."""
        home = np.array(self.settings.task.home_q_rad)
        result = self._start_ik.solve(start, home)
        if result.error_m > 1e-4:
            raise IKError(f"start position {start.round(3).tolist()} m is not reachable")
        return result.q


class Episode:
    """The tick loop of one reach and its log."""

    def __init__(
        self,
        runner: ReachRunner,
        controller: Controller,
        human: SimulatedHuman,
        task: ReachTask,
    ) -> None:
        self.runner = runner
        self.sim = runner.sim
        self.controller = controller
        self.human = human
        self.policy: Policy | None = None  # who chooses the model in run()
        self.task = task
        self.steps: list[StepEvent] = []
        self.decisions: list[Decision] = []
        self.pending: Decision | None = None
        task_settings = runner.settings.task
        self.goal_monitor = GoalMonitor(
            task.goal, task_settings.goal_tolerance_m, task_settings.goal_dwell_s
        )
        capacity = int(task_settings.episode_timeout_s / runner.control_dt_s) + 2
        capacity += int(HOLD_OBSERVATION_S / runner.control_dt_s) + 2
        self.timeout_s = task_settings.episode_timeout_s
        self.outcome, self.reason = "timeout", "episode timeout"
        self.hold_s: float | None = None  # when the controller entered a hold
        self.hold_until: float | None = None  # end of the observation after a hold
        self.last_state: RobotState  # the last state observed (set by the loop)
        self.button_pressed = False
        self.log = np.full((capacity, 3 + 3 + 6 + 6 + 3 + 1 + 1), np.nan)
        self.n = 0

    def run(self) -> tuple[ReachMetrics, Trajectory]:
        """The whole reach, the policy choosing the model at every decision."""
        assert self.policy is not None, "set Episode.policy before run()"
        loop = self.loop()
        try:
            next(loop)
            while True:
                loop.send(self.policy.choose())
        except StopIteration:
            pass
        return self.result()

    def loop(self) -> Generator[RobotState, ModelChoice, None]:
        """The tick loop as a generator: it yields the state whenever the human is asked
        for a decision and takes the ModelChoice in force for that decision."""
        sim, task = self.sim, self.task
        state = sim.reset(self.runner.start_posture(task.start), (task.goal[0], task.goal[1]))
        sim.apply(self.controller.reset(state, task.goal))
        while True:
            state = sim.read()
            self.last_state = state
            if self._observe(state):
                return
            if self.pending is None and self.controller.wants_intent:
                self._ask_human(state, (yield state))
            self._act(state)
            idle = self._idle_periods(state.t_s)
            if idle > 1:
                if self._fast_forward(idle):
                    return
            else:
                sim.step(self.runner.substeps)

    def segment(self, start: int) -> Trajectory:
        """What was logged since row ``start`` (``self.n`` is the next row)."""
        return self._trajectory(start)

    def result(self) -> tuple[ReachMetrics, Trajectory]:
        """Metrics and trajectory once the loop has ended."""
        return self._metrics(self.last_state), self._trajectory()

    def _observe(self, state: RobotState) -> bool:
        """Log the tick, decide whether the reach is over, deliver a due decision."""
        self._record(state)
        if self.hold_until is not None:
            return state.t_s >= self.hold_until
        if self.goal_monitor.update(state.t_s, state.ee_pos):
            self.outcome, self.reason = "success", "goal reached"
            return True
        if state.t_s >= self.timeout_s:
            return True
        if self.pending is not None and state.t_s >= self.pending.intent.t_s - 1e-9:
            self.controller.on_intent(self.pending.intent)
            self.pending = None
        return False

    def _ask_human(self, state: RobotState, choice: ModelChoice) -> None:
        self.controller.set_steps(choice.steps_m)
        axis = self.controller.settings.primary_axis
        self.pending = self.human.decide(
            state.t_s, state.ee_pos, self.task.goal, axis, choice.human_model
        )
        self.decisions.append(self.pending)

    def _act(self, state: RobotState) -> None:
        """Tick the controller and latch its command."""
        output = self.controller.tick(state)
        self.steps.extend(output.steps)
        if output.hold_reason is not None:
            self.outcome, self.reason = "hold", output.hold_reason
            self.hold_s = state.t_s
            self.hold_until = state.t_s + HOLD_OBSERVATION_S
        self.sim.apply(output.command)

    def _idle_periods(self, t_s: float) -> int:
        """Control periods until something can change while the controller is idle."""
        if not self.runner.settings.fast_forward or not self.controller.idle:
            return 0
        if self.hold_until is not None:
            until = self.hold_until
        elif self.pending is not None:
            until = min(self.pending.intent.t_s, self.timeout_s)
        else:
            return 0
        return math.ceil((until - t_s - 1e-9) / self.runner.control_dt_s)

    def _fast_forward(self, periods: int) -> bool:
        """Advance ``periods`` idle control periods in one MuJoCo rollout.

        Ticks at which nothing can happen (far from the goal, inside the limits, before
        any deadline) are only logged, in bulk; from the first that might matter on, each
        tick runs exactly as in the loop. The last period's state is left for the loop.
        True when the reach ended inside the stretch.
        """
        times, rows = self.sim.advance(periods, self.runner.substeps)
        times, rows = times[:-1], rows[:-1]
        quiet = self._quiet_ticks(times, rows)
        self._record_many(times[:quiet], rows[:quiet])
        for t_s, row in zip(times[quiet:], rows[quiet:], strict=True):
            state = self.sim.state_from_sensors(float(t_s), row)
            self.last_state = state
            if self._observe(state):
                return True
            self._act(state)  # idle: no decision can be due before the stretch ends
        return False

    def _quiet_ticks(self, times: np.ndarray, rows: np.ndarray) -> int:
        """How many leading ticks need no more than logging (see ``_fast_forward``)."""
        if self.goal_monitor.entered_s is not None:
            return 0
        layout = SENSOR_LAYOUT
        deadline = self.timeout_s if self.hold_until is None else self.hold_until
        eventful = times >= deadline - 1e-9
        if self.hold_until is None:
            distance = np.linalg.norm(rows[:, layout["ee_pos"]] - self.task.goal, axis=1)
            eventful |= distance <= self.goal_monitor.tolerance_m
            violation = self.controller.limits.first_violation(
                rows[:, layout["q"]], rows[:, layout["dq"]]
            )
            if violation is not None:
                eventful[violation] = True
        return int(np.argmax(eventful)) if eventful.any() else len(times)

    def _record_many(self, times: np.ndarray, rows: np.ndarray) -> None:
        """Log many ticks at once (a fast-forwarded stretch: subgoal and radius fixed)."""
        if len(times) == 0:
            return
        layout, block = SENSOR_LAYOUT, self.log[self.n : self.n + len(times)]
        block[:, 0:3] = rows[:, layout["ee_pos"]]
        block[:, 3:6] = rows[:, layout["ee_vel"]]
        block[:, 6:12] = rows[:, layout["q"]]
        block[:, 12:18] = rows[:, layout["tau"]]
        subgoal = self.controller.subgoal
        block[:, 18:21] = subgoal if subgoal is not None else np.nan
        block[:, 21] = self.controller.radius_m
        block[:, 22] = times
        self.n += len(times)
        travel = -rows[:, layout["button"]][:, 0]
        self.button_pressed |= bool(np.any(travel >= self.sim.settings.button_press_travel_m))

    def _record(self, state: RobotState) -> None:
        subgoal = self.controller.subgoal
        row = self.log[self.n]
        row[0:3] = state.ee_pos
        row[3:6] = state.ee_vel
        row[6:12] = state.q
        row[12:18] = state.tau
        row[18:21] = subgoal if subgoal is not None else np.nan
        row[21] = self.controller.radius_m
        row[22] = state.t_s
        self.n += 1
        self.button_pressed |= state.button_pressed

    def _trajectory(self, start: int = 0) -> Trajectory:
        """The log from row ``start`` on (the RL environment takes one decision's worth)."""
        log = self.log[start : self.n]
        return Trajectory(
            t=log[:, 22].copy(),
            x=log[:, 0:3].copy(),
            v=log[:, 3:6].copy(),
            q=log[:, 6:12].copy(),
            tau=log[:, 12:18].copy(),
            subgoal=log[:, 18:21].copy(),
            radius=log[:, 21].copy(),
        )

    def _metrics(self, state: RobotState) -> ReachMetrics:
        traj = self._trajectory()
        t_end = state.t_s if self.hold_s is None else self.hold_s  # a hold ends the reach
        moving = traj.t <= t_end + 1e-9
        return reach_metrics(
            outcome=self.outcome,
            reason=self.reason,
            t_end_s=t_end,
            t=traj.t[moving],
            x=traj.x[moving],
            v=traj.v[moving],
            goal=self.task.goal,
            subgoals=np.array([step.subgoal for step in self.steps]),
            radii=np.array([step.radius_m for step in self.steps]),
            decisions_correct=[d.correct for d in self.decisions if d.intent.t_s <= t_end + 1e-9],
            button_pressed=self.button_pressed,
        )
