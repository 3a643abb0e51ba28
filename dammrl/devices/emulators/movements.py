"""What an emulated wearer does, whatever the sensor: commands planned on the sensor's own
clock, sensors that come off, and a cooperative participant's cued calibration session."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dammrl_core.intent.emg.training import Cue


@dataclass
class Movement:
    """One command: the muscle group or posture of ``u_h`` from ``start_s`` [s]."""

    u_h: int
    start_s: float
    duration_s: float
    strength: float  # of a full one (0-1)


class Wearer:
    """The schedule of a synthetic sensor's wearer (its subclasses make the samples)."""

    STRENGTH = (0.4, 1.0)  # a command's strength is drawn from this range

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.t_s = 0.0  # the sensor's own clock [s]
        self.contractions: list[Movement] = []
        self.lifted: dict[int, str] = {}  # channel -> "flat" | "clip"

    def generate(self, n: int) -> np.ndarray:
        """The next ``n`` samples (n, channels)."""
        raise NotImplementedError

    def contract(self, u_h: int, duration_s: float, delay_s: float = 0.0,
                 strength: float | None = None) -> None:  # fmt: skip
        """A command ``u_h`` from ``delay_s`` after now, held ``duration_s``."""
        level = float(self.rng.uniform(*self.STRENGTH)) if strength is None else strength
        self.contractions.append(Movement(u_h, self.t_s + delay_s, duration_s, level))

    def release(self) -> None:
        """Every command in progress or planned ends now (the wearer relaxes)."""
        for c in self.contractions:
            c.duration_s = max(0.0, min(c.duration_s, self.t_s - c.start_s))

    def lift(self, channel: int, how: str = "flat") -> None:
        """A sensor comes off: its channel flat, or clipping at the amplifier's rail."""
        self.lifted[channel] = how

    def put_back(self, channel: int) -> None:
        self.lifted.pop(channel, None)

    def _apply_lifted(self, out: np.ndarray) -> None:
        for channel, how in self.lifted.items():  # flat: no contact; clip: the rail
            out[:, channel] = 0.0 if how == "flat" else np.clip(20 * out[:, channel], -1, 1)

    def _advance(self, t: np.ndarray, rate_hz: float, linger_s: float = 0.0) -> None:
        """The clock past ``t``; commands that ended (and their ``linger_s``) forgotten."""
        if len(t):
            self.t_s = float(t[-1] + 1 / rate_hz)
        self.contractions = [c for c in self.contractions
                             if c.start_s + c.duration_s + linger_s > self.t_s]  # fmt: skip


def cued_session(wearer: Wearer, rate_hz: float, blocks: int = 4, trial_s: float = 3.0,
                 relax_s: float = 1.5, seed: int = 0, reaction_s: float = 0.3,
                 ) -> tuple[np.ndarray, np.ndarray, list[Cue]]:  # fmt: skip
    """A cooperative participant's calibration, as ``dammrl intent calibrate`` cues it:
    per block rest, -1 and +1 in a shuffled order; (samples, times, cues)."""
    order = np.random.default_rng(seed + 1)
    chunks, cues, t = [], [], 0.0
    for block in range(blocks):
        for label in order.permutation([-1, 0, 1]):
            if label:
                wearer.contract(int(label), trial_s - reaction_s, reaction_s)
            chunks.append(wearer.generate(round(trial_s * rate_hz)))
            cues.append(Cue(int(label), t, t + trial_s, block))
            chunks.append(wearer.generate(round(relax_s * rate_hz)))
            t += trial_s + relax_s
    samples = np.concatenate(chunks)
    return samples, np.arange(len(samples)) / rate_hz, cues
