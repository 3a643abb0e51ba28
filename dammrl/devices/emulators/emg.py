"""An emulated EMG armband (or wrist IMU) on Lab Streaming Layer: the wearable path
without hardware.

The synthetic forearm (:mod:`dammrl.devices.emulators.emg_signal`) or wrist
(:mod:`dammrl.devices.emulators.imu_signal`) is streamed in real time on an LSL outlet, in chunks
as an amplifier's software sends them. Who moves the forearm:

* ``patient``: a simulated patient answers the stack's decision requests with
  contractions (quick for E_big, held for E_small; see ``dammrl.devices.emulators.patient``);
* ``cued``: it follows the cues of ``dammrl intent calibrate`` (an LSL marker stream,
  ``dammrl-cues:<stream>``, as lab software cues), as a cooperative participant would;
* ``rest``: nobody moves (phantom decisions are then all errors).

Faults on demand (methods, or lines on stdin from ``dammrl intent emulate``): an
electrode off (flat) or clipping, the stream lost for a while, non-finite samples, a
jump of the timestamps, a second stream of the same name (another device), and the
amplifier's own: a DC offset added to every channel, another gain.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from dammrl.devices.emulators.emg_signal import EmgSynth
from dammrl.devices.emulators.imu_signal import ImuSynth

log = logging.getLogger("dammrl.emg")

CHUNK_S = 0.02
"""An amplifier's software sends chunks about this often [s]."""


def cue_stream(stream: str) -> str:
    """The marker stream of ``dammrl intent calibrate`` on ``stream``: "rest", "-1", "+1",
    "end" (named after the stream: two calibrations at once never cross)."""
    return f"dammrl-cues:{stream}"


QUICK_S = 0.25
HELD_S = 0.9


class EmgStream:
    """Streams a synthetic forearm on an LSL outlet until stopped (a context manager)."""

    def __init__(self, name: str, synth: EmgSynth | ImuSynth,
                 source_id: str = "dammrl-emulated-emg") -> None:  # fmt: skip
        self.name = name
        self.synth = synth
        self.source_id = source_id
        self.stream_type = "IMU" if isinstance(synth, ImuSynth) else "EMG"
        self.outlet: Any = None
        self.twin: Any = None
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="emg-stream", daemon=True)
        self.started_s = 0.0  # LSL's clock when the first sample was acquired
        self.clock_offset_s = 0.0
        self.dc_offset = 0.0  # added to every sample (the stream's units)
        self.gain = 1.0  # every sample multiplied
        self.nan_until = 0.0
        self.silent_until = 0.0
        self.sent = 0

    def __enter__(self) -> EmgStream:
        import pylsl

        from dammrl_core.intent.lsl import QUIET_LSL

        pylsl.set_config_content(QUIET_LSL)
        self.outlet = self._outlet(self.source_id)
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(2.0)
        self.outlet = self.twin = None

    def _outlet(self, source_id: str) -> Any:
        import pylsl

        m = self.synth.model
        info = pylsl.StreamInfo(self.name, self.stream_type, m.channels, m.rate_hz,
                                pylsl.cf_float32, source_id)  # fmt: skip
        channels = info.desc().append_child("channels")
        for label, unit in self._channels():
            channel = channels.append_child("channel")
            channel.append_child_value("label", label)
            channel.append_child_value("unit", unit)
        return pylsl.StreamOutlet(info)  # each chunk pushed through as it is made

    def _channels(self) -> list[tuple[str, str]]:
        """(label, unit) per channel, as LSL's metadata convention has them."""
        if self.stream_type == "IMU":
            return [(f"accel_{a}", "g") for a in "xyz"] + [(f"gyro_{a}", "rad/s") for a in "xyz"]
        return [(f"EMG{k + 1}", "microvolts") for k in range(self.synth.model.channels)]

    # ---- the stream ------------------------------------------------------------------------
    def _run(self) -> None:
        import pylsl

        rate = self.synth.model.rate_hz
        start = self.started_s = pylsl.local_clock()
        while not self.stop.wait(CHUNK_S / 2):
            due = int((pylsl.local_clock() - start) * rate) - self.sent
            if due <= 0:
                continue
            with self.lock:
                samples = (self.gain * self.synth.generate(due) + self.dc_offset).astype(np.float32)
                self.sent += due
                now = pylsl.local_clock()
                if now < self.silent_until:
                    self.outlet = None
                    continue
                if self.outlet is None:  # back after a loss: the same source id
                    self.outlet = self._outlet(self.source_id)
                if now < self.nan_until:
                    samples[::7, 0] = np.nan
                # each sample stamped as acquired at the rate, the newest now
                stamps = now + self.clock_offset_s - np.arange(due)[::-1] / rate
                self.outlet.push_chunk(samples, stamps.tolist())
                if self.twin is not None:
                    self.twin.push_chunk(samples[::-1], (stamps - self.clock_offset_s).tolist())

    # ---- faults ----------------------------------------------------------------------------
    def lose(self, seconds: float) -> None:
        """The stream disappears (the amplifier's software closed it), then returns."""
        import pylsl

        with self.lock:
            self.silent_until = pylsl.local_clock() + seconds

    def non_finite(self, seconds: float) -> None:
        import pylsl

        with self.lock:
            self.nan_until = pylsl.local_clock() + seconds

    def jump_clock(self, seconds: float) -> None:
        """The sender's timestamps jump (a clock reset on the amplifier's PC)."""
        with self.lock:
            self.clock_offset_s += seconds

    def amplifier(self, dc_offset: float | None = None, gain: float | None = None) -> None:
        """The amplifier's DC offset (added, the stream's units) or gain from now on."""
        with self.lock:
            self.dc_offset = self.dc_offset if dc_offset is None else dc_offset
            self.gain = self.gain if gain is None else gain

    def add_twin(self) -> None:
        """A second stream of the same name (another device or machine)."""
        with self.lock:
            self.twin = self._outlet(self.source_id + "-twin")

    def remove_twin(self) -> None:
        with self.lock:
            self.twin = None

    def fault(self, line: str) -> str:
        """A fault from a line of text (``dammrl intent emulate`` reads stdin)."""
        words = line.split()
        if not words:
            return ""
        what, arg = words[0], float(words[1]) if len(words) > 1 else 1.0
        actions: dict[str, Callable[[], None]] = {
            "flat": lambda: self.synth.lift(int(arg), "flat"),
            "clip": lambda: self.synth.lift(int(arg), "clip"),
            "back": lambda: self.synth.put_back(int(arg)),
            "lose": lambda: self.lose(arg),
            "nan": lambda: self.non_finite(arg),
            "jump": lambda: self.jump_clock(arg),
            "twin": self.add_twin,
            "untwin": self.remove_twin,
            "dc": lambda: self.amplifier(dc_offset=arg),
            "gain": lambda: self.amplifier(gain=arg),
        }
        if what not in actions:
            return (f"unknown fault {what!r}: {', '.join(actions)} (with a channel, seconds, "
                    "an offset or a gain)")  # fmt: skip
        actions[what]()
        return f"{line.strip()}: done"

    # ---- who moves ---------------------------------------------------------------------------
    def contract(self, u_h: int, duration_s: float, delay_s: float) -> float:
        """A contraction ``delay_s`` from now; its onset as stamped (LSL's clock, this
        machine's monotonic one) [s]. The samples may lag real time (a busy machine): the
        contraction is placed at now + ``delay_s`` on their timeline, never in its past."""
        import pylsl

        with self.lock:
            behind = pylsl.local_clock() - (self.started_s + self.synth.t_s)
            self.synth.contract(u_h, duration_s, delay_s + max(0.0, behind))
            onset = self.synth.contractions[-1].start_s
        return self.started_s + onset + 1.0 / self.synth.model.rate_hz

    def act(self, u_h: int, held: bool, delay_s: float) -> str:
        """The simulated patient's contraction (``dammrl.devices.emulators.patient.Body``)."""
        self.contract(u_h, HELD_S if held else QUICK_S, delay_s)
        return f"{'held' if held else 'quick'} contraction {u_h:+d}"

    def follow_cues(self, stop: threading.Event, reaction_s: float = 0.3) -> int:
        """Contract as ``dammrl intent calibrate`` cues until it ends (or ``stop``); the
        number of cues followed."""
        import pylsl

        inlet = None
        followed = 0
        while not stop.is_set() and inlet is None:
            found = pylsl.resolve_byprop("name", cue_stream(self.name), 1, 0.5)
            inlet = pylsl.StreamInlet(found[0]) if found else None
            if inlet is not None:
                inlet.open_stream(5.0)  # subscribed before the first cue is sent
        while inlet is not None and not stop.is_set():
            marker, _ = inlet.pull_sample(timeout=0.2)
            if not marker:
                continue
            cue = marker[0]
            log.info("cue %s", cue)
            if cue == "end":
                break
            with self.lock:
                self.synth.release()
                if cue in ("-1", "+1"):
                    self.synth.contract(int(cue), 60.0, reaction_s)
            followed += 1
        return followed
