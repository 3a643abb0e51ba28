"""What the participant's page says, decided from the session's steps and the stack's
messages: a state machine with no server and no clock.

One screen at a time fills the words area (at least half of the page): a title, a line,
the reach's place in the session ("Trial 3 of 5 · Block 2 of 3"), and for a decision the
two direction arrows with the input that gives each. An emergency stop and a pause take
the whole page over until they end, whatever else happens meanwhile; the screen that
comes under them shows again after them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

from schemas import (
    DecisionRequest,
    EmergencyStop,
    EpisodeResult,
    Intent,
    IntentEvidence,
    Message,
    SessionControl,
    TaskGoal,
)
from schemas.messages import OPERATOR

OUTCOME_S = 2.0
"""How long a reach's outcome stays on the page before the next reach begins, by default
[s] (a session's ``--outcome-s``, 0-30)."""
KINDS = ("welcome", "block", "ready", "cue", "moving", "outcome", "rest", "comfort", "thanks",
         "stopped", "released", "paused", "taken", "end", "info", "not-counted")  # fmt: skip
"""Every screen the page can show (``Screen.kind``)."""


@dataclass(frozen=True)
class Inputs:
    """How the participant gives each decision: written under its arrow."""

    forward: str
    back: str
    note: str = ""


INPUTS = {
    "pad": Inputs("Press firmly", "Press lightly", "Quick for big steps, held for small ones."),
    "lsl": Inputs(
        "Close your hand", "Open your hand", "Briefly for big steps, held for small ones."
    ),
    "simulated": Inputs("Forward", "Back", "The simulated patient decides."),
}
"""The inputs of the built-in intent sources."""


def inputs_for(source: str) -> Inputs:
    """The inputs of intent source ``source`` (a lab's own: named by it)."""
    return INPUTS.get(source, Inputs("Forward", "Back", f"Use the {source}."))


@dataclass(frozen=True)
class Place:
    """A reach's place in the session."""

    trial: int  # in its block, from 1
    trials: int  # in its block
    block: int  # the block's position in this participant's order, from 1
    blocks: int
    practice: bool = False

    def text(self) -> str:
        practice = "Practice · " if self.practice else ""
        return (
            f"{practice}Trial {self.trial} of {self.trials} · Block {self.block} of {self.blocks}"
        )


@dataclass(frozen=True)
class Screen:
    """One screen of the page (what ``page.html`` renders)."""

    kind: str  # one of KINDS
    title: str
    line: str = ""
    tone: str = "info"  # info, decide, good, bad, stop, pause
    place: str = ""  # the reach's place ("Trial 3 of 5 · Block 2 of 3"), or ""
    arrows: bool = False  # the two direction arrows with their inputs
    chosen: int = 0  # the arrow of the decision taken: +1 forward, -1 back, 0 none
    question: int = 0  # a comfort question (its buttons show) by its number; 0: none
    countdown_s: float | None = None  # a rest's time left [s]

    def message(self, inputs: Inputs) -> dict[str, Any]:
        """The screen as the page receives it."""
        return {"t": "screen", **asdict(self), "inputs": asdict(inputs)}


WELCOME = Screen("welcome", "Welcome", "The session starts soon.")
STOPPED = Screen("stopped", "STOPPED", "The arm is stopped. Stay relaxed: your therapist is "
                 "with you.", tone="stop")  # fmt: skip
RELEASED = Screen("released", "The arm is free again", "Your therapist will go on soon.")
END = Screen("end", "Thank you", "The session is complete.", tone="good")


class Screens:
    """The page's screen, from the session's steps and the stack's messages."""

    def __init__(self, inputs: Inputs) -> None:
        self.inputs = inputs
        self.places: dict[int, Place] = {}  # the running stack's reaches, by episode
        self.episode = 0  # the reach under way
        self.ended = 0  # the last reach whose outcome came
        self.guided = False  # the therapist decides for the participant
        self.paused = False
        self.stopped = False  # an emergency stop (the bus's or the session's)
        self.question = 0  # the comfort questions asked so far
        self.asking = False  # a decision request is open (the cue shows, or showed)
        self.base = WELCOME  # what shows when neither a stop nor a pause does

    @property
    def screen(self) -> Screen:
        if self.stopped:
            return STOPPED
        if self.paused:
            return Screen("paused", "Paused", "Relax. We go on soon.", tone="pause",
                          place=self._place())  # fmt: skip
        return self.base

    # ---- the session's steps ----------------------------------------------------------
    def expect_run(self, places: dict[int, Place], inputs: Inputs) -> None:
        """A new stack run: its reaches' places (by episode), who decides and how."""
        self.places, self.inputs, self.episode, self.ended = places, inputs, 0, 0
        self.guided = self.paused = False

    def show(self, screen: Screen) -> None:
        self.base = screen

    def rest(self, seconds: float) -> None:
        self.base = Screen("rest", "Rest", "Relax your arm. We go on in", countdown_s=seconds)

    def comfort(self) -> int:
        """Ask the comfort question; its number. It shows over a pause (the session holds
        the next reach back while it asks)."""
        self.question += 1
        self.paused = False
        self.base = Screen("comfort", "How comfortable was that block?", "Touch one answer.",
                           tone="decide", question=self.question)  # fmt: skip
        return self.question

    def answered(self, rating: int | None) -> None:
        if rating is None:
            self.base = Screen("thanks", "Block finished", "Your therapist will go on soon.")
        else:
            self.base = Screen("thanks", "Thank you", f"You answered {rating} of 5.", tone="good")

    def stop(self, engaged: bool) -> None:
        """The session's own stop (typed while no stack runs) or its release."""
        if self.stopped and not engaged:
            self.base = RELEASED
        self.stopped = engaged

    # ---- the stack's messages ---------------------------------------------------------
    def take(self, message: Message) -> bool:
        """Follow one bus message; whether the screen may have changed."""
        if isinstance(message, TaskGoal):
            return self._new_reach(message)
        if isinstance(message, DecisionRequest | Intent) and not self._running(message.episode):
            return False  # late: its reach has its outcome (or was never announced here)
        if isinstance(message, DecisionRequest):
            self.asking = True
            self.base = self._cue()
        elif isinstance(message, Intent):
            self.asking = False
            self.base = self._moving(message)
        elif isinstance(message, IntentEvidence):
            return self._not_counted(message)
        elif isinstance(message, EpisodeResult):
            self._outcome(message)
        elif isinstance(message, SessionControl):
            self._control(message)
        elif isinstance(message, EmergencyStop):
            self.stop(message.engaged)
        else:
            return False
        return True

    def _running(self, episode: int) -> bool:
        """Whether ``episode`` runs: the reach under way, or a later one whose goal this
        page did not hear (a page that joined late, a goal announced before it listened)."""
        if episode > self.episode:
            self.episode, self.paused = episode, False
        return episode == self.episode and self.ended != episode

    def _new_reach(self, goal: TaskGoal) -> bool:
        if goal.episode == self.episode:
            return False  # announced again
        self.episode, self.paused = goal.episode, False  # a held reach begins only resumed
        self.asking = False  # an earlier reach's question closed with it
        self.base = Screen("ready", "Get ready", "Reach for the red button.", place=self._place())
        return True

    def _cue(self) -> Screen:
        if self.guided:
            return self._taken()
        return Screen("cue", "Decide now", self.inputs.note, tone="decide",
                      place=self._place(), arrows=True)  # fmt: skip

    def _taken(self, line: str = "Relax and watch the arm.") -> Screen:
        return Screen("taken", "Your therapist decides", line, place=self._place())

    def _moving(self, intent: Intent) -> Screen:
        way = "forward" if intent.u_h > 0 else "back"
        if self.guided or intent.source == OPERATOR:
            return self._taken(f"The arm moves {way}.")
        said = f"You chose {way}." if intent.person else f"The arm moves {way}."
        return Screen("moving", f"Moving {way}", said, place=self._place(), arrows=True,
                      chosen=intent.u_h)  # fmt: skip

    def _not_counted(self, evidence: IntentEvidence) -> bool:
        """A movement that answers no question: the participant is told why (not while the
        therapist decides, nor for one that was acted on)."""
        if evidence.acted or self.guided or not self._running(evidence.episode):
            return False
        if "before the request opened" in evidence.reason:
            line = "That movement began before the question. Relax, then answer."
            self.base = Screen("not-counted", "Too early", line, tone="bad", place=self._place())
        elif evidence.reason == "no request open":
            line = "That movement counts for nothing. Wait for 'Decide now'."
            self.base = Screen("not-counted", "No question now", line, tone="bad",
                               place=self._place())  # fmt: skip
        else:
            return False
        return True

    def _outcome(self, result: EpisodeResult) -> None:
        self.ended = result.episode
        place = self._place()
        # a question still open closes with its reach: nobody should go on answering it
        closed = " The question is closed: no need to answer it." if self.asking else ""
        self.asking = False
        if result.outcome == "stopped":
            return  # the stop's screen says it
        if result.success:
            self.base = Screen("outcome", "Well done!", f"Button pressed in "
                               f"{result.t_total_s:.0f} s.{closed}", tone="good",
                               place=place)  # fmt: skip
        elif result.outcome == "skipped":
            self.base = Screen("outcome", "Reach ended", f"Your therapist ended that one.{closed}",
                               place=place)  # fmt: skip
        else:
            self.base = Screen("outcome", "Reach ended", f"That one did not reach the button."
                               f"{closed}", tone="bad", place=place)  # fmt: skip

    def _control(self, control: SessionControl) -> None:
        if control.action == "pause":
            self.paused = True
        elif control.action == "resume":
            self.paused = False
        elif control.action == "take":
            self.guided = True
            self.base = self._taken()
        elif control.action == "give":
            self.guided = False
            self.base = replace(self._cue(), kind="cue", title="Your turn again")

    def _place(self) -> str:
        place = self.places.get(self.episode)
        if place is not None:
            return place.text()
        return f"Reach {self.episode}" if self.episode else ""
