"""Recorder benchmark, in one run (figures, not pass/fail):

(a) the recorder service's sustained rate with zero loss: one publisher process sends
    RobotState-sized messages at a fixed rate (default 10,000/s for 30 s); afterwards the
    file is read back and every sequence number must be there;
(b) the bare mcap writer (zstd chunks) on the same payloads, in this process;
(c) ``dammrl replay --rate 0`` of that recording into another namespace.

    python benchmarks/bench_recorder.py [--rate 10000] [--seconds 30]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh
from mcap.writer import CompressionType, Writer

from dammrl.stack.recording import read_recording
from dammrl.stack.replay import ReplayOptions, replay
from schemas import Header, RobotState, encode
from services.common.bus import zenoh_config
from services.common.config import BusSettings

NS = "bench"


def payload(seq: int) -> bytes:
    header = Header(stamp_ns=time.time_ns(), seq=seq, source="bench")
    j6 = (0.1, -0.2, 0.3, 1.2, 0.0, -0.5)
    return encode(RobotState(header=header, episode=1, t_s=seq * 0.001, q_rad=j6, dq_rad_s=j6,
                             tau_nm=j6, ee_pos_m=(0.4, 0.0, -0.2), ee_vel_m_s=(0.0, 0.0, 0.0),
                             button_pressed=False, button_travel_m=0.0, holding=False))  # fmt: skip


def publisher(endpoint: str, rate: float, seconds: float, done: multiprocessing.Queue) -> None:  # type: ignore[type-arg]
    with zenoh.open(zenoh_config(BusSettings(connect=[endpoint], namespace=NS))) as session:
        pub = session.declare_publisher(
            f"{NS}/robot/state", congestion_control=zenoh.CongestionControl.BLOCK
        )
        time.sleep(1.0)
        start = time.perf_counter()
        sent = 0
        total = int(rate * seconds)
        while sent < total:
            due = int((time.perf_counter() - start) * rate) + 1
            while sent < min(due, total):
                pub.put(payload(sent))  # a fresh header (stamp, seq), as a real publisher
                sent += 1
            time.sleep(0.0005)
        done.put((sent, time.perf_counter() - start))
        time.sleep(1.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=10_000)
    parser.add_argument("--seconds", type=float, default=30.0)
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="dammrl-bench-"))
    path = workdir / "bench.mcap"
    endpoint = "tcp/127.0.0.1:17890"

    with zenoh.open(zenoh_config(BusSettings(listen=[endpoint], mode="router", namespace=NS))):
        env = os.environ | {
            "DAMMRL_BUS_CONNECT": f'["{endpoint}"]',
            "DAMMRL_BUS_NAMESPACE": NS,
            "DAMMRL_RECORDER_OUT": str(path),
            "DAMMRL_LOG_LEVEL": "WARNING",
        }
        recorder = subprocess.Popen([sys.executable, "-m", "services.recorder"], env=env)
        time.sleep(3.0)
        spawn = multiprocessing.get_context("spawn")
        done: multiprocessing.Queue = spawn.Queue()  # type: ignore[type-arg]
        pub = spawn.Process(target=publisher, args=(endpoint, args.rate, args.seconds, done))
        pub.start()
        sent, publish_s = done.get(timeout=args.seconds * 3 + 60)
        pub.join()
        time.sleep(2.0)
        recorder.send_signal(signal.SIGINT)
        recorder.wait(120)

    recording = read_recording(path)
    seqs = sorted(
        m.sequence for m in recording.messages if recording.topic(m) == f"{NS}/robot/state"
    )
    missing = sent - len(set(seqs))
    rate = sent / publish_s
    print(f"(a) recorder service: {sent} messages at {rate:,.0f}/s for {publish_s:.1f} s")
    print(f"    recorded {len(seqs)}, missing {missing}, every sequence number: {missing == 0}; "
          f"file {path.stat().st_size / 1e6:.1f} MB")  # fmt: skip

    payloads = [payload(i) for i in range(min(sent, 100_000))]
    with open(workdir / "bare.mcap", "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start()
        channel = writer.register_channel("robot/state", "msgpack", 0)
        start = time.perf_counter()
        for i, data in enumerate(payloads):
            writer.add_message(channel, time.time_ns(), data, time.time_ns(), i)
        writer.finish()  # type: ignore[no-untyped-call]
        bare_s = time.perf_counter() - start
    print(f"(b) bare mcap writer (zstd), same payloads: {len(payloads) / bare_s:,.0f} messages/s")

    replay_endpoint = "tcp/127.0.0.1:17891"
    with zenoh.open(
        zenoh_config(BusSettings(listen=[replay_endpoint], mode="router", namespace="replayed"))
    ) as s:
        got = []
        s.declare_subscriber("replayed/**", lambda sample: got.append(1))
        settings = BusSettings(connect=[replay_endpoint], namespace="replayed")
        start = time.perf_counter()
        n = replay(recording, settings, ReplayOptions(rate=0.0), info=lambda _: None)
        replay_s = time.perf_counter() - start - 1.0  # replay() waits 1 s to connect
        time.sleep(2.0)
    print(
        f"(c) replay --rate 0: {n} messages in {replay_s:.2f} s = {n / replay_s:,.0f}/s "
        f"({len(got)} received)"
    )


if __name__ == "__main__":
    main()
