"""Semi-virtual sensor path benchmarks, in one run on this machine (figures, not pass/fail):

(a) latency from a frame's arrival at the port (written into the emulated pty) to the
    message on the bus, through the real intent service (its own process): every
    SensorSample, and each Intent measured from the frame that completed the press;
    also from the release of the press (includes the decoder's filter and hysteresis);
(b) baseline in the same run: the same frames read straight off the pty with pyserial in
    this process (no decoding, no bus);
(c) the highest frame rate the service decodes and publishes without losing a frame.

    python benchmarks/bench_sensor.py [--presses 40] [--rates 100,250,500,720,1000,2000,5000]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from dammrl.devices.emulators.pad import SensorEmulator
from dammrl_core.intent.pad.protocol import BAUD_RATE
from dammrl_core.intent.pad.serial import SerialSensor
from schemas import DecisionRequest, Health, Intent, SensorSample, decode, type_of
from services.common.bus import Bus
from services.common.config import BusSettings

NS = "dammrl"
UART_FRAME_BYTES = 16  # "$P,1234,2048*HH\r\n" with a 4-digit sequence number
UART_MAX_HZ = BAUD_RATE / 10 / UART_FRAME_BYTES  # 8N1: 10 bits a byte


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def percentiles(samples_s: list[float]) -> str:
    ms = np.asarray(samples_s) * 1e3
    p50, p99 = np.percentile(ms, [50, 99])
    return f"p50 {p50:6.3f} ms  p99 {p99:6.3f} ms  (n={len(ms)})"


class Stack:
    """This process is the hub (and plays the controller); the intent service reads the pty."""

    def __init__(self, link: Path) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.bus = Bus(BusSettings(listen=[self.endpoint], mode="router"), "controller")
        self.raw: list[tuple[float, str, bytes]] = []  # (monotonic, key, payload)
        self.link = link
        self.intent: subprocess.Popen[bytes] | None = None

    def __enter__(self) -> Stack:
        self.bus.__enter__()
        self.bus.session.declare_subscriber(f"{NS}/**", self._on_sample)
        env = os.environ | {
            "DAMMRL_BUS_CONNECT": json.dumps([self.endpoint]),
            "DAMMRL_INTENT_SOURCE": "pad",
            "DAMMRL_PAD_PORT": str(self.link),
            "DAMMRL_LOG_LEVEL": "ERROR",
        }
        self.intent = subprocess.Popen([sys.executable, "-m", "services.intent"], env=env)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.intent is not None:
            self.intent.terminate()
            self.intent.wait(10)
        self.bus.__exit__(None, None, None)

    def _on_sample(self, sample: Any) -> None:  # cheap: decoding waits until the end
        self.raw.append((time.monotonic(), str(sample.key_expr), sample.payload.to_bytes()))

    @property
    def arrivals(self) -> list[tuple[float, Any]]:
        """(arrival, decoded message) of the SensorSamples and Intents so far."""
        decoded = []
        for t, key_expr, payload in list(self.raw):
            message_type = type_of(NS, key_expr)
            if message_type in (SensorSample, Intent, Health):
                decoded.append((t, decode(message_type, payload)))
        return decoded

    def samples(self) -> list[tuple[float, SensorSample]]:
        return [(t, m) for t, m in self.arrivals if isinstance(m, SensorSample)]

    def wait_for_samples(self, count: int, timeout_s: float = 30) -> None:
        deadline = time.monotonic() + timeout_s
        while len(self.raw) < count:
            if time.monotonic() > deadline:
                raise SystemExit("the intent service publishes no SensorSample")
            time.sleep(0.05)


def baseline(link: Path, seconds: float) -> list[float]:
    """Write -> pyserial read in this process, the same emulated frames."""
    latencies = []
    with SensorEmulator(link, [], record_write_times=True) as pad, SerialSensor(str(link)) as port:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            for arrival in port.read():
                written = pad.write_times.get(arrival.frame.seq) if pad.write_times else None
                if written is not None:
                    latencies.append(arrival.t_s - written)
    return latencies


def latency(link: Path, presses: int) -> dict[str, list[float]]:
    with SensorEmulator(link, [], record_write_times=True) as pad, Stack(link) as stack:
        stack.wait_for_samples(50)
        request = stack.bus.publisher(DecisionRequest)
        releases = []
        for k in range(presses):
            request.send(DecisionRequest(header=request.stamp(), episode=1, seed=1, request=k,
                                         t_s=0.0, ee_pos_m=(0.0, 0.0, 0.0), goal_m=(0.3, 0.0, 0.0),
                                         primary_axis=0, human_model=1))  # fmt: skip
            time.sleep(0.1)
            pad.press(1.0, 0.2)
            releases.append(time.monotonic() + 0.2)  # the pad is back at rest
            time.sleep(0.6)
        time.sleep(0.5)
        assert pad.write_times is not None
        return _latencies(stack.arrivals, pad.write_times, releases)


def _latencies(
    arrivals: list[tuple[float, Any]], written: dict[int, float], releases: list[float]
) -> dict[str, list[float]]:
    sample_lat, intent_lat, release_lat = [], [], []
    last_sample: SensorSample | None = None
    for t, message in arrivals:
        if isinstance(message, SensorSample):
            sample_lat.append(t - written[message.device_seq])
            last_sample = message
        elif isinstance(message, Intent) and last_sample is not None:
            # published right after the SensorSample of the frame that completed the press
            intent_lat.append(t - written[last_sample.device_seq])
            if message.request < len(releases):
                release_lat.append(t - releases[message.request])
    return {"sample": sample_lat, "intent": intent_lat, "release": release_lat}


def loss_at(link: Path, rate_hz: float, seconds: float) -> dict[str, Any]:
    """At ``rate_hz``: frames written vs decoded by the service (its Health count) vs
    SensorSamples that reached this process over the bus."""
    with (
        SensorEmulator(link, [], rate_hz=rate_hz, record_write_times=True) as pad,
        Stack(link) as stack,
    ):
        stack.wait_for_samples(20)
        first = stack.samples()[-1][1].device_seq + 1
        time.sleep(seconds)
        pad.silent.set()  # stop sending; everything written so far must be decoded
        last = pad.sent - 1
        time.sleep(1.5)  # let the tail arrive and one more Health report
        arrivals = stack.arrivals
        assert pad.write_times is not None
        span_s = pad.write_times[last] - pad.write_times[first]
    received = {m.device_seq for _, m in arrivals if isinstance(m, SensorSample)}
    health = [m.detail for _, m in arrivals if isinstance(m, Health) and "frames" in m.detail]
    decoded = int(health[-1].split()[0]) if health else 0  # "<n> frames, <m> bad"
    expected = [seq % 65_536 for seq in range(first, last + 1)]
    return {
        "sent_hz": (len(expected) - 1) / span_s,
        "undecoded": pad.sent - min(received) - decoded,  # pyserial flushes on open
        "lost": sum(1 for seq in expected if seq not in received),
        "frames": len(expected),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presses", type=int, default=40)
    parser.add_argument("--rates", default="100,250,500,720,1000,2000,5000")
    parser.add_argument("--seconds", type=float, default=3.0, help="per rate")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "ttySENSOR"
        print("(b) baseline, frame written -> read by pyserial in-process:")
        print(f"    {percentiles(baseline(link, 5.0))}")
        print("(a) frame written -> message on the bus, through the intent service (100 Hz):")
        lat = latency(link, args.presses)
        print(f"    SensorSample                      {percentiles(lat['sample'])}")
        print(f"    Intent, from the deciding frame   {percentiles(lat['intent'])}")
        print(f"    Intent, from the press's release  {percentiles(lat['release'])}")
        print(f"(c) frames lost at each rate ({args.seconds:.0f} s each):")
        clean = {"decoded": 0.0, "on the bus": 0.0}  # highest rate with no loss up to it
        rate_before = 0.0
        for rate in (float(r) for r in args.rates.split(",")):
            r = loss_at(link, rate, args.seconds)
            print(f"    target {rate:5.0f}/s  written {r['sent_hz']:5.0f}/s  not decoded "
                  f"{r['undecoded']:3d}  SensorSamples lost on the bus {r['lost']:4d} of "
                  f"{r['frames']:5d}")  # fmt: skip
            for what, lost in (("decoded", r["undecoded"]), ("on the bus", r["lost"])):
                if lost == 0 and r["sent_hz"] >= 0.95 * rate and clean[what] == rate_before:
                    clean[what] = rate
            rate_before = rate
        print(f"    highest rate without loss: decoded {clean['decoded']:.0f} frames/s, "
              f"every sample on the bus {clean['on the bus']:.0f} frames/s")  # fmt: skip
        print(f"    (a real UART at {BAUD_RATE} baud 8N1 carries at most {UART_MAX_HZ:.0f} "
              f"frames/s of {UART_FRAME_BYTES} bytes)")  # fmt: skip


if __name__ == "__main__":
    main()
