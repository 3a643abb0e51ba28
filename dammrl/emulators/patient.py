"""A simulated patient at the emulated pressure pad: the semi-virtual stack without a person.

It watches the bus like a patient watches the arm: each DecisionRequest (end-effector,
goal, primary axis) is decided by the same stochastic human as in virtual mode, then
*pressed* on the emulated sensor, so the decision travels the real semi-virtual path
(serial frames, decoder, intent service): a firm press for +1, a light press for -1, a
quick press for E_big, a held one for E_small, after the human's reaction time. The
patient keeps one sub-model (``human_model``); the policy's posterior should find it.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from dammrl.emulators.pad import SensorEmulator
from dammrl_core.human import HumanModel
from dammrl_core.intent.simulated import Decision, SimulatedHuman
from dammrl_core.models import ModelSet
from schemas import DecisionRequest
from services.common.bus import Bus

log = logging.getLogger("dammrl.patient")

FIRM_LEVEL = 0.95  # normalised pressure (1 = the calibration's firm press)
LIGHT_LEVEL = 0.35
QUICK_PRESS_S = 0.2  # below the decoder's long_press_s (0.5 s): E_big
HELD_PRESS_S = 0.8  # above it: E_small


class SimulatedPatient:
    def __init__(
        self,
        sensor: SensorEmulator,
        human_model: int,
        human: HumanModel | None = None,
        seed: int = 0,
    ) -> None:
        self.sensor = sensor
        self.human_model = human_model
        self.human = SimulatedHuman(human or HumanModel(), ModelSet(), seed)
        self.answered = 0

    def answer(self, request: DecisionRequest) -> Decision:
        """Decide like the simulated human, then press the pad accordingly."""
        decision = self.human.decide(
            0.0,
            np.array(request.ee_pos_m),
            np.array(request.goal_m),
            request.primary_axis,
            self.human_model,
        )
        level = FIRM_LEVEL if decision.intent.u_h > 0 else LIGHT_LEVEL
        duration = QUICK_PRESS_S if self.human_model == 1 else HELD_PRESS_S
        self.sensor.press(level, duration, delay_s=decision.decision_s)
        self.answered += 1
        log.info(
            "request %d: %s %s press in %.2f s",
            request.request,
            "firm" if level == FIRM_LEVEL else "light",
            "quick" if duration == QUICK_PRESS_S else "held",
            decision.decision_s,
        )
        return decision

    def run(self, bus: Bus, stop: threading.Event) -> None:
        bus.subscribe(DecisionRequest)
        bus.expect(DecisionRequest, "controller")
        while not stop.is_set():
            message = bus.receive(0.1)
            if isinstance(message, DecisionRequest):
                self.answer(message)
