"""The participant display: a page in any browser of the lab's network, for a person
(possibly older, after a stroke) at arm's length from a screen beside the arm, and
nothing for an engineer.

- The words fill at least half of the page, in large type with strong colours (a setting
  makes them larger still): what to do now ("Decide now", "Rest", "Get ready"), the
  reach's place ("Trial 3 of 5 · Block 2 of 3"), and for a decision two big arrows, each
  with the input that gives it ("Press firmly", "Close your hand").
- Each reach's outcome ("Well done!") stays on the page until the next reach begins (the
  session holds it ``--outcome-s``, 2 s by default); an emergency stop turns the whole page
  red ("STOPPED") and a pause blue until they end; while the therapist decides, the page
  says so.
- Below the words, the arm, the table, the goal button, the current subgoal and its
  admission sphere (drawn at least 36 px across: a 4-10 mm sphere would be a dot), on a 2D
  canvas through a fixed camera.
- The comfort question after a block: five large answers, returned to the session (which
  puts the rating on the bus and in its events).
- The page reconnects by itself after any restart of the session, its stacks or the
  display; the console says whether a page is connected.

Modules: ``screens`` (what the page says: a state machine, no server, no clock),
``scene`` (the shapes drawn), ``server`` (HTTP and WebSocket on one port), ``page.html``
(the page; its messages handled in one table), ``participant`` (the display put together
and fed from the bus). Operator tools (Foxglove through ``dammrl view``) stay apart.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dammrl.people.display.participant import DISPLAYED, BusFeed, ParticipantDisplay
    from dammrl.people.display.screens import INPUTS, KINDS, Inputs, Place, Screen, inputs_for

__all__ = ["DISPLAYED", "INPUTS", "KINDS", "BusFeed", "Inputs", "ParticipantDisplay", "Place",
           "Screen", "inputs_for"]  # fmt: skip
_WHERE = {"DISPLAYED": "participant", "BusFeed": "participant", "ParticipantDisplay":
          "participant", "INPUTS": "screens", "KINDS": "screens", "Inputs": "screens",
          "Place": "screens", "Screen": "screens", "inputs_for": "screens"}  # fmt: skip


def __getattr__(name: str) -> Any:
    """The package's names, imported when first used (the server and the arm's geometry
    load only for a session that shows the page)."""
    if name not in _WHERE:
        raise AttributeError(f"module 'dammrl.people.display' has no attribute {name!r}")
    return getattr(importlib.import_module(f"dammrl.people.display.{_WHERE[name]}"), name)
