"""Per-person refinement: fine-tune the dual-agent DQN on a person's recorded sessions.

Two sources of transitions, one update:

* **the person's own reaches**, read back from their recordings: at each decision the
  observation the policy had (end-effector, goal, model in force), the M_ij it chose, and
  the composite reward of the stretch until the next decision, computed from the recorded
  robot states and steps with the training's own reward terms;
* **simulated reaches with a simulated person fitted to them**: their share of commands
  toward the goal and their decision times against the sub-models' (the lognormal
  sub-model with that accuracy and time factor), explored epsilon-greedily from the
  current policy.

The update is the training's double DQN with a conservative term (CQL(H), Kumar et al.
2020): ``alpha * (logsumexp_a Q(s, a) - Q(s, a_data))`` for each agent. A person's
recordings are few reaches of one policy's choices; plain off-policy Q-learning on such
narrow data overrates the actions it never saw (bootstrapping error), and the refined
policy would wander to them on the strength of nothing. The conservative term keeps each
Q-network's unseen actions below the ones in the data unless the rewards say otherwise.
Everything is seeded: on a CPU the same recordings and settings give the same checkpoint,
tensor for tensor.

A refined policy is a *candidate*: it is deployed only when it is better for this person
than the policy in use. The **gate** runs both on the person's fitted simulator, paired
by task seed (``gate_seeds`` reaches each, seeds of their own), and compares the time to
success restricted at the task's horizon (a failed reach counts the full 60 s: one number
for success and speed). It deploys when the lower end of the 95 % bootstrap interval of
the gain (in use minus candidate, seconds) exceeds ``min_gain_s``; otherwise the policy
in use stays, and the verdict says why. The recorded transitions give no usable
off-policy estimate here: both policies are greedy (deterministic), so an importance
weight is zero wherever they disagree; the verdict reports how often they agree on the
recorded decisions instead.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from scipy.stats import bootstrap

from dammrl.learning.rl.config import RewardWeights, TrainSettings
from dammrl.learning.rl.dqn import DualAgentDQN, ReplayBuffer
from dammrl.learning.rl.env import ReachEnv, RewardTerms, accuracy_term
from dammrl.learning.rl.train import EpisodeLog, pick_device, save
from dammrl.stack.recording import read_recording
from dammrl.stack.runner import ReachResult, ReachRunner, ReachSettings
from dammrl_core.errors import ConfigurationError
from dammrl_core.human import HumanModel, direction_to_goal
from dammrl_core.metrics import n_oscillations
from dammrl_core.models import ModelSet
from dammrl_core.person import SimulatedPerson
from dammrl_core.policy.learned import (
    ACTIONS,
    OBSERVATION_SIZE,
    LearnedPolicy,
    load_checkpoint,
    observe,
)
from schemas import (
    DecisionRequest,
    EpisodeResult,
    Intent,
    ModelChoice,
    RobotState,
    StepEvent,
    TaskGoal,
)
from schemas.messages import OPERATOR

SIM_SEEDS_START = 6_950_000
"""The simulated reaches' task seeds: below the held-out range, apart from training's and
the model table's; seed s of the refinement has ``SIM_SEEDS_PER_SEED`` of its own."""
SIM_SEEDS_PER_SEED = 7_500
GATE_SEEDS_START = 6_980_000
"""The gate's task seeds (apart from the simulated reaches' and the model table's); seed
s of the refinement has ``GATE_SEEDS_PER_SEED`` of its own, all below 7,000,000 (held-out
evaluation seeds start there)."""
GATE_SEEDS_PER_SEED = 5_000
MIN_RADIUS_DECISIONS = 20
"""Decisions under a radius before the fit gives that radius an accuracy of its own."""


class RefineSettings(BaseModel):
    """How hard to refine and judge (defaults: 100 simulated reaches, 1,000 gradient steps, a
    gate of 2 x 200 reaches)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    sim_reaches: int = Field(100, ge=0, le=SIM_SEEDS_PER_SEED)
    """Simulated reaches with the fitted person (each on a task seed of its own)."""
    updates: int = Field(1000, ge=1, le=1_000_000)
    """Gradient steps."""
    conservative: float = Field(1.0, ge=0, le=100)
    """alpha of the conservative term (0: plain double DQN)."""
    epsilon: float = Field(0.2, ge=0, le=1)
    """Exploration of the simulated reaches."""
    learning_rate: float = Field(1e-4, gt=0, le=1)
    seed: int = Field(0, ge=0, le=3)
    """Seed of the refinement; it also picks the simulated reaches' and the gate's task seeds
    (four disjoint sets, none among the model table's or any held-out evaluation's)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """auto: a GPU when one is present (then without the byte-identical rerun)."""
    gate_seeds: int = Field(200, ge=10, le=GATE_SEEDS_PER_SEED)
    """Reaches of the fitted person per policy when the candidate is judged (paired). 200:
    when most reaches go alike under both policies and a few fail under one, 40 deploy a
    candidate no better 9 % of the time, 200 about 3 % (``dammrl coadapt gate-rates``)."""
    min_gain_s: float = Field(0.0, ge=0, le=60)
    """The gain's lower bound (seconds of time to success) must exceed this to deploy."""


@dataclass(frozen=True)
class Transition:
    obs: np.ndarray
    action: tuple[int, int]  # 0-based (i, j)
    reward: float
    next_obs: np.ndarray
    done: bool


@dataclass(frozen=True)
class PersonFit:
    """What the person's recorded decisions say, as a simulated person."""

    decisions: int
    accuracy: float  # share toward the goal
    decision_time_factor: float  # median of decision time / the sub-model's median
    accuracy_big: float  # under E_big (the overall share with few decisions under it)
    accuracy_small: float  # under E_small (likewise)

    def person(self) -> SimulatedPerson:
        return SimulatedPerson(
            accuracy_big=self.accuracy_big,
            accuracy_small=self.accuracy_small,
            decision_time_factor=self.decision_time_factor,
        )


Decision = tuple[int, bool, float]
"""(radius i, toward the goal, decision time / the sub-model's median) of one decision."""


# ---- the recordings ------------------------------------------------------------------
def recorded_reaches(
    paths: list[Path], weights: RewardWeights, human: HumanModel
) -> tuple[list[Transition], PersonFit]:
    """The transitions of every recorded reach and the person's fit."""
    transitions: list[Transition] = []
    decisions: list[Decision] = []
    for path in paths:
        for episode in _episodes(path).values():
            transitions += [t for t in _transitions(episode, weights) if _finite(t)]
            decisions += _decisions(episode, human)
    return transitions, fit_person(decisions)


def _finite(t: Transition) -> bool:
    """A transition a crafted recording cannot poison the Q-networks with."""
    return bool(
        math.isfinite(t.reward) and np.isfinite(t.obs).all() and np.isfinite(t.next_obs).all()
    )


def fit_person(decisions: list[Decision]) -> PersonFit:
    """The simulated person of a person's decisions: their share toward the goal (within
    [0.51, 0.99]) overall and under each radius with ``MIN_RADIUS_DECISIONS`` or more, and
    their median time ratio."""
    if not decisions:
        raise ConfigurationError("no decision of a person in the recordings: nothing to adapt to")
    overall = _share([ok for _, ok, _ in decisions])
    per_radius = [[ok for i, ok, _ in decisions if i == radius] for radius in (1, 2)]
    big, small = (_share(d) if len(d) >= MIN_RADIUS_DECISIONS else overall for d in per_radius)
    factor = min(10.0, max(0.1, float(np.median([ratio for _, _, ratio in decisions]))))
    return PersonFit(len(decisions), overall, factor, big, small)


def _share(correct: list[bool]) -> float:
    return min(0.99, max(0.51, float(np.mean(correct))))


@dataclass
class _Episode:
    requests: dict[int, DecisionRequest]
    choices: dict[int, ModelChoice]
    intents: dict[int, Intent]
    steps: list[StepEvent]
    states: list[RobotState]
    result: EpisodeResult | None


def _episodes(path: Path) -> dict[int, _Episode]:
    """Each recorded episode's messages (the robot states it tagged with the episode, up to
    its end on the robot clock)."""
    recording = read_recording(path)
    episodes: dict[int, _Episode] = {}
    # by the episode the arm tagged, not by log time: the recorder hears the goal and the
    # arm's reset state on separate subscribers, in either order on a loaded machine
    states: dict[int, list[RobotState]] = {}
    announced: set[int] = set()
    for _, message in recording.decoded(
        TaskGoal, DecisionRequest, ModelChoice, Intent, StepEvent, RobotState, EpisodeResult
    ):
        number = getattr(message, "episode", 0)
        if number < 1:
            continue
        if isinstance(message, RobotState):
            states.setdefault(number, []).append(message)
            continue
        episode = episodes.setdefault(number, _Episode({}, {}, {}, [], [], None))
        if isinstance(message, TaskGoal):
            announced.add(number)
        elif isinstance(message, DecisionRequest):
            episode.requests.setdefault(message.request, message)
        elif isinstance(message, ModelChoice) and message.request > 0:
            episode.choices.setdefault(message.request, message)
        elif isinstance(message, Intent):
            episode.intents.setdefault(message.request, message)
        elif isinstance(message, StepEvent):
            episode.steps.append(message)
        elif isinstance(message, EpisodeResult):
            episode.result = message
    complete = {}
    for number, episode in episodes.items():
        if episode.result is None or not episode.requests or number not in announced:
            continue  # cut by the end of the recording, or begun before it
        end_s = episode.result.t_total_s + 1e-9
        episode.states = [s for s in states.get(number, []) if s.t_s <= end_s]
        complete[number] = episode
    return complete


def _transitions(episode: _Episode, weights: RewardWeights) -> list[Transition]:
    """One transition per answered request, rewarded over the stretch to the next."""
    assert episode.result is not None
    answered = [r for r in sorted(episode.requests) if r in episode.choices]
    # one state per robot time: a state recorded twice (or forged with an old time) would
    # make a zero time step and an infinite effort
    states = list({s.t_s: s for s in sorted(episode.states, key=lambda s: s.t_s)}.values())
    if not answered or len(states) < 2:
        return []
    goal = np.array(episode.requests[answered[0]].goal_m)
    t = np.array([s.t_s for s in states])
    x = np.array([s.ee_pos_m for s in states])
    out: list[Transition] = []
    model: tuple[int, int] | None = None
    for k, request in enumerate(answered):
        asked = episode.requests[request]
        choice = episode.choices[request]
        obs = observe(np.array(asked.ee_pos_m), goal, model)
        model = (choice.human_model, choice.robot_model)
        last = k == len(answered) - 1
        end_s = episode.requests[answered[k + 1]].t_s if not last else float(t[-1])
        next_x = np.array(episode.requests[answered[k + 1]].ee_pos_m) if not last else x[-1]
        since = asked.t_s if k > 0 else -math.inf  # the first: every state from the reset
        terms = _terms(states, t, x, since, end_s, next_x, goal, episode, last)
        out.append(Transition(obs, (model[0] - 1, model[1] - 1), terms.total(weights),
                              observe(next_x, goal, model), last))  # fmt: skip
    return out


def _terms(states: list[RobotState], t: np.ndarray, x: np.ndarray, start_s: float,
           end_s: float, next_x: np.ndarray, goal: np.ndarray, episode: _Episode,
           last: bool) -> RewardTerms:  # fmt: skip
    """The training's reward terms over the recorded stretch (start_s, end_s], as the
    environment's segment: the states after the decision's up to the next one's."""
    inside = (t > start_s + 1e-9) & (t <= end_s + 1e-9)
    effort, oscillations = 0.0, 0
    dt = float(np.median(np.diff(t[inside]))) if inside.sum() > 2 else 0.0
    if dt > 0:
        segment = [s for s, keep in zip(states, inside, strict=True) if keep]
        q = np.array([s.q_rad for s in segment])
        tau = np.array([s.tau_nm for s in segment])
        dq = np.gradient(q, dt, axis=0)
        effort = float(np.sum(np.abs(np.sum(tau * dq, axis=1))) * dt)
        steps = [s for s in episode.steps if s.start_s <= end_s + 1e-9]
        oscillations = n_oscillations(
            x[inside], np.array([s.subgoal_m for s in steps]).reshape(-1, 3),
            np.array([s.radius_m for s in steps]), 1.0 / dt,
        )  # fmt: skip
    assert episode.result is not None
    times = t[inside]
    return RewardTerms(
        accuracy=accuracy_term(float(np.linalg.norm(next_x - goal))),
        time_s=float(times[-1] - times[0]) if times.size else 0.0,
        effort_j=effort,
        oscillations=oscillations,
        success=last and episode.result.success,
    )  # fmt: skip


def _decisions(episode: _Episode, human: HumanModel) -> list[Decision]:
    """Each of the person's decisions (a therapist's are left out)."""
    out = []
    for request, intent in sorted(episode.intents.items()):
        asked = episode.requests.get(request)
        if asked is None or intent.source == OPERATOR:
            continue
        toward = direction_to_goal(asked.ee_pos_m, asked.goal_m, asked.primary_axis)
        median = human.decision_median_s(intent.human_model)
        out.append((intent.human_model, intent.u_h == toward, intent.decision_s / median))
    return out


# ---- the refinement ------------------------------------------------------------------
@dataclass(frozen=True)
class Refined:
    out: Path
    fit: PersonFit
    recorded: int  # transitions from the recordings
    simulated: int  # transitions from the simulated reaches
    sim_success: float  # the refined policy's exploring reaches' success share


def refine(recordings: list[Path], start: Path, out: Path, settings: RefineSettings,
           progress: Callable[[int], None] | None = None,
           in_use: Path | None = None) -> tuple[Refined, Gate]:  # fmt: skip
    """Fine-tune the checkpoint ``start`` on ``recordings``; write the candidate run to
    ``out`` (a run directory any policy setting can load) and judge it against the policy
    ``in_use`` (default: ``start``) on the person's fitted simulator."""
    weights = RewardWeights(**load_checkpoint(start)["weights"])
    recorded, fit = recorded_reaches(recordings, weights, HumanModel())
    refined = refine_transitions(recorded, fit, start, out, settings, progress)
    verdict = gate(out, in_use or start, fit, settings, recorded, progress)
    meta = json.loads((out / "refined.json").read_text())
    meta["recordings"] = {str(p): _sha256(p) for p in recordings}
    meta["gate"] = verdict.as_dict()
    (out / "refined.json").write_text(json.dumps(meta, indent=1) + "\n")
    return refined, verdict


# ---- the gate: deployed only when better --------------------------------------------
@dataclass(frozen=True)
class Interval:
    """A mean with its 95 % percentile-bootstrap interval (paired differences, per seed)."""

    value: float
    low: float
    high: float

    @classmethod
    def of(cls, differences: np.ndarray, seed: int) -> Interval:
        rng = np.random.default_rng(seed)
        result = bootstrap((differences,), np.mean, n_resamples=2000, method="percentile",
                           random_state=rng)  # fmt: skip
        mean = float(np.mean(differences))
        interval = result.confidence_interval
        return cls(mean, min(mean, float(interval.low)), max(mean, float(interval.high)))

    def text(self, digits: int = 2) -> str:
        return f"{self.value:+.{digits}f} [{self.low:+.{digits}f}, {self.high:+.{digits}f}]"


@dataclass(frozen=True)
class Gate:
    """The candidate against the policy in use on the person's fitted simulator."""

    deployed: bool
    reason: str
    gain: Interval  # in use minus candidate, mean time to success [s] (restricted)
    candidate: tuple[float, float]  # success share, mean time to success [s]
    in_use: tuple[float, float]
    seeds: int
    agreement: float | None  # share of recorded decisions the candidate would take alike

    def as_dict(self) -> dict[str, Any]:
        return {"deployed": self.deployed, "reason": self.reason, "gain_s": asdict(self.gain),
                "candidate": self.candidate, "in_use": self.in_use, "seeds": self.seeds,
                "agreement": self.agreement}  # fmt: skip


def gate(candidate: Path, in_use: Path, fit: PersonFit, settings: RefineSettings,
         recorded: list[Transition] | None = None,
         progress: Callable[[int], None] | None = None) -> Gate:  # fmt: skip
    """Deploy ``candidate`` only when the lower 95 % bound of its gain over ``in_use``
    exceeds ``settings.min_gain_s`` (see the module)."""
    runner = ReachRunner(ReachSettings(human=HumanModel(person=fit.person())))
    horizon = runner.settings.task.episode_timeout_s
    first = GATE_SEEDS_START + settings.seed * GATE_SEEDS_PER_SEED
    seeds = range(first, first + settings.gate_seeds)
    runs = {}
    for name, run in (("candidate", candidate), ("in_use", in_use)):
        policy = LearnedPolicy(runner.settings.models, run)
        runs[name] = [_restricted(runner.run(seed, policy=policy), horizon, progress)
                      for seed in seeds]  # fmt: skip
    mine, theirs = (np.array(runs[k]) for k in ("candidate", "in_use"))
    gain = Interval.of(theirs[:, 1] - mine[:, 1], settings.seed)
    deployed = deploys(gain, settings.min_gain_s)
    sign = "lower bound" if deployed else "its lower bound"
    reason = (f"time to success {mine[:, 1].mean():.1f} s vs {theirs[:, 1].mean():.1f} s in use "
              f"(success {mine[:, 0].mean():.0%} vs {theirs[:, 0].mean():.0%}) on "
              f"{len(seeds)} reaches of the fitted person: gain {gain.value:+.2f} s, {sign} "
              f"{gain.low:+.2f} s {'>' if deployed else '<='} "
              f"{settings.min_gain_s:g} s")  # fmt: skip
    return Gate(deployed, reason, gain, _summary(mine), _summary(theirs), len(seeds),
                _agreement(candidate, in_use, recorded or []))  # fmt: skip


def deploys(gain: Interval, min_gain_s: float) -> bool:
    """The gate's rule: the lower 95 % bound of the gain is above the least gain asked for."""
    return bool(gain.low > min_gain_s)


def deployment_rate(gains: np.ndarray, true_gain_s: float, gate_seeds: int,
                    min_gain_s: float = 0.0, gates: int = 1000,
                    seed: int = 0) -> tuple[int, int]:  # fmt: skip
    """How often the gate deploys for a person whose per-reach gains (in use minus
    candidate, seconds) are distributed as ``gains`` shifted to mean ``true_gain_s``: each
    of ``gates`` gates draws ``gate_seeds`` of them. At a true gain of 0 (the least
    favourable of the candidates that are not better) this is the gate's false-positive
    rate; at a true gain above 0, its power. Returns (deployed, gates)."""
    rng = np.random.default_rng(seed)
    shifted = np.asarray(gains, dtype=float) - float(np.mean(gains)) + true_gain_s
    deployed = 0
    for k in range(gates):
        sample = rng.choice(shifted, size=gate_seeds)
        deployed += deploys(Interval.of(sample, seed * gates + k), min_gain_s)
    return deployed, gates


def _restricted(result: ReachResult, horizon_s: float,
                progress: Callable[[int], None] | None) -> tuple[float, float]:  # fmt: skip
    """(success, time to success restricted at the horizon: a failure counts all of it)."""
    if progress is not None:
        progress(1)
    m = result.metrics
    return float(m.success), m.t_total_s if m.success else horizon_s


def _summary(rows: np.ndarray) -> tuple[float, float]:
    return float(rows[:, 0].mean()), float(rows[:, 1].mean())


def _agreement(candidate: Path, in_use: Path, recorded: list[Transition]) -> float | None:
    """The share of recorded decisions both policies would take alike (None: none)."""
    if not recorded:
        return None
    a, b = (LearnedPolicy(ModelSet(), run).network for run in (candidate, in_use))
    same = [a.greedy(t.obs) == b.greedy(t.obs) for t in recorded]
    return float(np.mean(same))


def refine_transitions(recorded: list[Transition], fit: PersonFit, start: Path, out: Path,
                       settings: RefineSettings,
                       progress: Callable[[int], None] | None = None) -> Refined:  # fmt: skip
    """The refinement of ``start`` on a person's transitions (from recordings, or from
    reaches run in-process: the same numbers) and simulated reaches of their fit."""
    torch.manual_seed(settings.seed)
    checkpoint = load_checkpoint(start)
    weights = RewardWeights(**checkpoint["weights"])
    train = TrainSettings(**checkpoint["settings"]).model_copy(
        update={"learning_rate": settings.learning_rate}
    )
    agent = DualAgentDQN(OBSERVATION_SIZE, ACTIONS, train, pick_device(settings.device))
    agent.online.human.load_state_dict(checkpoint["agent"]["q_human"])
    agent.online.robot.load_state_dict(checkpoint["agent"]["q_robot"])
    agent.sync_targets()
    if not recorded:
        raise ConfigurationError("the recordings hold no complete reach with its decisions")
    own = _buffer(recorded, settings.seed)
    simulated, success = _simulate(agent, fit, weights, train, settings, progress)
    sim = _buffer(simulated, settings.seed + 1) if simulated else None
    for _ in range(settings.updates):
        stats = agent.update(_batch(own, sim, train.batch_size), settings.conservative)
        if progress is not None:
            progress(1)
    out.mkdir(parents=True, exist_ok=True)
    log = EpisodeLog(episode=0, ret=0.0, success=bool(success >= 0.5), decisions=len(simulated),
                     epsilon=settings.epsilon, t_total_s=0.0, loss_human=stats.loss_human,
                     loss_robot=stats.loss_robot, q_human=stats.q_human, q_robot=stats.q_robot,
                     small_steps=math.nan)  # fmt: skip
    save(out, agent, checkpoint["reward"], weights, train, [log], len(simulated))
    (out / "refined.json").write_text(json.dumps({
        "from": str(start), "fit": asdict(fit), "settings": settings.model_dump(),
        "recorded_transitions": len(recorded), "simulated_transitions": len(simulated),
    }, indent=1) + "\n")  # fmt: skip
    return Refined(out, fit, len(recorded), len(simulated), success)


def _simulate(agent: DualAgentDQN, fit: PersonFit, weights: RewardWeights, train: TrainSettings,
              settings: RefineSettings, progress: Callable[[int], None] | None
              ) -> tuple[list[Transition], float]:  # fmt: skip
    if settings.sim_reaches == 0:
        return [], math.nan
    runner = ReachRunner(ReachSettings(human=HumanModel(person=fit.person())))
    env = ReachEnv(runner, weights, train.max_decisions)
    rng = np.random.default_rng(settings.seed)
    out, successes = [], 0
    for n in range(settings.sim_reaches):
        obs, _ = env.reset(seed=SIM_SEEDS_START + settings.seed * SIM_SEEDS_PER_SEED + n)
        while True:
            action = agent.act(obs, settings.epsilon, rng)
            next_obs, reward, terminated, truncated, info = env.step(action)
            out.append(Transition(obs, action, reward, next_obs, terminated or truncated))
            obs = next_obs
            if terminated or truncated:
                successes += bool(info["metrics"].success)
                break
        if progress is not None:
            progress(1)
    return out, successes / settings.sim_reaches


def _buffer(transitions: list[Transition], seed: int) -> ReplayBuffer:
    buffer = ReplayBuffer(len(transitions), OBSERVATION_SIZE, seed)
    for t in transitions:
        buffer.add(t.obs, t.action, t.reward, t.next_obs, t.done)
    return buffer


def _batch(own: ReplayBuffer, sim: ReplayBuffer | None, size: int) -> tuple[np.ndarray, ...]:
    """Half the batch from the person's own reaches (all of it without simulation)."""
    if sim is None:
        return own.sample(size)
    mine, simulated = own.sample(size // 2), sim.sample(size - size // 2)
    return tuple(np.concatenate(pair) for pair in zip(mine, simulated, strict=True))


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def describe(refined: Refined, verdict: Gate) -> dict[str, Any]:
    return {
        "out": str(refined.out), **{f"person_{k}": v for k, v in asdict(refined.fit).items()},
        "recorded_transitions": refined.recorded, "simulated_transitions": refined.simulated,
        "simulated_success": refined.sim_success, "gate": verdict.as_dict(),
    }  # fmt: skip
