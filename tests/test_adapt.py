"""Per-person refinement (``dammrl adapt``) on a recording of the real stack, and the
adaptive policy in protocols and sessions."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dammrl.adapt import RefineSettings, _episodes, _transitions, recorded_reaches, refine
from dammrl.launch import Stack, StackOptions
from dammrl.rl.config import RewardWeights
from dammrl.rl.env import ReachEnv
from dammrl.runner import ReachRunner
from dammrl.session import Participant
from dammrl_core.coadaptation import Targets
from dammrl_core.errors import ConfigurationError
from dammrl_core.human import HumanModel, direction_to_goal
from dammrl_core.policy.learned import load_checkpoint
from dammrl_core.protocol import Condition
from tests.busutil import free_port

SEED = 7_800_000
SHIPPED = Path("reward2")
TINY = RefineSettings(sim_reaches=3, updates=40)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three reaches of the stack in lockstep (the in-process runner's exact twin)."""
    path = tmp_path_factory.mktemp("rec") / "P1.mcap"
    command = [sys.executable, "-m", "dammrl", "up", "--episodes", "3", "--seed", str(SEED),
               "--lockstep", "--record", str(path), "--bus-port", str(free_port())]  # fmt: skip
    done = subprocess.run(command, timeout=240, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    return path


def weights() -> RewardWeights:
    return RewardWeights(**load_checkpoint(SHIPPED)["weights"])


@pytest.mark.slow
def test_a_recorded_reach_gives_the_transitions_training_would_have(recording: Path) -> None:
    """Observation, action and reward of every recorded decision equal the training
    environment's for the same seed and choices (the reward from the recorded states)."""
    env = ReachEnv(ReachRunner(), weights(), 150)
    episodes = _episodes(recording)
    assert sorted(episodes) == [1, 2, 3]
    for number, episode in episodes.items():
        obs, _ = env.reset(seed=SEED + number - 1)
        transitions = _transitions(episode, weights())
        for k, t in enumerate(transitions):
            np.testing.assert_allclose(t.obs, obs, atol=1e-6)
            obs, reward, terminated, _, _ = env.step(t.action)
            assert t.reward == pytest.approx(reward, abs=1e-6), (number, k)
            assert t.done == terminated
        assert transitions[-1].done


@pytest.mark.slow
def test_an_arms_state_heard_before_its_episodes_goal_still_belongs_to_it(
    recording: Path, tmp_path: Path
) -> None:
    """The recorder hears the goal and the arm's reset state on separate subscribers: on a
    loaded machine the reset state can be logged first (CI did). Its transitions stay."""
    from dammrl.recording import read_recording
    from schemas.codec import decode
    from schemas.keys import type_of
    from schemas.messages import RobotState, TaskGoal
    from services.recorder.core import McapRecorder

    original = read_recording(recording)
    first_state_ns: dict[int, int] = {}
    for log_ns, state in original.decoded(RobotState):
        assert isinstance(state, RobotState)
        first_state_ns.setdefault(state.episode, log_ns)
    moved = tmp_path / "goal-late.mcap"
    writer = McapRecorder(moved, original.namespace(), {}, 4096)
    for record in original.messages:
        topic, log_ns = original.topic(record), record.log_time
        if type_of(original.namespace(), topic) is TaskGoal:
            log_ns = first_state_ns[decode(TaskGoal, record.data).episode] + 1
        writer.record(topic, record.data, log_ns)
    writer.finish()
    assert set(first_state_ns) >= {1, 2, 3}
    for number, episode in _episodes(recording).items():
        expected = _transitions(episode, weights())
        got = _transitions(_episodes(moved)[number], weights())
        assert [t.reward for t in got] == [t.reward for t in expected], number


@pytest.mark.slow
def test_the_fitted_person_is_what_the_recorded_decisions_say(recording: Path) -> None:
    human = HumanModel()
    toward, ratios = [], []
    for episode in _episodes(recording).values():
        for request, intent in episode.intents.items():
            asked = episode.requests[request]
            goal = direction_to_goal(asked.ee_pos_m, asked.goal_m, asked.primary_axis)
            toward.append(intent.u_h == goal)
            ratios.append(intent.decision_s / human.decision_median_s(intent.human_model))
    _, fit = recorded_reaches([recording], weights(), human)
    assert fit.decisions == len(toward) > 10
    assert fit.accuracy == pytest.approx(min(0.99, np.mean(toward)))
    assert fit.decision_time_factor == pytest.approx(np.median(ratios))


@pytest.mark.slow
def test_refinement_is_deterministic_and_loads_as_a_policy(recording: Path, tmp_path: Path) -> None:
    first = refine([recording], SHIPPED, tmp_path / "a", TINY)
    refine([recording], SHIPPED, tmp_path / "b", TINY)
    a, b = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=True) for d in "ab")
    for net in ("q_human", "q_robot"):
        for name, tensor in a["agent"][net].items():
            assert torch.equal(tensor, b["agent"][net][name]), name
    shipped = load_checkpoint(SHIPPED)["agent"]["q_robot"]
    assert any(not torch.equal(t, shipped[n]) for n, t in a["agent"]["q_robot"].items())
    meta = json.loads((tmp_path / "a" / "refined.json").read_text())
    assert meta["recorded_transitions"] == first.recorded and str(recording) in meta["recordings"]
    from dammrl_core.models import ModelSet
    from dammrl_core.policy.learned import LearnedPolicy

    LearnedPolicy(ModelSet(), tmp_path / "a").decide(np.zeros(3), np.ones(3))


def test_a_recording_without_a_persons_decision_is_refused(tmp_path: Path) -> None:
    from services.recorder.core import McapRecorder

    empty = tmp_path / "empty.mcap"
    McapRecorder(empty, "dammrl", {}, 4096).finish()
    with pytest.raises(ConfigurationError, match="no decision of a person"):
        recorded_reaches([empty], weights(), HumanModel())


def test_a_participants_refined_policy_is_what_their_next_session_loads(tmp_path: Path) -> None:
    participant = Participant(tmp_path, "P012")
    assert participant.refined_policy() is None
    participant.policy_folder.mkdir(parents=True)
    (participant.policy_folder / "checkpoint.pt").write_bytes(b"")
    assert participant.refined_policy() == participant.policy_folder
    env = Stack(StackOptions(checkpoint=participant.policy_folder, port=free_port())).environment()
    assert env["DAMMRL_POLICY_CHECKPOINT"] == str(participant.policy_folder.resolve())


def test_a_protocol_block_can_ask_for_the_adaptive_policy_and_its_targets() -> None:
    block = Condition(policy="adaptive", targets=Targets(window=3, time_max_s=12.0))
    env = Stack(StackOptions(adaptive=block.targets, port=free_port())).environment()
    assert env["DAMMRL_POLICY_KIND"] == "adaptive"
    assert json.loads(env["DAMMRL_POLICY_TARGETS"])["time_max_s"] == 12.0
    with pytest.raises(ValueError, match="targets are for an adaptive policy"):
        Condition(policy="learned", targets=Targets())


@pytest.mark.slow
def test_a_state_recorded_twice_changes_no_transition(recording: Path) -> None:
    """Duplicated (or replayed) states would make a zero time step: no infinite effort, no
    NaN reward reaches the Q-networks."""
    episode = _episodes(recording)[1]
    clean = _transitions(episode, weights())
    episode.states = episode.states + episode.states[::7]
    doubled = _transitions(episode, weights())
    assert [t.reward for t in doubled] == [t.reward for t in clean]
    assert all(np.isfinite(t.reward) for t in doubled)
