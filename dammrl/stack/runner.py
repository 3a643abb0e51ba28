"""The in-process composition: sim, simulated human, policy and the controller's reach
supervisor, called directly without a bus and run as fast as the machine allows.

This is what ``dammrl reach``, training, evaluation and the studies use. Every decision
the episode takes goes through the same objects the bus stack runs (``Reach`` for the
per-tick logic, ``SimulatedHuman``, the ``Policy`` protocol, ``Simulation``), and every
random draw comes from the seed's named streams, so a seed gives the same reach here and
on the bus. One control tick: ``Reach.tick`` on the state; when it asks, the policy
chooses M_ij and the human decides (due after their decision time); the command is
latched and the physics advances one control period inside MuJoCo.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass, field
from typing import Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from dammrl_core.coadaptation import (
    DecisionEvidence,
    ReachEvidence,
    ReachRecord,
    robot_model_of,
)
from dammrl_core.control.controller import Controller, first_true, latency_model
from dammrl_core.control.reach import HOLD_OBSERVATION_S, Answer, Reach, Trajectory
from dammrl_core.control.settings import ControllerSettings, check_workspace
from dammrl_core.dynamics import ArmModel
from dammrl_core.human import HumanModel
from dammrl_core.ik import IKSolver, make_ik_solver
from dammrl_core.intent.simulated import Decision, SimulatedHuman
from dammrl_core.metrics import ReachMetrics, episode_summary
from dammrl_core.models import ModelSet
from dammrl_core.policy import FixedPolicy, ModelChoice, Policy
from dammrl_core.robot import RobotSettings
from dammrl_core.robot.scene import SENSOR_LAYOUT
from dammrl_core.sim.settings import SimSettings
from dammrl_core.sim.simulation import Simulation
from dammrl_core.state import RobotState, StepEvent
from dammrl_core.task import (
    ReachTask,
    TaskSettings,
    scene_layout,
    seed_streams,
    start_posture,
    task_for_seed,
)

COAST_PERIODS = 100
"""The most control periods stepped in one go while a reach coasts (1 s at 100 Hz)."""


SETTLE_S = 0.05
"""While the arm approaches its subgoal, a stretch foresees the commands this far past
the reference's rest (the trigger fires about then; foreseen beyond it, they are waste)."""


def _tick_times(t_s: float, ticks: int, substeps: int, timestep_s: float) -> np.ndarray:
    """The robot times of the next ``ticks`` ticks after ``t_s``, as MuJoCo's clock will
    read them: it adds the timestep once per step (``accumulate`` adds in order too)."""
    steps = np.full(ticks * substeps + 1, timestep_s)
    steps[0] = t_s
    return np.asarray(np.add.accumulate(steps)[substeps::substeps])


class ReachSettings(BaseModel):
    """Everything one in-process reach needs (the same settings the services read)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    fast_forward: bool = True
    """Step idle stretches (controller waiting for the human) in one MuJoCo rollout."""
    sim: SimSettings = Field(default_factory=SimSettings)
    controller: ControllerSettings = Field(default_factory=ControllerSettings)
    human: HumanModel = Field(default_factory=HumanModel)
    models: ModelSet = Field(default_factory=ModelSet)
    robot: RobotSettings = Field(default_factory=RobotSettings)
    task: TaskSettings = Field(default_factory=TaskSettings)

    @model_validator(mode="after")
    def _workspace_above_the_table(self) -> Self:
        check_workspace(self.controller, self.task)
        return self

    def randomized(self, enabled: bool = True) -> ReachSettings:
        """These settings on a randomised arm (dynamics, kinematics, sensor noise) or not."""
        randomization = self.sim.randomization.model_copy(update={"enabled": enabled})
        sim = self.sim.model_copy(update={"randomization": randomization})
        return self.model_copy(update={"sim": sim})


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
    choices: list[ModelChoice] = field(default_factory=list)
    ik_latencies_s: list[float] = field(default_factory=list)  # every solve's, in order
    ik_evaluations: list[int] = field(default_factory=list)  # and its work (see IKLatency)

    def summary(self) -> dict[str, object]:
        """The metrics plus what identifies the run (the ``--json`` object)."""
        return episode_summary(self.metrics, self.trigger, self.model, self.seed, self.task)


def evidence_of(result: ReachResult, models: ModelSet) -> ReachEvidence:
    """What a finished reach tells the posterior over M_ij: the same numbers the policy
    service collects on the bus from the reach's messages."""
    record = ReachRecord(
        choices=[(c.human_model, c.robot_model) for c in result.choices],
        decisions=[DecisionEvidence(c.human_model, d.correct, d.decision_s)
                   for d, c in zip(result.decisions, result.choices, strict=True)],
        asked_s=[d.intent.t_s - d.decision_s for d in result.decisions],
        steps=[(robot_model_of(models, s.steps_m), float(np.linalg.norm(s.dx)), s.radius_m,
                s.start_s) for s in result.steps],
    )  # fmt: skip
    m = result.metrics
    return record.evidence(m.success, m.t_total_s, m.final_error_m, m.sparc, result.model)


class ReachRunner:
    """Builds the cores once (MuJoCo compile, IK chain) and runs reaches on demand."""

    def __init__(self, settings: ReachSettings | None = None) -> None:
        self.settings = settings or ReachSettings()
        robot = self.settings.robot.load()
        self.sim = Simulation(self.settings.sim, robot, scene_layout(self.settings.task))
        self.robot = robot
        self.arm = ArmModel(robot)
        self._solvers: dict[str, IKSolver] = {}
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
        return task_for_seed(self.settings.task, seed)

    def start_posture(self, start: np.ndarray) -> np.ndarray:
        """Joint positions placing the end-effector at ``start`` (the one definition)."""
        return start_posture(self.arm, self.settings.task, start)

    def run(
        self,
        seed: int,
        model: tuple[int, int] = (1, 1),
        trigger: str | None = None,
        task: ReachTask | None = None,
        policy: Policy | None = None,
        ik_latencies: Sequence[float] | None = None,
        human: HumanModel | None = None,
    ) -> ReachResult:
        """One reach. ``trigger`` overrides the controller setting ('event' or 'fixed');
        ``policy`` (default: the fixed ``model``) chooses M_ij at every decision;
        ``ik_latencies``: a measured run's (its ``ik_latencies_s``), replayed exactly;
        ``human``: the simulated person of this reach in place of the settings' (one who
        has practised or tired, ``HumanModel.practised``)."""
        policy = policy or FixedPolicy(self.settings.models, *model)
        episode = self.episode(seed, trigger, task, ik_latencies, human)
        metrics, trajectory = episode.run(policy)
        if episode.choices:  # the model in force at the end
            model = (episode.choices[-1].human_model, episode.choices[-1].robot_model)
        return ReachResult(
            seed=seed,
            trigger=episode.controller.settings.trigger,
            model=model,
            task=episode.task,
            metrics=metrics,
            trajectory=trajectory,
            steps=episode.reach.steps,
            decisions=episode.decisions,
            choices=episode.choices,
            ik_latencies_s=list(episode.controller.latency.spent_s),
            ik_evaluations=list(episode.controller.latency.evaluations),
        )

    def episode(
        self,
        seed: int,
        trigger: str | None = None,
        task: ReachTask | None = None,
        ik_latencies: Sequence[float] | None = None,
        human: HumanModel | None = None,
    ) -> Episode:
        """A fresh episode of ``seed``, ready to run (or to be stepped, see Episode.loop)."""
        settings = self.settings.controller
        if trigger is not None:
            settings = settings.model_copy(update={"trigger": trigger})
        streams = seed_streams(seed)
        task = task or self.sample(seed)
        latency = latency_model(settings, streams.ik_latency, ik_latencies)
        controller = Controller(
            self.robot, settings, streams.ik_latency, self.arm, self.solver(settings), latency
        )
        reach = Reach(controller, task, self.settings.task, self.control_dt_s)
        person = SimulatedHuman(human or self.settings.human, self.settings.models,
                                streams.human)  # fmt: skip
        return Episode(self, reach, person, streams.sim)


class Episode:
    """The tick loop of one reach."""

    def __init__(
        self,
        runner: ReachRunner,
        reach: Reach,
        human: SimulatedHuman,
        sim_rng: np.random.Generator,
    ) -> None:
        self.runner = runner
        self.sim = runner.sim
        self.reach = reach
        self.controller = reach.controller
        self.task = reach.task
        self.human = human
        self.sim_rng = sim_rng
        self.decisions: list[Decision] = []
        self.choices: list[ModelChoice] = []
        self.hold_until: float | None = None  # end of the observation after a hold
        self.last_state: RobotState  # the last state observed (set by the loop)

    # ---- what the RL environment reads ----------------------------------------------
    @property
    def steps(self) -> list[StepEvent]:
        return self.reach.steps

    @property
    def n(self) -> int:
        """Rows logged so far."""
        return self.reach.log.n

    @property
    def outcome(self) -> str:
        return self.reach.ended[0] if self.reach.ended else "timeout"

    def segment(self, start: int) -> Trajectory:
        """What was logged since row ``start``."""
        return self.reach.log.trajectory(start)

    def result(self) -> tuple[ReachMetrics, Trajectory]:
        """Metrics and trajectory once the loop has ended."""
        return self.reach.metrics(), self.reach.log.trajectory()

    # ---- the loop -------------------------------------------------------------------
    def run(self, policy: Policy) -> tuple[ReachMetrics, Trajectory]:
        """The whole reach, ``policy`` choosing the model at every decision."""
        policy.reset()
        loop = self.loop()
        try:
            state = next(loop)
            while True:
                state = loop.send(policy.decide(state.ee_pos, self.task.goal))
        except StopIteration:
            pass
        return self.result()

    def loop(self) -> Generator[RobotState, ModelChoice, None]:
        """The tick loop as a generator: it yields the state whenever the human is asked
        for a decision and takes the ModelChoice in force for that decision."""
        task = self.task
        q_start = self.runner.start_posture(task.start)
        state = self.sim.reset(q_start, (task.goal[0], task.goal[1]), rng=self.sim_rng)
        while True:
            self.last_state = state
            tick = self.reach.tick(state)
            if tick.ask:
                self._ask_human(state, (yield state))
            if tick.command is None or self._observed_enough(state):
                return
            self.sim.apply(tick.command)
            next_state = self._advance(state)
            if next_state is None:
                return
            state = next_state

    def _ask_human(self, state: RobotState, choice: ModelChoice) -> None:
        axis = self.controller.settings.primary_axis
        decision = self.human.decide(
            state.t_s, state.ee_pos, self.task.goal, axis, choice.human_model
        )
        self.decisions.append(decision)
        self.choices.append(choice)
        self.reach.answer(Answer(decision.intent, choice.steps_m, decision.correct))

    def _observed_enough(self, state: RobotState) -> bool:
        """After a hold the arm is logged for ``HOLD_OBSERVATION_S`` more (plots)."""
        if self.reach.ended is None or self.reach.end_s is None:
            return False
        if self.hold_until is None:
            self.hold_until = self.reach.end_s + HOLD_OBSERVATION_S
        return state.t_s >= self.hold_until - 1e-9

    def _advance(self, state: RobotState) -> RobotState | None:
        """The next tick's state: one control period, an idle stretch in one rollout
        (None when the reach ended inside it), or a stretch of quiet ticks in one go."""
        idle = self._idle_periods(state.t_s)
        if idle > 1:
            return self._fast_forward(idle)
        periods = self._coast_periods(state)
        if periods > 1:
            return self._coast(state.t_s, periods)
        self.sim.step(self.runner.substeps)
        return self.sim.read()

    def _coast_periods(self, state: RobotState) -> int:
        """Control periods to step in one go while the reach coasts (0: tick each): up to
        the next event known in advance (a decision due, a timeout) or about when the
        trigger fires (a planned step's approach included), at most ``COAST_PERIODS``;
        none while the arm is already near its subgoal."""
        reach, controller = self.reach, self.controller
        if not self.runner.settings.fast_forward or not reach.coasting:
            return 0
        if controller.awaiting_trigger and controller.subgoal is not None:
            error = controller.subgoal - state.ee_pos
            if error @ error <= controller.radius_m**2 * (1 + 1e-9):
                return 0  # the trigger may fire at any tick now
            until = controller.segment.t0_s + controller.settings.trigger_timeout_s
            # it fires about when the reference comes to rest: foresee no farther
            until = min(until, max(controller.segment.end_s, state.t_s) + SETTLE_S)
        else:
            until = math.inf
        if controller.planned:  # the step starts within the stretch: foresee its approach
            until = min(until, controller.foreseen_end_s() + SETTLE_S)
        if reach.pending is not None:
            until = min(until, reach.pending.intent.t_s)
        until = min(until, reach.timeout_s)
        ahead = math.ceil((until - state.t_s) / self.runner.control_dt_s - 1e-9)
        return min(ahead, COAST_PERIODS)

    def _coast(self, t_s: float, periods: int) -> RobotState:
        """Quiet ticks in bulk: the commands the controller would send at each (a function
        of time while it coasts) are stepped in one go, stopping when the arm comes near its
        subgoal; the ticks before the first state that brings an event are logged as ticks
        (the physics rewound to it if it came earlier), and that state is returned for the
        loop to tick. Bitwise the same reach as ticking each period."""
        runner, controller, sim = self.runner, self.controller, self.sim
        times = _tick_times(t_s, periods - 1, runner.substeps, sim.timestep_s)
        inputs = controller.reference_inputs(times)
        ctrl = sim.inputs_of(inputs.q_ref, inputs.dq_ref, inputs.tau_ff, controller.kp,
                             controller.kd)  # fmt: skip
        stretch = sim.coast(ctrl, runner.substeps, controller.armed_trigger(inputs))
        stepped = len(stretch.times)
        ticks = stretch.times[: stepped - 1]
        # the commands are those of the times foreseen: a tick at another time ends it
        ran = first_true(ticks != times[: stepped - 1])
        press = sim.settings.button_press_travel_m
        ran = self.reach.first_event(ticks[:ran], stretch.rows[:ran], press, inputs)
        sim.rewind(stretch, ctrl, runner.substeps, ran + 1)
        command = self.reach.coast(ticks[:ran], stretch.rows[:ran], stretch.true_ee[:ran],
                                   press, inputs)  # fmt: skip
        if command is not None:
            sim.latch(command)
        return sim.state_from_sensors(float(stretch.times[ran]), stretch.rows[ran],
                                      stretch.true_ee[ran])  # fmt: skip

    def _idle_periods(self, t_s: float) -> int:
        """Control periods until something can change while the controller is idle."""
        if not self.runner.settings.fast_forward or not self.controller.idle:
            return 0
        if self.hold_until is not None:
            until = self.hold_until
        elif self.reach.pending is not None:
            until = min(self.reach.pending.intent.t_s, self.reach.timeout_s)
        else:
            return 0
        return math.ceil((until - t_s - 1e-9) / self.runner.control_dt_s)

    def _fast_forward(self, periods: int) -> RobotState | None:
        """Advance ``periods`` idle control periods in one MuJoCo rollout.

        Ticks at which nothing can happen (far from the goal, inside the limits, before
        any deadline) are only logged, in bulk; from the first that might matter on, each
        tick runs exactly as in the loop. The last period's state is returned for the
        loop; None when the reach ended inside the stretch.
        """
        times, rows, true_ee = self.sim.advance(periods, self.runner.substeps)
        quiet = self._quiet_ticks(times[:-1], rows[:-1])
        controller = self.controller
        self.reach.log.record_many(
            times[:quiet],
            rows[:quiet],
            controller.subgoal,
            controller.radius_m,
            self.sim.settings.button_press_travel_m,
            true_ee[:quiet],
        )
        for k in range(quiet, len(times) - 1):
            state = self.sim.state_from_sensors(float(times[k]), rows[k], true_ee[k])
            self.last_state = state
            tick = self.reach.tick(state)  # idle: no decision can be due in the stretch
            if tick.command is None or self._observed_enough(state):
                return None
            self.sim.apply(tick.command)
        return self.sim.state_from_sensors(float(times[-1]), rows[-1], true_ee[-1])

    def _quiet_ticks(self, times: np.ndarray, rows: np.ndarray) -> int:
        """How many leading ticks need no more than logging (see ``_fast_forward``)."""
        reach = self.reach
        if reach.dwelling:
            return 0
        deadline = reach.timeout_s if self.hold_until is None else self.hold_until
        eventful = times >= deadline - 1e-9
        if self.hold_until is None:
            travel = -rows[:, SENSOR_LAYOUT["button"]][:, 0]
            eventful |= travel >= self.sim.settings.button_press_travel_m
            violation = self.controller.limits.first_violation(
                rows[:, SENSOR_LAYOUT["q"]], rows[:, SENSOR_LAYOUT["dq"]]
            )
            if violation is not None:
                eventful[violation] = True
        return first_true(eventful)
