"""What the participant's page says, from the session's steps and the stack's messages
(the screens' state machine, no browser: tests/test_display.py renders them)."""

from __future__ import annotations

from dammrl.people.display.screens import INPUTS, Place, Screens
from schemas import (
    DecisionRequest,
    EmergencyStop,
    EpisodeResult,
    Header,
    Intent,
    SessionControl,
    TaskGoal,
)
from schemas.messages import OPERATOR

HEADER = Header(stamp_ns=1, seq=0, source="test")


def _goal(episode: int) -> TaskGoal:
    return TaskGoal(header=HEADER, episode=episode, seed=1, start_m=(0.3, 0, 0),
                    goal_m=(0.5, 0, -0.2), q_start_rad=(0, 1, 0, 1.6, 0, 0.3))  # fmt: skip


def _intent(u_h: int, source: str = "pad", person: bool = True) -> Intent:
    return Intent(header=HEADER, episode=1, request=1, u_h=u_h, human_model=1,  # type: ignore[arg-type]
                  radius_m=0.01, confidence=1.0, source=source, person=person,
                  decision_s=0.5)  # fmt: skip


def _control(action: str, episode: int = 1) -> SessionControl:
    return SessionControl(header=HEADER, episode=episode, action=action, who="T1")  # type: ignore[arg-type]


def _screens() -> Screens:
    screens = Screens(INPUTS["pad"])
    screens.expect_run({1: Place(3, 5, 2, 3), 2: Place(4, 5, 2, 3)}, INPUTS["pad"])
    return screens


def test_a_reach_goes_ready_cue_moving_outcome_with_its_place_and_arrows() -> None:
    screens = _screens()
    screens.take(_goal(1))
    assert screens.screen.kind == "ready" and screens.screen.place == "Trial 3 of 5 · Block 2 of 3"
    screens.take(DecisionRequest.model_construct(episode=1, request=1))
    cue = screens.screen
    assert cue.kind == "cue" and cue.arrows and cue.title == "Decide now"
    assert cue.message(screens.inputs)["inputs"]["forward"] == "Press firmly"
    screens.take(_intent(-1))
    moving = screens.screen
    assert (moving.kind, moving.line, moving.chosen) == ("moving", "You chose back.", -1)
    result = EpisodeResult.model_construct(
        episode=1, success=True, t_total_s=12.3, outcome="success"
    )
    screens.take(result)
    assert (screens.screen.kind, screens.screen.title) == ("outcome", "Well done!")
    screens.take(_intent(1))  # the last request's answer, late: the outcome stays
    screens.take(DecisionRequest.model_construct(episode=1, request=9))
    assert screens.screen.kind == "outcome"
    screens.take(_goal(2))
    assert screens.screen.place == "Trial 4 of 5 · Block 2 of 3"


def test_while_the_therapist_decides_the_page_never_says_you_chose() -> None:
    screens = _screens()
    screens.take(_goal(1))
    screens.take(_control("take"))
    screens.take(DecisionRequest.model_construct(episode=1, request=1))
    assert screens.screen.kind == "taken"
    screens.take(_intent(1, source=OPERATOR, person=False))
    assert screens.screen.title == "Your therapist decides"
    assert screens.screen.line == "The arm moves forward." and "You" not in screens.screen.line
    screens.take(_control("give"))
    assert screens.screen.kind == "cue" and screens.screen.title == "Your turn again"


def test_a_stop_and_a_pause_take_the_page_over_until_they_end() -> None:
    screens = _screens()
    screens.take(_goal(1))
    screens.take(_control("pause"))
    assert screens.screen.kind == "paused" and screens.screen.tone == "pause"
    screens.take(DecisionRequest.model_construct(episode=1, request=2))
    assert screens.screen.kind == "paused"  # a request meanwhile changes nothing seen
    screens.take(EmergencyStop(header=HEADER, engaged=True))
    assert (screens.screen.kind, screens.screen.title) == ("stopped", "STOPPED")
    stopped = EpisodeResult.model_construct(
        episode=1, success=False, t_total_s=3.0, outcome="stopped"
    )
    screens.take(stopped)
    screens.take(_control("resume"))
    assert screens.screen.kind == "stopped"  # the stop outlasts the pause and the result
    screens.take(EmergencyStop(header=HEADER, engaged=False))
    assert screens.screen.kind == "released"


def test_the_simulated_patients_choice_is_not_the_participants() -> None:
    screens = _screens()
    screens.take(_goal(1))
    screens.take(_intent(1, source="simulated", person=False))
    assert screens.screen.line == "The arm moves forward."


def test_a_comfort_question_has_a_number_and_its_answer_thanks() -> None:
    screens = _screens()
    first, second = screens.comfort(), screens.comfort()
    assert (first, second) == (1, 2) and screens.screen.question == 2
    screens.answered(4)
    assert screens.screen.title == "Thank you" and screens.screen.question == 0
    screens.rest(42.0)
    assert screens.screen.kind == "rest" and screens.screen.countdown_s == 42.0


def test_the_comfort_question_shows_over_the_pause_that_holds_the_next_reach_back() -> None:
    """Ending a block holds its next reach back with a pause, then asks: the participant
    sees the question, not "Paused"."""
    screens = _screens()
    screens.take(_goal(1))
    screens.take(_control("pause", episode=2))
    assert screens.screen.kind == "paused"
    screens.comfort()
    assert screens.screen.kind == "comfort"


def test_a_reach_whose_goal_the_page_missed_begins_with_its_first_request() -> None:
    screens = _screens()
    screens.take(DecisionRequest.model_construct(episode=2, request=1))
    assert screens.screen.kind == "cue" and screens.screen.place == "Trial 4 of 5 · Block 2 of 3"
    screens.take(DecisionRequest.model_construct(episode=1, request=7))  # an older reach's
    assert screens.screen.place == "Trial 4 of 5 · Block 2 of 3"


def test_a_movement_that_answers_no_question_is_said_and_an_open_one_closes_with_the_reach() -> (
    None
):
    """A contraction begun before the question, or with none open, counts for nothing: the
    participant is told so (not while the therapist decides); an outcome that comes while
    a question is open says it is closed."""
    from schemas import IntentEvidence

    def evidence(reason: str, acted: bool = False) -> IntentEvidence:
        return IntentEvidence.model_construct(episode=1, request=-1, acted=acted, reason=reason)

    screens = _screens()
    screens.take(_goal(1))
    assert screens.take(evidence("no request open"))
    assert (screens.screen.kind, screens.screen.title) == ("not-counted", "No question now")
    screens.take(DecisionRequest.model_construct(episode=1, request=1))
    assert screens.take(evidence("it began 0.4 s before the request opened"))
    assert screens.screen.title == "Too early"
    assert not screens.take(evidence("", acted=True))  # acted on: the Intent says it
    screens.take(_control("take"))
    assert not screens.take(evidence("no request open"))  # the therapist decides
    assert screens.screen.kind == "taken"
    screens.take(_control("give"))
    screens.take(EpisodeResult.model_construct(episode=1, success=False, t_total_s=30.0,
                                               outcome="timeout"))  # fmt: skip
    assert "The question is closed" in screens.screen.line
