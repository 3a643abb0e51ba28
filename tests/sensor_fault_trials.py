"""Fault trials of the pressure-sensor path, as figures (issue 12, "presses nobody made").

Decoder trials feed known traces straight into :class:`PressDecoder` (seeded, fast). Port
trials run the real intent service on a real bus, reading an emulated pad on a pty, with a
DecisionRequest open during every trial: each Intent it publishes is a decision.

    .venv/bin/python -m tests.sensor_fault_trials            # decoder trials
    .venv/bin/python -m tests.sensor_fault_trials --port     # + the real service on a pty
"""

from __future__ import annotations

import argparse
import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from dammrl.devices.emulators.pad import DEFAULT_CALIBRATION, Press, SensorEmulator
from dammrl_core.errors import DammrlError
from dammrl_core.intent.pad.decoder import Calibration, PressDecoder
from dammrl_core.settings import error_line
from schemas import DecisionRequest, Header, Intent, SensorSample, encode
from tests.busutil import Observer, free_port, start_service, wait_for

RATE_HZ = 100.0
NOISE_RAW = 12.0  # the emulator's ADC noise [counts]
GLITCH_RAWS = (4095, 3000, 1200, 900, 0)  # beyond firm, firm, light, over the on level, 0
GLITCH_FRAMES = (1, 2, 3, 4, 5, 6)
QUICK_S, HELD_S = (0.1, 0.15, 0.2, 0.25), (0.8,)


def noisy_rest(total_s: float, rng: np.random.Generator, cal: Calibration) -> np.ndarray:
    """Raw readings of an untouched pad at 100 Hz."""
    return cal.rest_raw + rng.normal(0, NOISE_RAW, int(total_s * RATE_HZ))


def with_press(raws: np.ndarray, start_s: float, press: Press, cal: Calibration) -> np.ndarray:
    """``raws`` with a trapezoid press added (the emulator's shape)."""
    t = np.arange(raws.size) / RATE_HZ
    ramp = np.clip(np.minimum(t - start_s, start_s + press.duration_s - t) / 0.05, 0, 1)
    return raws + press.level * ramp * (cal.firm_raw - cal.rest_raw)


def decisions(raws: np.ndarray, cal: Calibration = DEFAULT_CALIBRATION) -> list[tuple[int, int]]:
    decoder = PressDecoder(cal)
    out = []
    for k, raw in enumerate(np.clip(raws, 0, 4095)):
        if (d := decoder.update(k / RATE_HZ, float(raw))) is not None:
            out.append((d.u_h, d.human_model))
    return out


def glitch_trials(per_case: int = 3, seed: int = 0) -> tuple[int, int]:
    """(decisions, trials): glitches of 1..6 frames, every amplitude, at random times."""
    rng, found, trials = np.random.default_rng(seed), 0, 0
    for frames in GLITCH_FRAMES:
        for raw in GLITCH_RAWS:
            for _ in range(per_case):
                raws = noisy_rest(1.5, rng, DEFAULT_CALIBRATION)
                at = int(rng.integers(20, 100))
                raws[at : at + frames] = raw
                found += len(decisions(raws))
                trials += 1
    return found, trials


def glitch_in_press_trials(per_case: int = 2, seed: int = 1) -> tuple[int, int, int]:
    """(presses decoded wrong, presses dropped, trials): a glitch inside a held light press."""
    rng, wrong, dropped, trials = np.random.default_rng(seed), 0, 0, 0
    for frames in GLITCH_FRAMES:
        for raw in GLITCH_RAWS:
            for _ in range(per_case):
                raws = with_press(noisy_rest(3.0, rng, DEFAULT_CALIBRATION), 0.5,
                                  Press(0, 1.2, 0.35), DEFAULT_CALIBRATION)  # fmt: skip
                at = int(rng.integers(70, 150))
                raws[at : at + frames] = raw
                found = decisions(raws)
                wrong += bool(found) and found != [(-1, 2)]
                dropped += not found
                trials += 1
    return wrong, dropped, trials


def press_trials(per_case: int = 5, seed: int = 2) -> dict[float, float]:
    """Fraction of genuine presses decoded right, per press duration [s]."""
    rng, rates = np.random.default_rng(seed), {}
    for duration in (*QUICK_S, *HELD_S):
        right = 0
        for level, u_h in ((0.95, 1), (0.35, -1)):
            for _ in range(per_case):
                start = float(rng.uniform(0.3, 0.6))
                raws = with_press(noisy_rest(2.0, rng, DEFAULT_CALIBRATION), start,
                                  Press(0, duration, level), DEFAULT_CALIBRATION)  # fmt: skip
                right += decisions(raws) == [(u_h, 2 if duration >= 0.5 else 1)]
        rates[duration] = right / (2 * per_case)
    return rates


TIGHT = {"rest_raw": 400, "light_raw": 400.0001, "firm_raw": 400.0002}  # the issue's
NARROWEST = {"rest_raw": 400, "light_raw": 600, "firm_raw": 1000, "rest_noise_raw": NOISE_RAW}
"""About the narrowest range the default thresholds accept with the emulator's noise."""


def phantom_trial(levels: dict[str, float], seconds: float = 20.0, seed: int = 4) -> str:
    """Decisions from an untouched pad (the emulator's noise) under a calibration."""
    try:
        cal = Calibration.model_validate(levels)
        decoder = PressDecoder(cal)
    except ValidationError as exc:
        return f"refused: {error_line(exc)}"
    except DammrlError as exc:
        return f"refused: {exc}"
    raws = noisy_rest(seconds, np.random.default_rng(seed), cal)
    found = [d for k, raw in enumerate(raws) if (d := decoder.update(k / RATE_HZ, raw))]
    return f"{len(found)} decisions in {seconds:.0f} s"


# --- the real intent service on a pty -----------------------------------------------------


@dataclass
class PortRig:
    """An intent service reading ``link``, this process's observer, and requests."""

    link: Path
    observer: Observer
    requests: int = 0

    def open_request(self) -> None:
        self.requests += 1
        request = DecisionRequest(
            header=Header(stamp_ns=time.time_ns(), seq=self.requests, source="controller"),
            episode=1, seed=1, request=self.requests, t_s=0.0, ee_pos_m=(0.0, 0.0, 0.0),
            goal_m=(0.3, 0.0, 0.0), primary_axis=0, human_model=1,
        )  # fmt: skip
        self.observer.session.put("dammrl/intent/request", encode(request))

    def intents(self) -> int:
        return len(self.observer.of(Intent))

    def wait_samples(self, more: int = 20, timeout_s: float = 20) -> None:
        count = len(self.observer.of(SensorSample))
        wait_for(lambda: len(self.observer.of(SensorSample)) > count + more, timeout_s, "samples")


@contextlib.contextmanager
def port_rig(directory: Path, **env: str) -> Iterator[PortRig]:
    """The intent service (source serial) on ``directory/ttySENSOR``; stopped after."""
    link, port = directory / "ttySENSOR", free_port()
    observer = Observer(port)
    serial_env = {"DAMMRL_INTENT_SOURCE": "pad", "DAMMRL_PAD_PORT": str(link)}
    service = start_service("intent", port, DAMMRL_PAD_RECONNECT_MAX_S="0.5",
                            **serial_env, **env)  # fmt: skip
    try:
        yield PortRig(link, observer)
        assert service.poll() is None, "the intent service died"
    finally:
        service.terminate()
        service.wait(15)
        observer.close()


def port_glitch_trials(rig: PortRig, pad: SensorEmulator, raws: tuple[int, ...],
                       seed: int = 3) -> tuple[int, int]:  # fmt: skip
    """(intents, trials): one glitch of 1..6 frames per trial, a request open each time."""
    rng, before, trials = np.random.default_rng(seed), rig.intents(), 0
    for frames in GLITCH_FRAMES:
        for raw in raws:
            rig.open_request()
            time.sleep(float(rng.uniform(0.1, 0.3)))
            pad.glitch(raw, frames)
            time.sleep(0.5)  # longer than any stretch of the glitch by the filters
            trials += 1
    return rig.intents() - before, trials


def port_press_trials(rig: PortRig, pad: SensorEmulator, per_case: int = 2) -> tuple[int, int]:
    """(answered right, trials): genuine quick and held presses, each with its own request."""
    expected: dict[int, tuple[int, int]] = {}
    for duration in (0.15, 0.2, 0.8):
        for level, u_h in ((0.95, 1), (0.35, -1)):
            for _ in range(per_case):
                rig.open_request()
                expected[rig.requests] = (u_h, 2 if duration >= 0.5 else 1)
                pad.press(level, duration, delay_s=0.05)
                time.sleep(duration + 0.6)
    answers = {i.request: (i.u_h, i.human_model) for i in rig.observer.of(Intent)
               if isinstance(i, Intent) and i.request in expected}  # fmt: skip
    return sum(answers.get(r) == e for r, e in expected.items()), len(expected)


def unplug_trials(rig: PortRig, trials: int = 2) -> tuple[int, int]:
    """(intents, trials): unplugged during a firm press, replugged at rest, request open."""
    before = rig.intents()
    for seed in range(trials):
        with SensorEmulator(rig.link, [], seed=seed) as pad:
            rig.wait_samples()
            rig.open_request()
            pad.hold(1.0)
            time.sleep(0.4)  # pressed: unplug now
        time.sleep(0.3)
        with SensorEmulator(rig.link, [], seed=100 + seed):  # replugged, nobody pressing
            rig.wait_samples()
            time.sleep(1.5)
    return rig.intents() - before, trials


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--port", action="store_true", help="also the real service on a pty")
    args = parser.parse_args()
    found, trials = glitch_trials()
    print(f"decoder: glitches of 1-6 frames, raw {GLITCH_RAWS}: {found} decisions in {trials}")
    wrong, dropped, trials = glitch_in_press_trials()
    print(f"decoder: a glitch inside a held light press: {wrong} decoded wrong, {dropped} "
          f"dropped, of {trials}")  # fmt: skip
    rates = ", ".join(f"{d:.2f} s {r:.0%}" for d, r in press_trials().items())
    print(f"decoder: genuine presses decoded right: {rates}")
    for name, levels in (("1e-4 counts apart", TIGHT), ("rest/light/firm 400/600/1000", NARROWEST)):
        print(f"decoder: untouched pad, calibration {name}: {phantom_trial(levels)}")
    if not args.port:
        return
    import tempfile

    with tempfile.TemporaryDirectory() as tmp, port_rig(Path(tmp)) as rig:
        with SensorEmulator(rig.link, []) as pad:
            rig.wait_samples()
            found, trials = port_glitch_trials(rig, pad, (4095, 3000, 0))
            print(f"port: glitches of 1-6 frames, raw 4095/3000/0: {found} intents in {trials}")
            right, trials = port_press_trials(rig, pad)
            print(f"port: genuine presses (0.15/0.2/0.8 s): {right} of {trials} answered right")
        found, trials = unplug_trials(rig)
        print(f"port: unplugged while pressed, replugged at rest: {found} intents in {trials}")


if __name__ == "__main__":
    main()
