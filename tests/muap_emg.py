"""Surface EMG of another kind than the project's emulator, to check what does not depend
on that emulator: motor units firing, not shaped noise.

Written apart from ``dammrl.devices.emulators.emg_signal`` (which filters Gaussian noise under an
envelope), after the textbook model of surface EMG (De Luca; Farina & Merletti 2001):

* two muscles (flexors: +1, extensors: -1), each of ``units`` motor units recruited in
  order of size as the drive rises (thresholds spread exponentially), each firing at
  8-35 Hz with the drive, with 20 % jitter of its intervals;
* each unit's action potential is a biphasic wavelet (the derivative of a Gaussian,
  2-6 ms wide) whose amplitude on each electrode falls with the distance from the unit,
  electrodes around the forearm, flexors on one side;
* a DC-coupled amplifier: each channel's own electrode offset (tens of mV) drifting,
  60 Hz mains with its third harmonic, 4 µV of white noise, float32 samples in µV, at
  2 kHz by default.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from dammrl_core.intent.emg.training import Cue


@dataclass(frozen=True)
class Contraction:
    u_h: int  # +1: flexors, -1: extensors
    start_s: float
    duration_s: float
    strength: float  # of a full contraction's drive (0-1)


@dataclass(frozen=True)
class Forearm:
    channels: int = 8
    rate_hz: float = 2000.0
    units: int = 50  # motor units per muscle
    peak_uv: float = 120.0  # the largest unit's potential on its nearest electrode [µV]
    noise_uv: float = 4.0
    mains_uv: float = 15.0  # 60 Hz
    offset_mv: float = 30.0  # the electrodes' DC offsets are drawn up to this [mV]
    drift_uv_per_s: float = 20.0  # their random walk
    rest_drive: float = 0.02  # tonic activity at rest (of a full contraction's drive)


class MuapForearm:
    """Generates the samples of a forearm doing ``contractions`` (a session at once)."""

    def __init__(self, arm: Forearm = Forearm(), seed: int = 0) -> None:
        self.arm = arm
        self.rng = np.random.default_rng(seed)
        n = arm.units
        self.threshold = np.sort(np.exp(self.rng.uniform(np.log(0.01), np.log(0.8), (2, n))))
        self.width_s = self.rng.uniform(0.001, 0.003, (2, n))
        self.size = (self.threshold / self.threshold.max()) ** 0.5  # bigger units later
        self.gain = self._electrodes()  # (2, n, channels)
        self.offset_uv = self.rng.uniform(-1, 1, arm.channels) * arm.offset_mv * 1000

    def _electrodes(self) -> np.ndarray:
        """Each unit's amplitude on each electrode: by distance around the forearm."""
        arm = self.arm
        electrode = np.linspace(0, 2 * np.pi, arm.channels, endpoint=False)
        gains = np.zeros((2, arm.units, arm.channels))
        for muscle, centre in ((0, np.pi / 2), (1, 3 * np.pi / 2)):  # flexors, extensors
            angle = centre + self.rng.normal(0, 0.5, arm.units)
            depth = self.rng.uniform(0.3, 1.0, arm.units)
            apart = np.abs(np.angle(np.exp(1j * (angle[:, None] - electrode[None, :]))))
            gains[muscle] = np.exp(-(apart + depth[:, None]) / 0.6)
        return gains / gains.max()

    def samples(self, seconds: float, contractions: list[Contraction]) -> np.ndarray:
        """(n, channels) float32 µV over ``seconds``."""
        arm = self.arm
        n = round(seconds * arm.rate_hz)
        t = np.arange(n) / arm.rate_hz
        out = np.zeros((n, arm.channels))
        for muscle, u_h in ((0, 1), (1, -1)):
            drive = self._drive(t, [c for c in contractions if c.u_h == u_h])
            for unit in range(arm.units):
                train = self._spikes(drive, unit, muscle)
                if train.any():
                    wave = self._potential(muscle, unit)
                    out += np.outer(signal.fftconvolve(train, wave)[:n],
                                    self.gain[muscle, unit])  # fmt: skip
        out += self._amplifier(t)
        return out.astype(np.float32)

    def _drive(self, t: np.ndarray, contractions: list[Contraction]) -> np.ndarray:
        drive = np.full(len(t), self.arm.rest_drive)
        for c in contractions:
            ramp = np.clip(np.minimum(t - c.start_s, c.start_s + c.duration_s - t) / 0.05, 0, 1)
            drive = np.maximum(drive, c.strength * ramp)
        return drive

    def _spikes(self, drive: np.ndarray, unit: int, muscle: int) -> np.ndarray:
        """A unit's firing (impulses, size-scaled): 8 Hz at its threshold, up to 35 Hz."""
        above = drive - self.threshold[muscle, unit]
        rate = np.where(above > 0, 8 + 27 * np.clip(above / 0.5, 0, 1), 0.0)
        phase = np.cumsum(rate) / self.arm.rate_hz  # expected firings so far
        jitter = 1 + 0.2 * self.rng.standard_normal(int(phase[-1]) + 2)
        fired = np.searchsorted(phase, np.cumsum(np.clip(jitter, 0.3, None)))
        train = np.zeros(len(drive))
        train[fired[fired < len(drive)]] = self.size[muscle, unit]
        return train

    def _potential(self, muscle: int, unit: int) -> np.ndarray:
        width = self.width_s[muscle, unit]
        t = np.arange(-4 * width, 4 * width, 1 / self.arm.rate_hz)
        wave = -t / width * np.exp(-0.5 * (t / width) ** 2)
        return np.asarray(self.arm.peak_uv * wave / np.abs(wave).max())

    def _amplifier(self, t: np.ndarray) -> np.ndarray:
        arm = self.arm
        n = len(t)
        walk = np.cumsum(self.rng.normal(0, arm.drift_uv_per_s / np.sqrt(arm.rate_hz),
                                         (n, arm.channels)), axis=0)  # fmt: skip
        mains = np.sin(2 * np.pi * 60 * t) + 0.3 * np.sin(2 * np.pi * 180 * t + 1.0)
        phases = self.rng.uniform(0.5, 1.0, arm.channels)
        return np.asarray(self.offset_uv + walk + arm.mains_uv * np.outer(mains, phases)
                          + self.rng.normal(0, arm.noise_uv, (n, arm.channels)))  # fmt: skip


def cued_session(forearm: MuapForearm, blocks: int = 4, trial_s: float = 3.0,
                 relax_s: float = 1.5, seed: int = 0
                 ) -> tuple[np.ndarray, np.ndarray, list[Cue]]:  # fmt: skip
    """A cooperative participant's calibration (rest, -1, +1 shuffled per block, a
    0.3 s reaction), as ``dammrl intent calibrate`` cues it: (samples, times, cues)."""
    rng = np.random.default_rng(seed + 1)
    cues, contractions, t = [], [], 1.0  # a second of rest before the first cue
    for block in range(blocks):
        for label in rng.permutation([-1, 0, 1]):
            if label:
                strength = float(rng.uniform(0.4, 1.0))
                contractions.append(Contraction(int(label), t + 0.3, trial_s - 0.3, strength))
            cues.append(Cue(int(label), t, t + trial_s, block))
            t += trial_s + relax_s
    samples = forearm.samples(t, contractions)
    return samples, np.arange(len(samples)) / forearm.arm.rate_hz, cues


def decisions_session(forearm: MuapForearm, count: int, seed: int
                      ) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:  # fmt: skip
    """A scripted patient: ``count`` contractions (quick 0.3 s: E_big; held 0.9 s:
    E_small) 2.5 s apart after 2 s of rest: (samples, times, [(u_h, radius)])."""
    rng = np.random.default_rng(seed)
    plan, contractions = [], []
    for k in range(count):
        u_h, held = int(rng.choice([-1, 1])), bool(rng.integers(2))
        strength = float(rng.uniform(0.4, 1.0))
        contractions.append(Contraction(u_h, 2.5 + 2.5 * k, 0.9 if held else 0.3, strength))
        plan.append((u_h, 2 if held else 1))
    samples = forearm.samples(2.5 + 2.5 * count + 1.0, contractions)
    return samples, np.arange(len(samples)) / forearm.arm.rate_hz, plan
