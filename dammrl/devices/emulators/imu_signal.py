"""A synthetic wrist IMU: +1 and -1 are the wrist flexed or extended, seeded.

Six channels as a typical IMU streams them: accelerometer x, y, z [g] and gyroscope x, y,
z [rad/s], default 100 Hz. A command tilts the hand about the y axis by a random 0.5-1.0
of ``tilt_rad`` (+ for +1, - for -1) along smooth ramps, held for the command's length:
gravity moves from z to x (the accelerometer's x channel changes sign with the command)
and the gyroscope's y channel shows the turning. Noise, a slowly wandering gyroscope
bias, physiological tremor (8-12 Hz) and small arm movements (the arm the robot moves)
are added. The same interface as :class:`dammrl.devices.emulators.emg_signal.EmgSynth`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dammrl.devices.emulators.movements import Wearer


@dataclass(frozen=True)
class ImuModel:
    channels: int = 6
    rate_hz: float = 100.0
    accel_noise_g: float = 0.01
    gyro_noise_rad_s: float = 0.02
    tilt_rad: float = 0.5  # a full command's wrist angle
    ramp_s: float = 0.08  # time to tilt and to come back
    tremor_rad: float = 0.005
    sway_rad: float = 0.03  # slow arm movement (the robot moving the forearm)


IMU_NOISE_LEVELS: dict[str, ImuModel] = {
    "low": ImuModel(accel_noise_g=0.005, gyro_noise_rad_s=0.01, sway_rad=0.01),
    "medium": ImuModel(),
    "high": ImuModel(accel_noise_g=0.05, gyro_noise_rad_s=0.1, tilt_rad=0.25, sway_rad=0.15),
}


@dataclass
class ImuSynth(Wearer):
    """Generates the samples of one wrist IMU, chunk by chunk, on its own clock."""

    STRENGTH = (0.5, 1.0)

    model: ImuModel = field(default_factory=ImuModel)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.model.channels != 6:
            raise ValueError("the IMU emulator streams 6 channels (accelerometer, gyroscope)")
        Wearer.__init__(self, self.seed)
        self.bias = np.zeros(3)
        self.sway_phase = float(self.rng.uniform(0, 2 * np.pi))

    def generate(self, n: int) -> np.ndarray:
        """The next ``n`` samples (n, 6)."""
        m = self.model
        t = self.t_s + np.arange(n) / m.rate_hz
        angle = self._angle(t)
        rate = np.gradient(angle, 1 / m.rate_hz) if n > 1 else np.zeros(n)
        self.bias += self.rng.normal(0, 0.002 * np.sqrt(n / m.rate_hz), 3)
        self.bias *= 0.999  # a gyroscope's bias wanders, within a few hundredths of rad/s
        out = np.zeros((n, 6))
        out[:, 0], out[:, 2] = np.sin(angle), np.cos(angle)
        out[:, :3] += self.rng.normal(0, m.accel_noise_g, (n, 3))
        out[:, 4] = rate
        out[:, 3:] += self.bias + self.rng.normal(0, m.gyro_noise_rad_s, (n, 3))
        self._apply_lifted(out)
        self._advance(t, m.rate_hz, linger_s=m.ramp_s)
        return out

    def _angle(self, t: np.ndarray) -> np.ndarray:
        m = self.model
        angle = m.sway_rad * np.sin(2 * np.pi * 0.3 * t + self.sway_phase)
        angle += m.tremor_rad * np.sin(2 * np.pi * 10 * t)
        for c in self.contractions:
            up = np.clip((t - c.start_s) / m.ramp_s, 0, 1)
            down = np.clip((c.start_s + c.duration_s - t) / m.ramp_s + 1, 0, 1)
            shape = _smooth(np.minimum(up, down))
            angle += c.u_h * c.strength * m.tilt_rad * shape
        return angle


def _smooth(s: np.ndarray) -> np.ndarray:
    """A minimum-jerk ramp 0 -> 1 for s in [0, 1]."""
    return np.asarray(10 * s**3 - 15 * s**4 + 6 * s**5)
