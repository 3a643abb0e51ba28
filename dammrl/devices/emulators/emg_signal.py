"""Synthetic surface EMG of a forearm: two muscle groups, electrodes, and what goes wrong.

No pip package ships a real EMG data set (LibEMG's and MOABB's download at run time), so
the emulated sensor is a model, seeded and documented:

* two muscle groups: the flexors make +1, the extensors -1; each channel sits over one
  group and picks up ``crosstalk`` of the other's signal;
* a contraction's activity is band-limited Gaussian noise (20-450 Hz, surface EMG's
  band) under a trapezoid envelope (30 ms ramps) of a random strength (0.4-1.0 of a
  full contraction, whose RMS is 1);
* tonic activity at rest (3 % of the flexors' and extensors' full signal) and white
  electrode noise of ``noise_rms``; 50 Hz mains hum;
* motion artefacts: low-frequency bumps (2-5 Hz) on every channel, ``artefact_per_min``;
* drift: each channel's gain follows a slow random walk (electrode contact, sweat);
* electrode lift-off on demand: one channel flat (or clipping) until put back.

The sample rate and channel count are those of a typical 8-channel armband (Myo: 200 Hz;
research amplifiers: 1-2 kHz); default 1 kHz, 8 channels. Samples are in microvolts, a
full contraction's RMS ``full_uv`` (surface EMG of the forearm: a few hundred µV), as
many amplifier programs stream them; an amplifier's own faults (a DC offset, another
gain) are the stream's (``dammrl.devices.emulators.emg.EmgStream``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import signal

from dammrl.devices.emulators.movements import Wearer

REST_TONE = 0.03
RAMP_S = 0.03
HUM_HZ = 50.0


@dataclass(frozen=True)
class EmgModel:
    channels: int = 8
    rate_hz: float = 1000.0
    noise_rms: float = 0.05  # electrode noise, relative to a full contraction's RMS (1.0)
    crosstalk: float = 0.3  # share of the other muscle group on each channel
    hum_rms: float = 0.02  # 50 Hz mains
    artefact_per_min: float = 2.0  # motion artefacts per minute
    artefact_size: float = 0.6  # their peak, relative to a full contraction
    drift_per_min: float = 0.1  # log-sd of each channel's gain after a minute
    full_uv: float = 500.0  # a full contraction's RMS [µV]: the unit of the levels above


NOISE_LEVELS: dict[str, EmgModel] = {
    "low": EmgModel(noise_rms=0.02, crosstalk=0.2, hum_rms=0.01, artefact_per_min=0.0,
                    drift_per_min=0.02),
    "medium": EmgModel(),
    "high": EmgModel(noise_rms=0.3, crosstalk=0.7, hum_rms=0.1, artefact_per_min=10.0,
                     drift_per_min=0.5),
}  # fmt: skip
"""The emulator's three noise levels (the benchmark's offline figures use all three)."""


@dataclass
class EmgSynth(Wearer):
    """Generates the samples of one forearm, chunk by chunk, on its own clock (from 0 s)."""

    model: EmgModel = field(default_factory=EmgModel)
    seed: int = 0

    def __post_init__(self) -> None:
        Wearer.__init__(self, self.seed)
        m = self.model
        self.artefacts: list[tuple[float, float, float]] = []  # (start, frequency, sign)
        self.gain_log = np.zeros(m.channels)
        self.weights = self._crosstalk(m)
        self.band = signal.butter(2, [20, min(450, 0.45 * m.rate_hz)], "bandpass",
                                  fs=m.rate_hz, output="sos")  # fmt: skip
        self.band_state = np.zeros((self.band.shape[0], 2, 2))

    @staticmethod
    def _crosstalk(m: EmgModel) -> np.ndarray:
        """(channels, 2): each channel's share of the flexors' and the extensors' signal."""
        over_flexors = np.arange(m.channels) < m.channels // 2
        return np.where(over_flexors[:, None], [1.0, m.crosstalk], [m.crosstalk, 1.0])

    # ---- the samples -----------------------------------------------------------------------
    def generate(self, n: int) -> np.ndarray:
        """The next ``n`` samples (n, channels)."""
        m = self.model
        t = self.t_s + np.arange(n) / m.rate_hz
        activity = self._activity(n, t)  # (n, 2)
        out = activity @ self.weights.T
        out += self.rng.normal(0, m.noise_rms, (n, m.channels))
        out += m.hum_rms * np.sqrt(2) * np.sin(2 * np.pi * HUM_HZ * t)[:, None]
        out += self._artefacts(t)[:, None]
        out *= np.exp(self._drift(n))
        self._apply_lifted(out)
        self._advance(t, m.rate_hz)
        return np.asarray(out * m.full_uv)

    def _activity(self, n: int, t: np.ndarray) -> np.ndarray:
        """Band-limited noise of each muscle group under its envelope (n, 2)."""
        white = self.rng.normal(0, 1, (n, 2))
        shaped, self.band_state = _filter(self.band, white, self.band_state)
        shaped /= 0.75  # the band's loss of power on white noise: RMS ~1 again
        envelope = np.full((n, 2), REST_TONE)
        for c in self.contractions:
            rise = np.minimum(t - c.start_s, c.start_s + c.duration_s - t) / RAMP_S
            level = c.strength * np.clip(rise, 0.0, 1.0)
            column = 0 if c.u_h > 0 else 1
            envelope[:, column] = np.maximum(envelope[:, column], level)
        return np.asarray(shaped * envelope)

    def _artefacts(self, t: np.ndarray) -> np.ndarray:
        m = self.model
        chance = m.artefact_per_min / 60 * len(t) / m.rate_hz
        if self.rng.random() < chance:
            self.artefacts.append((float(t[0]), float(self.rng.uniform(2, 5)),
                                   float(self.rng.choice([-1, 1]))))  # fmt: skip
        bump = np.zeros(len(t))
        for start, frequency, sign in self.artefacts:
            phase = (t - start) * frequency
            inside = (phase >= 0) & (phase < 0.5)
            bump[inside] += sign * m.artefact_size * np.sin(2 * np.pi * phase[inside])
        self.artefacts = [a for a in self.artefacts if (t[-1] - a[0]) * a[1] < 0.5]
        return bump

    def _drift(self, n: int) -> np.ndarray:
        m = self.model
        step_sd = m.drift_per_min * np.sqrt(n / m.rate_hz / 60)
        self.gain_log += self.rng.normal(0, step_sd, m.channels)
        self.gain_log *= 0.999  # drifts back slowly: contact comes and goes
        return np.asarray(np.broadcast_to(self.gain_log, (n, m.channels)))


def _filter(sos: np.ndarray, x: np.ndarray,
            state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``sosfilt`` along time for each column, the state carried between chunks."""
    y, new_state = signal.sosfilt(sos, x, axis=0, zi=state)
    return y, new_state


def model_named(level: str, **changes: float) -> EmgModel:
    """The noise level's model with ``changes`` (e.g. another rate or channel count)."""
    return replace(NOISE_LEVELS[level], **changes)  # type: ignore[arg-type]
