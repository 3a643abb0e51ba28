"""A simulated patient at the emulated pressure pad: the semi-virtual stack without a person.

It watches the bus like a patient watches the arm: each DecisionRequest (end-effector,
goal, primary axis) is decided by the same stochastic human as in virtual mode, then
*pressed* on the emulated sensor (or made as a contraction on the emulated EMG), so the
decision travels the real semi-virtual path (serial frames or an LSL stream, decoder,
intent service): a firm press (flexion) for +1, a light press (extension) for -1, a quick
one for E_big, a held one for E_small, after the human's reaction time. The
patient keeps one sub-model (``human_model``); the policy's posterior should find it.
"""

from __future__ import annotations

import logging
import threading
from typing import Protocol

import numpy as np

from dammrl.devices.emulators.pad import SensorEmulator
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


class Body(Protocol):
    """How the patient acts on a sensor: command u_h, quick (E_big) or held (E_small)."""

    def act(self, u_h: int, held: bool, delay_s: float) -> str:
        """Act after ``delay_s`` [s]; a few words saying what was done (for the log)."""
        ...


class PadPresses:
    """The pad: a firm press for +1, a light one for -1; quick or held."""

    def __init__(self, sensor: SensorEmulator) -> None:
        self.sensor = sensor

    def act(self, u_h: int, held: bool, delay_s: float) -> str:
        level = FIRM_LEVEL if u_h > 0 else LIGHT_LEVEL
        self.sensor.press(level, HELD_PRESS_S if held else QUICK_PRESS_S, delay_s=delay_s)
        return f"{'firm' if u_h > 0 else 'light'} {'held' if held else 'quick'} press"


class SimulatedPatient:
    def __init__(
        self,
        body: SensorEmulator | Body,
        human_model: int,
        human: HumanModel | None = None,
        seed: int = 0,
    ) -> None:
        self.body = PadPresses(body) if isinstance(body, SensorEmulator) else body
        self.human_model = human_model
        self.human = SimulatedHuman(human or HumanModel(), ModelSet(), seed)
        self.answered = 0

    def answer(self, request: DecisionRequest) -> Decision:
        """Decide like the simulated human, then act on the sensor accordingly."""
        decision = self.human.decide(
            0.0,
            np.array(request.ee_pos_m),
            np.array(request.goal_m),
            request.primary_axis,
            self.human_model,
        )
        done = self.body.act(decision.intent.u_h, self.human_model == 2, decision.decision_s)
        self.answered += 1
        log.info("request %d: %s in %.2f s", request.request, done, decision.decision_s)
        return decision

    def run(self, bus: Bus, stop: threading.Event) -> None:
        bus.subscribe(DecisionRequest)
        bus.expect(DecisionRequest, "controller")
        while not stop.is_set():
            message = bus.receive(0.1)
            if isinstance(message, DecisionRequest):
                self.answer(message)
