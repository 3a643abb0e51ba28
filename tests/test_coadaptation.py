"""The posterior over M_ij (known evidence -> known posterior) and S3's re-selection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dammrl.runner import ReachRunner, evidence_of
from dammrl_core.coadaptation import (
    BASE,
    MODELS,
    OPTIONS,
    PRIOR_REACHES,
    DecisionEvidence,
    ModelPosterior,
    ModelRow,
    ModelTable,
    ReachEvidence,
    StepEvidence,
    Targets,
    execution_times,
    model_in_force,
    robot_model_of,
)
from dammrl_core.human import HumanModel
from dammrl_core.models import ModelSet
from dammrl_core.policy import FixedPolicy
from dammrl_core.policy.adaptive import AdaptivePolicy
from dammrl_core.policy.learned import LearnedPolicy
from dammrl_core.policy.loading import load_policy
from dammrl_core.policy.settings import PolicySettings

HUMAN = HumanModel()
MODEL_SET = ModelSet()


def table(success: dict[tuple[int, int], float] | None = None) -> ModelTable:
    """Every model: 10 s, 20 mm, half the time deciding, a quarter executing."""
    rows = tuple(
        ModelRow(
            human_model=i,
            robot_model=j,
            reaches=10,
            big_share=1.0 if i == 1 else 0.0,
            success_rate=(success or {}).get((i, j), 0.9),
            log_time_mean=math.log(10.0),
            log_time_sd=0.2,
            log_error_mean=math.log(0.02),
            log_error_sd=0.3,
            sparc_mean=-8.0,
            sparc_sd=2.0,
            decision_share=0.5,
            execution_share=0.25,
        )
        for i, j in OPTIONS
    )
    return ModelTable(
        seeds="0:10",
        step_time_log_intercept=math.log(10.0),  # tau = 10 s/m x L
        step_time_log_length=1.0,
        step_time_log_radius=0.0,
        step_time_log_sd=0.2,
        rows=rows,
    )


def reach(model: tuple[int, int], success: bool, t_s: float = 10.0) -> ReachEvidence:
    return ReachEvidence(model, success, t_s, 0.02, -8.0)


def test_the_persons_accuracy_is_a_beta_posterior_from_the_sub_models_prior() -> None:
    posterior = ModelPosterior(table(), HUMAN, MODEL_SET)
    for k in range(100):
        posterior.decision(DecisionEvidence(1, correct=k < 65, decision_s=None))
    prior = HUMAN.accuracy_big * PRIOR_REACHES
    assert posterior.person_accuracy(1) == pytest.approx((prior + 65) / (PRIOR_REACHES + 100))
    assert posterior.person_accuracy(2) == pytest.approx(HUMAN.accuracy_small)  # untouched


def test_a_doubtful_command_counts_as_its_confidence() -> None:
    sure, doubtful = (ModelPosterior(table(), HUMAN, MODEL_SET) for _ in range(2))
    sure.decision(DecisionEvidence(2, correct=False, decision_s=None))
    doubtful.decision(DecisionEvidence(2, correct=False, decision_s=None, confidence=0.5))
    prior = HUMAN.accuracy_small * PRIOR_REACHES
    assert sure.person_accuracy(2) == pytest.approx(prior / (PRIOR_REACHES + 1))
    assert doubtful.person_accuracy(2) == pytest.approx(prior / (PRIOR_REACHES + 0.5))


def test_decision_times_give_the_conjugate_normal_estimate_of_the_persons_speed() -> None:
    posterior = ModelPosterior(table(), HUMAN, MODEL_SET)
    slow = 2.0 * HUMAN.decision_median_small_s
    for _ in range(50):
        posterior.decision(DecisionEvidence(2, True, slow))
    posterior.decision(DecisionEvidence(2, True, HUMAN.decision_min_s))  # at the floor: left out
    tau, sigma = HUMAN.decision_scale_sd, HUMAN.decision_sigma
    shift = (50 / sigma**2) * math.log(2.0) / (1 / tau**2 + 50 / sigma**2)
    assert posterior.decision_ratio(2) == pytest.approx(math.exp(shift))
    assert posterior.decision_ratio(1) == pytest.approx(1.0)


def test_step_times_estimate_the_arms_factor_against_the_nominal_arm() -> None:
    posterior = ModelPosterior(table(), HUMAN, MODEL_SET)
    for _ in range(40):  # predicted 10 s/m x 0.02 m = 0.2 s; observed 0.3 s
        posterior.step(StepEvidence(1, 0.02, 0.01, 0.3))
    tau, sigma = 0.3, 0.2  # ARM_SCALE_PRIOR_SD, the table's step_time_log_sd
    shift = (40 / sigma**2) * math.log(1.5) / (1 / tau**2 + 40 / sigma**2)
    assert posterior.arm_scale == pytest.approx(math.exp(shift))


def test_the_person_and_the_arm_move_every_models_predicted_time() -> None:
    posterior = ModelPosterior(table(), HUMAN, MODEL_SET)
    assert posterior.predicted_log_time((1, 3)) == pytest.approx(math.log(10.0))  # nominal
    for _ in range(200):
        posterior.decision(DecisionEvidence(1, True, 2.0 * HUMAN.decision_median_big_s))
    ratio = posterior.decision_ratio(1)
    accuracy = posterior.person_accuracy(1)
    steps = (2 * HUMAN.accuracy_big - 1) / (2 * accuracy - 1)
    expected = math.log(10.0 * (0.25 + steps * (0.5 * ratio + 0.25)))
    for j in (1, 8):  # both step vectors of radius 1, neither ever in force
        assert posterior.predicted_log_time((1, j)) == pytest.approx(expected)
    assert posterior.predicted_log_time((2, 1)) == pytest.approx(math.log(10.0))


def test_reaches_move_the_model_in_force_and_the_chance_of_meeting_the_targets() -> None:
    posterior = ModelPosterior(table(), HUMAN, MODEL_SET)
    targets = Targets(success_min=0.8, time_max_s=20.0)
    before = posterior.meets(targets)
    for _ in range(6):
        posterior.observe(reach((1, 1), success=False, t_s=40.0))
    after = posterior.meets(targets)
    k = MODELS.index((1, 1))
    assert after[k] < 0.01 < before[k]
    assert np.delete(after, k) == pytest.approx(np.delete(before, k))  # one model's own
    assert posterior.success_belief((1, 1)) == pytest.approx((0.9 * 4 + 0.5, 0.1 * 4 + 6.5))


def test_the_posterior_over_models_is_a_distribution_and_reproducible() -> None:
    posterior = ModelPosterior(table({(2, 3): 0.99}), HUMAN, MODEL_SET)
    targets = Targets()
    p = posterior.probabilities(targets)
    assert p.shape == (16,) and p.sum() == pytest.approx(1.0)
    assert p.argmax() == MODELS.index((2, 3))
    assert np.array_equal(
        p, ModelPosterior(table({(2, 3): 0.99}), HUMAN, MODEL_SET).probabilities(targets)
    )


def test_targets_name_what_is_missed() -> None:
    targets = Targets(
        window=2,
        success_min=0.8,
        time_max_s=15.0,
        final_error_max_m=0.01,
        sparc_min=-5.0,
        comfort_min=3.0,
    )
    recent = [reach((1, 1), True, 30.0), reach((1, 1), False, 10.0)]
    assert targets.unmet(recent, [2.0]) == [
        "success 50% < 80%",
        "median time 20.0 s > 15 s",
        "median error 20 mm > 10 mm",
        "comfort 2.0 < 3",
        "SPARC -8.00 < -5",
    ]
    assert Targets().unmet([reach((1, 1), True)], []) == []


def test_missed_targets_switch_to_the_alternative_most_likely_to_meet_them() -> None:
    posterior = ModelPosterior(table({(1, 1): 0.5, (2, 3): 0.99}), HUMAN, MODEL_SET)
    policy = AdaptivePolicy(FixedPolicy(MODEL_SET, 1, 1), MODEL_SET, posterior, Targets(window=3))
    assert [policy.observe(reach((1, 1), True)) for _ in range(3)] == [None] * 3  # met
    switch = policy.observe(reach((1, 1), False, 30.0))  # the last 3: one failure
    assert switch is not None and policy.switches == [switch]
    assert (switch.from_model, switch.to_model, switch.reach) == (BASE, (2, 3), 4)
    assert switch.reasons == ("success 67% < 80%",)
    assert "the base policy -> M_2,3" in switch.line
    assert posterior.beliefs[BASE].failures == 1 and posterior.beliefs[(1, 1)].failures == 0
    choice = policy.decide(np.zeros(3), np.ones(3))
    assert (choice.human_model, choice.robot_model) == (2, 3)
    assert policy.recent == []  # judged afresh after a switch


def test_a_selected_model_that_fails_hands_back_to_the_base_policy() -> None:
    posterior = ModelPosterior(table({BASE: 0.95, (2, 3): 0.9}), HUMAN, MODEL_SET)
    policy = AdaptivePolicy(FixedPolicy(MODEL_SET, 1, 1), MODEL_SET, posterior, Targets(window=2))
    policy.selected, policy.allowed = (2, 3), frozenset({3})
    policy.observe(reach((2, 3), False))
    switch = policy.observe(reach((2, 3), False))
    assert switch is not None and (switch.from_model, switch.to_model) == ((2, 3), BASE)
    assert policy.selected is None and "-> the base policy (P(meets" in switch.line


def test_targets_no_model_can_meet_leave_the_policy_as_it_is() -> None:
    posterior = ModelPosterior(table({(1, 1): 0.99}), HUMAN, MODEL_SET)
    policy = AdaptivePolicy(FixedPolicy(MODEL_SET, 1, 1), MODEL_SET, posterior,
                            Targets(window=2, success_min=None, time_max_s=1.0))  # fmt: skip
    assert [policy.observe(reach((1, 1), True, 5.0)) for _ in range(4)] == [None] * 4
    assert policy.selected is None  # every model's time is 10 s: none likelier than M_1,1


def test_a_learned_base_chooses_only_among_the_allowed_step_vectors() -> None:
    learned = LearnedPolicy(MODEL_SET, PolicySettings().checkpoint)
    rng = np.random.default_rng(1)
    for _ in range(20):
        x, goal = rng.uniform(-0.2, 0.6, 3), rng.uniform(-0.2, 0.6, 3)
        choice = learned.decide_within(x, goal, 2, frozenset({3, 7}))
        assert choice.human_model == 2 and choice.robot_model in {3, 7}


def test_the_adaptive_kind_loads_around_the_learned_policy() -> None:
    policy, health, description = load_policy(PolicySettings(kind="adaptive"), MODEL_SET)
    assert isinstance(policy, AdaptivePolicy) and isinstance(policy.base, LearnedPolicy)
    assert health == "ok" and description.startswith("adaptive around the learned")


def test_execution_times_run_from_a_steps_start_to_the_next_request() -> None:
    assert execution_times([1.0, 2.0, 3.0], [0.0, 1.5, 2.7]) == [0.5, pytest.approx(0.7), None]
    assert model_in_force([(1, 2), (2, 3), (2, 3), (1, 2)]) == (1, 2)  # the first of a tie
    assert model_in_force([]) is None
    assert robot_model_of(MODEL_SET, MODEL_SET.steps_m(6) + 1e-9) == 6


def test_a_reach_in_process_gives_the_evidence_of_its_decisions_and_steps() -> None:
    runner = ReachRunner()
    result = runner.run(7_000_001, (2, 3))
    evidence = evidence_of(result, runner.settings.models)
    assert evidence.model == (2, 3) and evidence.success == result.metrics.success
    assert len(evidence.decisions) == len(result.decisions)
    assert all(d.human_model == 2 for d in evidence.decisions)
    assert {s.robot_model for s in evidence.steps} == {3}
    assert len(evidence.steps) >= len(result.steps) - 1
    assert all(0 < s.execution_s < 5 for s in evidence.steps)


def test_the_packaged_table_has_every_model() -> None:
    shipped = ModelTable.load()
    assert {(r.human_model, r.robot_model) for r in shipped.rows} == set(OPTIONS)
    assert 0 < shipped.step_time_s(0.02, 0.004) < 1


def test_evaluate_in_the_adaptive_mode_is_the_policy_itself_until_a_switch() -> None:
    from dammrl.rl.train import evaluate

    seeds = range(7_000_000, 7_000_003)
    plain = evaluate(PolicySettings().checkpoint, seeds)
    adaptive = evaluate(PolicySettings().checkpoint, seeds, adaptive=True)
    assert adaptive.pop("adaptive") is True and adaptive.pop("switches") == []
    assert adaptive == plain


def test_the_studys_adaptive_row_runs_its_seeds_as_one_session() -> None:
    from dammrl.study.configs import adaptive_configuration, variant_configurations
    from dammrl.study.run import Job, run_job, run_session

    seeds = (7_000_000, 7_000_001)
    records = run_session((adaptive_configuration(), seeds, "nominal"))
    assert [r.row["configuration"] for r in records] == ["4a-adaptive-r2"] * 2
    learned = next(c for c in variant_configurations() if c.key == "4s-dammrl-r2")  # shipped
    plain = [run_job(Job(learned, s, "nominal", k)).row for k, s in enumerate(seeds)]
    assert [r.row["t_total_s"] for r in records] == [p["t_total_s"] for p in plain]  # no switch


def test_the_studys_adaptive_sessions_are_one_per_seed_set_counted_in_reaches() -> None:
    from dammrl.study.configs import adaptive_configuration
    from dammrl.study.study import StudyOptions, adaptive_sessions

    options = StudyOptions(seeds=range(7_000_000, 7_000_004), sets=2, conditions=("nominal",))
    bars: list[tuple[int, str]] = []
    ticks: list[int] = []

    def progress(total: int, description: str):  # type: ignore[no-untyped-def]
        bars.append((total, description))
        return ticks.append

    records = adaptive_sessions(options, adaptive_configuration(), progress)
    assert bars == [(4, "adaptive sessions")] and ticks == [2, 2]
    assert [(r.row["seed"], r.row["seed_set"]) for r in records] == [
        (7_000_000, 0), (7_000_001, 0), (7_000_002, 1), (7_000_003, 1)]  # fmt: skip
