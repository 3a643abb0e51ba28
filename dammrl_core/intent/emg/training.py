"""From a cued recording to a person's calibration: labelled windows, the classifier, and
leave-one-block-out cross-validation, refused when the classes do not separate.

A calibration session is blocks of cued trials (rest, -1, +1 in a shuffled order). A
window is labelled with its trial's class when it lies wholly inside the trial after the
person's reaction (``settle_s``); windows across a cue change are left out. The whole
session is conditioned and its windows normalised in time order first, exactly as the
decoder does live (:mod:`dammrl_core.intent.emg.conditioning`).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Literal

import numpy as np

from dammrl_core.errors import ConfigurationError
from dammrl_core.intent.emg.calibration import CueFollowing, EmgCalibration, StreamDescription
from dammrl_core.intent.emg.classifier import CrossValidation, cross_validate, fit
from dammrl_core.intent.emg.conditioning import Conditioning, Normaliser, condition
from dammrl_core.intent.emg.decoder import EmgDecoderSettings
from dammrl_core.intent.emg.features import FEATURES, FLOOR, sliding_windows

SETTLE_S = 0.5
"""A trial's first half second is the person's reaction: its windows are not labelled."""
MIN_ACCURACY = 0.85
"""Cross-validated accuracy below this: the classes do not separate well enough to use."""
MAX_ACTIVE_ERROR = 0.10
"""Cross-validated active error rate above this: -1 and +1 are confused too often."""
ACTIVE_OF_REST = 3.0
"""A window whose most active channel is this many times its rest level (MAV) is one of
activity (a contraction's is 5-30 times; rest's noise, under 1.5)."""
MIN_ACTIVE_AT_COMMANDS = 0.3
"""Active in fewer of the -1/+1 cues' windows: no contraction was seen."""
MIN_FOLLOWING = 0.3
"""Active in the -1/+1 cues' windows less than this share more often than in the rest
cues': the activity did not follow the cues."""


@dataclass(frozen=True)
class Cue:
    """One cued trial: the class asked for, from ``start_s`` to ``end_s`` (stream clock)."""

    label: int  # -1, 0 (rest) or +1
    start_s: float
    end_s: float
    block: int


def conditioned_windows(samples: np.ndarray, rate_hz: float, window_s: float, hop_s: float,
                        kind: str, conditioning: Conditioning
                        ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(features (m, k * channels), each window's last sample (m,)) of a recording
    conditioned and normalised window by window as the live decoder does it."""
    features, ends = sliding_windows(condition(samples, rate_hz, conditioning), rate_hz,
                                     window_s, hop_s, kind)  # fmt: skip
    normaliser = Normaliser(conditioning, hop_s, kind)
    return np.array([normaliser(row) for row in features]).reshape(features.shape), ends


def labelled_windows(samples: np.ndarray, times: np.ndarray, cues: list[Cue], rate_hz: float,
                     window_s: float, hop_s: float, kind: str, conditioning: Conditioning,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(features, labels, blocks, trials) of every window wholly inside a trial after its
    settle (``trials``: the index of its cue), conditioned as ``conditioning`` says (a
    calibration's classifier reads only features conditioned as its own were)."""
    features, ends = conditioned_windows(samples, rate_hz, window_s, hop_s, kind, conditioning)
    end_t = times[ends] if len(ends) else np.zeros(0)
    labels, blocks, trials = (np.full(len(ends), -99) for _ in range(3))
    for k, cue in enumerate(cues):
        inside = (end_t - window_s >= cue.start_s + SETTLE_S) & (end_t <= cue.end_s)
        labels[inside], blocks[inside], trials[inside] = cue.label, cue.block, k
    kept = labels != -99
    return features[kept], labels[kept], blocks[kept], trials[kept]


def rest_rms(samples: np.ndarray, times: np.ndarray, cues: list[Cue]) -> np.ndarray:
    """Each channel's RMS (about its mean) over the rest trials."""
    rest = np.zeros(len(times), dtype=bool)
    for cue in cues:
        if cue.label == 0:
            rest |= (times >= cue.start_s + SETTLE_S) & (times <= cue.end_s)
    if not rest.any():
        raise ConfigurationError("the calibration has no rest trial")
    return np.asarray(samples[rest].std(axis=0))


def rest_level(samples: np.ndarray, times: np.ndarray, cues: list[Cue], rate_hz: float,
               window_s: float, hop_s: float) -> np.ndarray:  # fmt: skip
    """Each channel's median window MAV over the rest trials (conditioned samples)."""
    features, ends = sliding_windows(samples, rate_hz, window_s, hop_s, "emg")
    end_t = times[ends] if len(ends) else np.zeros(0)
    rest = np.zeros(len(ends), dtype=bool)
    for cue in cues:
        if cue.label == 0:
            rest |= (end_t - window_s >= cue.start_s + SETTLE_S) & (end_t <= cue.end_s)
    channels = samples.shape[1]
    return np.asarray(np.exp(np.median(features[rest, :channels], axis=0)) - FLOOR)


def cue_following(features: np.ndarray, labels: np.ndarray,
                  conditioning: Conditioning, kind: str) -> CueFollowing | None:  # fmt: skip
    """How often the muscles were active under each kind of cue (features relative to the
    rest level; None when they are not)."""
    if not (conditioning.normalise_level and kind == "emg"):
        return None
    channels = features.shape[1] // len(FEATURES)
    active = features[:, :channels].max(axis=1) > np.log(ACTIVE_OF_REST)
    rest, commands = active[labels == 0], active[labels != 0]
    return CueFollowing(rest=float(rest.mean()) if len(rest) else 0.0,
                        commands=float(commands.mean()) if len(commands) else 0.0)  # fmt: skip


def default_conditioning(kind: str, mains_hz: Literal[0, 50, 60] = 50) -> Conditioning:
    """EMG: a 20 Hz high-pass, the mains notch, levels relative to rest; an IMU: none
    (its posture is the signal's DC)."""
    return Conditioning.emg(mains_hz) if kind == "emg" else Conditioning.none()


def train(samples: np.ndarray, times: np.ndarray, cues: list[Cue], stream: StreamDescription,
          window_s: float = 0.2, hop_s: float = 0.05,
          decoder: EmgDecoderSettings | None = None, participant: str | None = None,
          kind: Literal["emg", "imu"] = "emg",
          conditioning: Conditioning | None = None) -> EmgCalibration:  # fmt: skip
    """The calibration of a cued recording (samples (n, channels) at ``times`` (n,)) with
    the feature set ``kind`` and ``conditioning`` (default: ``default_conditioning``)."""
    decoder = decoder or EmgDecoderSettings()
    conditioning = conditioning or default_conditioning(kind)
    rate = stream.nominal_srate_hz
    if (problem := conditioning.problem(rate)) is not None:
        raise ConfigurationError(problem)
    features, labels, blocks, trials = labelled_windows(
        samples, times, cues, rate, window_s, hop_s, kind, conditioning
    )
    _enough(labels, blocks)
    cv = cross_validate(features, labels, blocks, trials, decoder.reject_below,
                        decoder.vote_windows)  # fmt: skip
    conditioned = condition(samples, rate, conditioning)
    return EmgCalibration(
        created=datetime.now(UTC).isoformat(timespec="seconds"),
        participant=participant,
        stream=stream,
        features=kind,
        window_s=window_s,
        hop_s=hop_s,
        conditioning=conditioning,
        classifier=fit(features, labels).model_copy(update={"temperature": cv.temperature}),
        rest_rms=rest_rms(conditioned, times, cues).tolist(),
        rest_level=(
            rest_level(conditioned, times, cues, rate, window_s, hop_s).tolist()
            if kind == "emg"
            else []
        ),
        cross_validation=cv,
        cue_following=cue_following(features, labels, conditioning, kind),
    )


def _enough(labels: np.ndarray, blocks: np.ndarray) -> None:
    if len(np.unique(blocks)) < 2:
        raise ConfigurationError("a calibration needs 2 blocks at least (leave-one-block-out)")
    for label in (-1, 0, 1):
        if np.sum(labels == label) < 10:
            raise ConfigurationError(
                f"the calibration has {np.sum(labels == label)} windows of class {label:+d}, "
                "10 at least are needed: longer trials or more blocks"
            )


def refusal(cv: CrossValidation, min_accuracy: float = MIN_ACCURACY,
            max_active_error: float = MAX_ACTIVE_ERROR,
            following: CueFollowing | None = None) -> str | None:  # fmt: skip
    """Why this calibration should not be used, or None when it may (``following``: how
    the activity followed the cues, when measured)."""
    if cv.accuracy >= min_accuracy and cv.active_error_rate <= max_active_error:
        return None
    metrics = _metrics_line(cv, min_accuracy, max_active_error)
    if following is not None and following.commands < MIN_ACTIVE_AT_COMMANDS:
        return (f"{metrics}: no contraction seen during the -1/+1 cues (muscles active in "
                f"{following.commands:.0%} of their windows): contract more firmly, or check "
                "the electrodes' contact")  # fmt: skip
    if following is not None and following.commands - following.rest < MIN_FOLLOWING:
        return (f"{metrics}: the person did not follow the cues (muscles active in "
                f"{following.rest:.0%} of the rest cues' windows and {following.commands:.0%} "
                "of the -1/+1 cues'): show them the cues again, or check that this stream "
                "is their sensor")  # fmt: skip
    (minus_as_plus, plus_as_minus) = (cv.confusion[0][2], cv.confusion[2][0])
    confused = (
        "-1 and +1 are confused with each other (place the electrodes over the two "
        "muscle groups, make the two movements more distinct)"
        if minus_as_plus + plus_as_minus > 0.1 * (cv.confusion[0][0] + cv.confusion[2][2])
        else "commands are confused with rest (contract more firmly, or check the "
        "electrodes' contact)"
    )
    return f"{metrics}: {confused}"


def _metrics_line(cv: CrossValidation, min_accuracy: float, max_active_error: float) -> str:
    """The cross-validation's figures, saying so when no window was accepted at all (an
    accuracy of 0.00 over none is no accuracy)."""
    if cv.rejection_rate >= 1.0:
        return (f"every window rejected in cross-validation (no class stood out: accuracy "
                f"at least {min_accuracy} needed)")  # fmt: skip
    return (
        f"cross-validated accuracy {cv.accuracy:.2f} (at least {min_accuracy} needed), "
        f"active error rate {cv.active_error_rate:.2f} (at most {max_active_error})"
    )
