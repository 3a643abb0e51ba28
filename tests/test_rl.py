"""DAMMRL pieces: reward terms, replay buffer, DQN updates, checkpoints, environment."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from dammrl.learning.rl.config import RewardWeights, TrainSettings
from dammrl.learning.rl.dqn import DualAgentDQN, ReplayBuffer
from dammrl.learning.rl.env import ACTIONS, OBSERVATION_SIZE, ReachEnv, RewardTerms, accuracy_term
from dammrl.learning.rl.train import CheckpointError, evaluate, load_checkpoint, train
from dammrl.stack.runner import ReachRunner
from dammrl_core.task import held_out_seeds

SMALL = TrainSettings(episodes=4, learning_starts=8, batch_size=8, buffer_size=500,
                      target_update_every=5, epsilon_decay_decisions=50)  # fmt: skip


def test_accuracy_term_discriminates_near_the_goal_in_centimetres() -> None:
    assert accuracy_term(0.0) == pytest.approx(2.0)
    assert accuracy_term(0.01) == pytest.approx(1 / 1.5)
    assert accuracy_term(0.05) == pytest.approx(1 / 25.5)


def test_reward_one_ignores_time_and_reward_two_charges_it() -> None:
    terms = RewardTerms(accuracy=0.5, time_s=0.4, effort_j=2.0, oscillations=3, success=True)
    r1, r2 = RewardWeights.preset(1), RewardWeights.preset(2)
    assert r1.beta == 0 and r2.beta > 0
    assert terms.total(r1) == pytest.approx(0.5 - r1.gamma * 2.0 - r1.eta * 3 + r1.rho)
    assert terms.total(r2) == pytest.approx(terms.total(r1) - r2.beta * 0.4)


def test_replay_buffer_wraps_around_and_samples_what_was_stored() -> None:
    buffer = ReplayBuffer(capacity=5, obs_size=2, seed=0)
    for k in range(8):
        buffer.add(np.full(2, k), (k % 2, k % 8), float(k), np.full(2, k + 1), k == 7)
    assert buffer.size == 5
    obs, actions, rewards, next_obs, dones = buffer.sample(100)
    assert set(rewards.tolist()) == {3.0, 4.0, 5.0, 6.0, 7.0}
    np.testing.assert_array_equal(obs[:, 0], rewards)
    np.testing.assert_array_equal(next_obs[:, 0], rewards + 1)
    assert np.all(dones[rewards == 7.0] == 1.0) and np.all(dones[rewards != 7.0] == 0.0)
    np.testing.assert_array_equal(actions[:, 0], rewards.astype(int) % 2)


def test_targets_follow_the_online_networks_only_every_n_updates() -> None:
    torch.manual_seed(0)
    agent = DualAgentDQN(OBSERVATION_SIZE, ACTIONS, SMALL, torch.device("cpu"))
    buffer = ReplayBuffer(100, OBSERVATION_SIZE, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(50):
        buffer.add(
            rng.normal(size=OBSERVATION_SIZE), (1, 3), 1.0, rng.normal(size=OBSERVATION_SIZE), False
        )
    frozen = [p.clone() for p in agent.target_robot.parameters()]
    for _ in range(SMALL.target_update_every - 1):
        agent.update(buffer.sample(8))
    assert all(
        torch.equal(a, b) for a, b in zip(frozen, agent.target_robot.parameters(), strict=True)
    )
    agent.update(buffer.sample(8))
    online = list(agent.q_robot.parameters())
    assert all(
        torch.equal(a, b) for a, b in zip(online, agent.target_robot.parameters(), strict=True)
    )


def test_q_values_move_toward_the_reward() -> None:
    torch.manual_seed(0)
    settings = SMALL.model_copy(update={"gamma": 0.5, "learning_rate": 1e-2})
    agent = DualAgentDQN(OBSERVATION_SIZE, ACTIONS, settings, torch.device("cpu"))
    buffer = ReplayBuffer(100, OBSERVATION_SIZE, seed=0)
    obs = np.zeros(OBSERVATION_SIZE, dtype=np.float32)
    for _ in range(64):
        buffer.add(obs, (0, 2), 3.0, obs, True)
    for _ in range(300):
        stats = agent.update(buffer.sample(16))
    assert stats.q_human == pytest.approx(3.0, abs=0.1) and stats.q_robot == pytest.approx(
        3.0, abs=0.1
    )


def test_environment_steps_one_decision_at_a_time() -> None:
    env = ReachEnv(ReachRunner(), RewardWeights.preset(2), max_decisions=3)
    obs, _ = env.reset(seed=1)
    assert obs.shape == (OBSERVATION_SIZE,) and np.all(obs[6:] == 0)
    obs, reward, terminated, truncated, info = env.step((1, 4))
    assert obs[7] == 1.0 and obs[8 + 4] == 1.0  # the model in force: E_small, j = 5
    assert np.isfinite(reward) and not terminated
    env.step((1, 4))
    *_, terminated, truncated, info = env.step((1, 4))
    assert truncated and "metrics" in info


def test_training_writes_a_checkpoint_that_resumes_and_evaluates(tmp_path: Path) -> None:
    logs = train(1, tmp_path, SMALL, "cpu", progress=lambda _: None)
    assert len(logs) == 4 and (tmp_path / "training.png").exists()
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    checkpoint = load_checkpoint(tmp_path)
    assert checkpoint["reward"] == 1 and checkpoint["settings"]["episodes"] == 4
    more = train(
        1, tmp_path, SMALL.model_copy(update={"episodes": 6}), "cpu", progress=lambda _: None
    )
    assert [log.episode for log in more] == [1, 2, 3, 4, 5, 6]
    result = evaluate(tmp_path, held_out_seeds(2))
    assert 0.0 <= result["success_rate"] <= 1.0 and result["episodes"] == 2
    with pytest.raises(CheckpointError, match="Reward 1 run"):
        train(2, tmp_path, SMALL, "cpu", progress=lambda _: None)


def test_missing_or_corrupt_checkpoints_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path)
    (tmp_path / "checkpoint.pt").write_bytes(b"\x00 not a torch file")
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(tmp_path)
    torch.save({"format": 99}, tmp_path / "checkpoint.pt")
    with pytest.raises(CheckpointError, match="not a dammrl checkpoint"):
        load_checkpoint(tmp_path)


def _posterior_right_after(n: int, true_model: int, seeds: int, use_time: bool) -> float:
    from dammrl_core.human import HumanModel
    from dammrl_core.intent.simulated import SimulatedHuman
    from dammrl_core.models import ModelSet
    from dammrl_core.posterior import HumanModelPosterior

    model = HumanModel()
    goal, right = np.array([0.5, 0.0, -0.2]), 0
    for seed in range(seeds):
        human = SimulatedHuman(model, ModelSet(), seed)
        posterior = HumanModelPosterior(model, use_decision_time=use_time)
        for _ in range(n):
            decision = human.decide(0.0, np.zeros(3), goal, 0, true_model)
            posterior.update(decision.correct, decision.decision_s)
        right += posterior.map_model == true_model
    return right / seeds


@pytest.mark.parametrize("true_model", [1, 2])
def test_posterior_finds_the_human_model_within_6_decisions(true_model: int) -> None:
    assert _posterior_right_after(6, true_model, seeds=200, use_time=True) >= 0.95


def test_posterior_from_commands_alone_needs_many_more_decisions() -> None:
    assert _posterior_right_after(8, 2, seeds=200, use_time=False) < 0.95
    assert _posterior_right_after(200, 2, seeds=200, use_time=False) >= 0.95
    assert _posterior_right_after(200, 1, seeds=200, use_time=False) >= 0.95


def test_policy_service_falls_back_to_the_safe_fixed_model(tmp_path: Path) -> None:
    from dammrl_core.models import ModelSet
    from dammrl_core.policy import FixedPolicy
    from dammrl_core.policy.learned import LearnedPolicy
    from dammrl_core.policy.loading import load_policy
    from dammrl_core.policy.settings import PolicySettings

    models = ModelSet()
    policy, health, description = load_policy(PolicySettings(checkpoint=tmp_path / "none"), models)
    assert isinstance(policy, FixedPolicy) and health == "degraded"
    assert "fallback M_2,1" in description and "no checkpoint" in description
    (tmp_path / "checkpoint.pt").write_bytes(b"garbage")
    policy, health, description = load_policy(PolicySettings(checkpoint=tmp_path), models)
    assert isinstance(policy, FixedPolicy) and "corrupt" in description
    shipped, health, _ = load_policy(PolicySettings(), models)
    assert isinstance(shipped, LearnedPolicy) and health == "ok" and shipped.reward == 2


def test_shipped_reward_1_policy_takes_smaller_steps_near_the_goal_than_reward_2() -> None:
    from dammrl.learning.rl.train import greedy_rollouts
    from dammrl_core.models import ModelSet
    from dammrl_core.policy.settings import SHIPPED_POLICY

    models, near = ModelSet(), {}
    for reward in (1, 2):
        run = SHIPPED_POLICY.parent.parent / f"reward{reward}"
        rollouts = greedy_rollouts(run, held_out_seeds(20))
        assert np.mean([r.metrics.success for r in rollouts]) >= 0.9
        near[reward] = np.mean(
            [models.steps_m(j).mean() for r in rollouts for d, _, j in r.decisions if d < 0.04]
        )
    assert near[1] < near[2]


def test_policy_service_estimates_a_real_humans_model_and_publishes_the_posterior() -> None:
    import threading
    import time

    from dammrl_core.human import HumanModel
    from dammrl_core.intent.simulated import SimulatedHuman
    from dammrl_core.models import ModelSet
    from dammrl_core.policy.settings import PolicySettings
    from schemas import DecisionRequest, Intent, ModelChoice
    from services.common.bus import Bus
    from services.policy.node import PolicyNode
    from tests.busutil import client_settings, free_port, listener_settings

    port, stop = free_port(), threading.Event()
    with (
        Bus(listener_settings(port), "controller") as controller,
        Bus(client_settings(port), "intent") as sensor,
        Bus(client_settings(port), "policy") as policy_bus,
    ):
        node = PolicyNode(PolicySettings(), HumanModel(), ModelSet(), policy_bus)
        thread = threading.Thread(target=node.run, args=(stop,))
        thread.start()
        controller.subscribe(ModelChoice)
        time.sleep(0.5)
        human = SimulatedHuman(HumanModel(), ModelSet(), seed=3)  # a careful human: E_small, i = 2
        requests, intents = controller.publisher(DecisionRequest), sensor.publisher(Intent)
        goal, choices = (0.5, 0.0, -0.2), []
        for k in range(1, 13):
            ee = (0.4, 0.0, -0.1)
            requests.send(DecisionRequest(header=requests.stamp(), episode=1, seed=1, request=k,
                                          t_s=k * 0.5, ee_pos_m=ee, goal_m=goal, primary_axis=0,
                                          human_model=1))  # fmt: skip
            time.sleep(0.05)
            decision = human.decide(0.0, np.array(ee), np.array(goal), 0, 2)
            intents.send(Intent(header=intents.stamp(), episode=1, request=k,
                                u_h=decision.intent.u_h, human_model=1, radius_m=0.01,
                                confidence=1.0, source="pad", person=True,
                                decision_s=decision.decision_s))  # fmt: skip
            time.sleep(0.05)
        time.sleep(0.3)
        while (message := controller.receive(0)) is not None:
            if isinstance(message, ModelChoice) and message.request > 0:
                choices.append(message)
        stop.set()
        thread.join(5)
    assert choices[-1].posterior is not None and choices[-1].posterior[1] > 0.95
    assert choices[-1].human_model == 2


def test_training_never_draws_a_held_out_seed_and_evaluation_only_does() -> None:
    from dammrl_core.errors import ConfigurationError
    from dammrl_core.task import HELD_OUT_START, training_seed

    assert training_seed(69, 99_999) < HELD_OUT_START
    for run_seed, episode in ((70, 0), (0, 100_000)):
        with pytest.raises(ConfigurationError, match="training uses seeds below"):
            training_seed(run_seed, episode)
    assert held_out_seeds(3) == range(HELD_OUT_START, HELD_OUT_START + 3)
    assert held_out_seeds("7000100:7000110") == range(7_000_100, 7_000_110)
    for bad in ("0:10", "x", "0", "7000010:7000005"):
        with pytest.raises(ConfigurationError):
            held_out_seeds(bad)
    with pytest.raises(Exception, match="outside its range"):
        TrainSettings(seed=70)
