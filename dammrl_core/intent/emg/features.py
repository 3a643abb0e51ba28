"""Features of a window of a wearable sensor's channels: EMG (Hudgins et al. 1993) or IMU.

Per channel: mean absolute value (MAV), waveform length (WL), zero crossings (ZC) and
slope sign changes (SSC), the field's standard set for EMG pattern recognition (LibEMG's
"HTD" group). MAV and WL enter as logarithms, so the classes of a linear discriminant
(whose covariance is shared) stay about equally spread whatever the contraction's
strength; ZC and SSC are rates per second, so a window's length does not change them.
ZC ignores crossings smaller than a deadband, a fraction of the window's own RMS; SSC
counts every peak and trough (LibEMG's threshold 0).

An IMU's command is a posture, not a muscle's activity: a wrist tilted one way or the
other changes the *sign* of an accelerometer channel, which MAV cannot see. Its set is
each channel's mean over the window (orientation: gravity's share on each axis). Measures
of movement (SD, waveform length) were tried and left out: a calibration holds postures,
so the classifier never sees the movement into and out of them, and extrapolated it to
the wrong command on quick tilts (30 % of them).
"""

from __future__ import annotations

import numpy as np

FEATURES = ("log_mav", "log_wl", "zc_hz", "ssc_hz")
IMU_FEATURES = ("mean",)
DEADBAND_OF_RMS = 0.05
"""ZC counts crossings whose step is larger than this fraction of the window's RMS."""
FLOOR = 1e-9
"""Added before a logarithm (a flat channel gives log(1e-9), not -inf)."""


def feature_names(channels: int, kind: str = "emg") -> list[str]:
    """``ch<k>_<feature>`` in the order the features of ``kind`` are returned."""
    names = FEATURES if kind == "emg" else IMU_FEATURES
    return [f"ch{c}_{name}" for name in names for c in range(channels)]


def per_channel(kind: str) -> int:
    """Features per channel of the set ``kind`` ("emg" or "imu")."""
    return len(FEATURES if kind == "emg" else IMU_FEATURES)


def features_of(window: np.ndarray, rate_hz: float, kind: str = "emg") -> np.ndarray:
    """The features of the set ``kind`` of one window (samples, channels)."""
    return window_features(window, rate_hz) if kind == "emg" else imu_features(window, rate_hz)


def imu_features(window: np.ndarray, rate_hz: float) -> np.ndarray:
    """An IMU window (samples, channels) -> (channels,): each channel's mean."""
    return np.asarray(np.asarray(window, dtype=float).mean(axis=0))


def window_features(window: np.ndarray, rate_hz: float) -> np.ndarray:
    """The features of one window (samples, channels) -> (4 * channels,), grouped by feature."""
    x = np.asarray(window, dtype=float)
    centred = x - x.mean(axis=0)
    rms = np.sqrt(np.mean(centred**2, axis=0))
    deadband = DEADBAND_OF_RMS * rms
    duration_s = len(x) / rate_hz
    mav = np.mean(np.abs(x), axis=0)
    wl = np.sum(np.abs(np.diff(x, axis=0)), axis=0) / duration_s
    a, b = centred[:-1], centred[1:]
    zc = np.sum((a * b < 0) & (np.abs(a - b) >= deadband), axis=0) / duration_s
    left, right = centred[1:-1] - centred[:-2], centred[1:-1] - centred[2:]
    ssc = np.sum(left * right > 0, axis=0) / duration_s
    return np.concatenate([np.log(mav + FLOOR), np.log(wl + FLOOR), zc, ssc])


def sliding_windows(samples: np.ndarray, rate_hz: float, window_s: float, hop_s: float,
                    kind: str = "emg") -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Every full window of ``samples`` (n, channels), a hop apart: (features (m, k * ch),
    the index of each window's last sample (m,))."""
    size, hop = window_samples(rate_hz, window_s), window_samples(rate_hz, hop_s)
    ends = np.arange(size, len(samples) + 1, hop) - 1
    if len(ends) == 0:
        return np.zeros((0, per_channel(kind) * samples.shape[1])), ends
    rows = [features_of(samples[end - size + 1 : end + 1], rate_hz, kind) for end in ends]
    return np.array(rows), ends


def window_samples(rate_hz: float, seconds: float) -> int:
    """Samples in ``seconds`` at ``rate_hz`` (at least 2: a difference needs two)."""
    return max(2, round(seconds * rate_hz))
