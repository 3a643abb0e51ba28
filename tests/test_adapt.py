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

from dammrl.cli import main
from dammrl.learning.adapt import (
    GATE_SEEDS_PER_SEED,
    GATE_SEEDS_START,
    SIM_SEEDS_PER_SEED,
    SIM_SEEDS_START,
    PersonFit,
    RefineSettings,
    _episodes,
    _transitions,
    deployment_rate,
    fit_person,
    gate,
    recorded_reaches,
    refine,
)
from dammrl.learning.rl.config import RewardWeights
from dammrl.learning.rl.env import ReachEnv
from dammrl.people.session import Participant
from dammrl.stack.launch import Stack
from dammrl.stack.options import StackOptions
from dammrl.stack.runner import ReachRunner
from dammrl_core.coadaptation import Targets
from dammrl_core.errors import ConfigurationError
from dammrl_core.human import HumanModel, direction_to_goal
from dammrl_core.policy.learned import load_checkpoint
from dammrl_core.protocol import Condition
from tests.busutil import free_port

SEED = 7_800_000
SHIPPED = Path("reward2")
TINY = RefineSettings(sim_reaches=3, updates=40, gate_seeds=10)
NOMINAL_FIT = PersonFit(200, 0.85, 1.0, 0.8, 0.9)


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
    from dammrl.stack.recording import read_recording
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
    first, verdict = refine([recording], SHIPPED, tmp_path / "a", TINY)
    refine([recording], SHIPPED, tmp_path / "b", TINY)
    a, b = (torch.load(tmp_path / d / "checkpoint.pt", weights_only=True) for d in "ab")
    for net in ("q_human", "q_robot"):
        for name, tensor in a["agent"][net].items():
            assert torch.equal(tensor, b["agent"][net][name]), name
    shipped = load_checkpoint(SHIPPED)["agent"]["q_robot"]
    assert any(not torch.equal(t, shipped[n]) for n, t in a["agent"]["q_robot"].items())
    meta = json.loads((tmp_path / "a" / "refined.json").read_text())
    assert meta["recorded_transitions"] == first.recorded and str(recording) in meta["recordings"]
    assert meta["gate"]["deployed"] == verdict.deployed and meta["gate"]["seeds"] == 10
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


# ---- the gate: a refined policy is deployed only when better ------------------------------
def worse_policy(folder: Path) -> Path:
    """The shipped policy with its robot agent pushed to M_i,2 (large z steps, which miss
    the button most of the time)."""
    checkpoint = load_checkpoint(SHIPPED)
    bias = checkpoint["agent"]["q_robot"]["4.bias"]
    bias[1] += 1e4
    folder.mkdir(parents=True)
    torch.save(checkpoint, folder / "checkpoint.pt")
    return folder


def test_the_gate_refuses_a_worse_candidate_and_says_why(tmp_path: Path) -> None:
    worse = worse_policy(tmp_path / "worse")
    verdict = gate(worse, SHIPPED, NOMINAL_FIT, RefineSettings(gate_seeds=12))
    assert not verdict.deployed
    assert verdict.gain.high < 0  # measurably worse for the fitted person
    assert "on 12 reaches of the fitted person" in verdict.reason and "<= 0 s" in verdict.reason
    assert verdict.candidate[0] < verdict.in_use[0]  # less success


def test_the_gate_deploys_a_candidate_better_than_the_policy_in_use(tmp_path: Path) -> None:
    worse = worse_policy(tmp_path / "worse")
    verdict = gate(SHIPPED, worse, NOMINAL_FIT, RefineSettings(gate_seeds=12))
    assert verdict.deployed and verdict.gain.low > 0 and "> 0 s" in verdict.reason


def test_a_gain_below_the_stated_minimum_is_not_deployed(tmp_path: Path) -> None:
    worse = worse_policy(tmp_path / "worse")
    verdict = gate(SHIPPED, worse, NOMINAL_FIT, RefineSettings(gate_seeds=12, min_gain_s=60))
    assert not verdict.deployed and "<= 60 s" in verdict.reason


def test_the_gates_false_positive_rate_is_near_its_level_and_a_real_gain_is_deployed() -> None:
    """The gate on per-reach gains spread as a person's are (sd 5 s): a candidate no better
    (true gain 0) is deployed about 2.5 % of the time (a rule on the mean gain, not its
    lower bound, would deploy half); one 5 s better nearly always, on 40 reaches."""
    gains = np.random.default_rng(3).normal(0.0, 5.0, 500)
    false_positives, gates = deployment_rate(gains, 0.0, 40, gates=400)
    assert false_positives / gates <= 0.05
    deployed, gates = deployment_rate(gains, 5.0, 40, gates=100)
    assert deployed / gates >= 0.9
    assert deployment_rate(gains, -5.0, 40, gates=100)[0] == 0  # a worse one: never


def test_the_simulated_reaches_and_the_gate_of_every_seed_have_task_seeds_of_their_own() -> None:
    """Four refinement seeds: their simulated reaches' and their gates' task seeds are
    disjoint, and all lie between the model table's and the held-out evaluation's."""
    top = RefineSettings.model_fields["seed"].metadata
    seeds = range(0, next(m.le for m in top if hasattr(m, "le")) + 1)
    used: list[range] = []
    for s in seeds:
        used.append(range(SIM_SEEDS_START + s * SIM_SEEDS_PER_SEED,
                          SIM_SEEDS_START + (s + 1) * SIM_SEEDS_PER_SEED))  # fmt: skip
        used.append(range(GATE_SEEDS_START + s * GATE_SEEDS_PER_SEED,
                          GATE_SEEDS_START + (s + 1) * GATE_SEEDS_PER_SEED))  # fmt: skip
    every = [seed for block in used for seed in block]
    assert len(every) == len(set(every))
    assert min(every) >= 6_900_012 and max(every) < 7_000_000
    with pytest.raises(ValueError, match="less than or equal to 3"):
        RefineSettings(seed=4)
    with pytest.raises(ValueError, match="less than or equal to 7500"):
        RefineSettings(sim_reaches=SIM_SEEDS_PER_SEED + 1)


@pytest.mark.parametrize(
    ("flag", "value", "says"),
    [("--seed", "4", "0-3"), ("--sim-reaches", "7501", "0-7500"), ("--updates", "0", "1-1000000"),
     ("--conservative", "-1", "0-100"), ("--gate-seeds", "9", "10-5000"),
     ("--min-gain-s", "nan", "0-60")],
)  # fmt: skip
def test_adapts_settings_are_refused_at_the_command_line_in_one_line(
    flag: str, value: str, says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["adapt", "--recordings", "x.mcap", "--out", "y", flag, value])
    assert exit_info.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert flag in last and says in last and repr(value) in last


def test_the_command_lines_ranges_are_the_settings() -> None:
    from dammrl.cli import coadapt

    assert coadapt.SIM_SEEDS_PER_SEED == SIM_SEEDS_PER_SEED
    assert coadapt.GATE_SEEDS_PER_SEED == GATE_SEEDS_PER_SEED


def test_the_fit_gives_each_radius_its_own_accuracy_when_it_has_enough_decisions() -> None:
    decisions = [(1, k < 12, 1.0) for k in range(20)] + [(2, True, 2.0)] * 5
    fit = fit_person(decisions)
    assert fit.accuracy_big == pytest.approx(0.6)
    assert fit.accuracy_small == fit.accuracy == pytest.approx(17 / 25)  # too few: overall
    assert fit.decision_time_factor == 1.0
    assert fit.person().accuracy_under(1, 0.8) == pytest.approx(0.6)


@pytest.mark.slow
def test_adapt_keeps_a_participants_policy_when_the_candidate_is_not_better(
    recording: Path, tmp_path: Path
) -> None:
    """``dammrl adapt --participant``: the candidate goes to policy-candidates/; the policy
    in use is left as it was and the command says why."""
    participant = Participant(tmp_path, "P007")
    folder = participant.folder / "ses-01" / "recordings"
    folder.mkdir(parents=True)
    (folder / "run-1.mcap").write_bytes(recording.read_bytes())
    in_use = worse_policy(participant.policy_folder)
    before = (in_use / "checkpoint.pt").read_bytes()
    command = [sys.executable, "-m", "dammrl", "adapt", "--participant", "P007", "--root",
               str(tmp_path), "--sim-reaches", "2", "--updates", "5", "--gate-seeds", "10",
               "--min-gain-s", "60"]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "not deployed: the candidate" in done.stdout and "<= 60 s" in done.stdout
    assert (participant.policy_folder / "checkpoint.pt").read_bytes() == before
    assert (participant.folder / "policy-candidates" / "001" / "checkpoint.pt").is_file()
    assert participant.next_candidate_folder().name == "002"


def test_deploying_keeps_the_replaced_policy_beside_the_candidates(tmp_path: Path) -> None:
    participant = Participant(tmp_path, "P008")
    old = worse_policy(participant.policy_folder)
    old_bytes = (old / "checkpoint.pt").read_bytes()
    candidate = participant.next_candidate_folder()
    candidate.mkdir(parents=True)
    (candidate / "checkpoint.pt").write_bytes(b"new")
    assert participant.deploy_policy(candidate) == participant.policy_folder
    assert (participant.policy_folder / "checkpoint.pt").read_bytes() == b"new"
    retired = participant.folder / "policy-candidates" / "001-replaced" / "checkpoint.pt"
    assert retired.read_bytes() == old_bytes


def test_gate_rates_prints_the_false_positive_rate_and_power_of_each_gate_size(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["coadapt", "gate-rates", "--gates", "20", "--gate-seeds", "40", "200"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("gains: sd 2 s, 50% identical, 3% each of +-50 s")
    assert [line.split(" reaches:")[0] for line in lines[1:]] == ["40", "200"]
    assert all("false positives" in line and "power at 2.5 s" in line for line in lines[1:])
