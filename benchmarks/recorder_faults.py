"""Recorder faults, measured (figures, not pass/fail):

(a) ``crafted``: every recording tool (info, repair, export json/csv, human, plot, replay)
    on every crafted or corrupt MCAP of ``tests/test_recorder_faults.py``, as the user
    runs it (``python -m dammrl ...``): how many answers are tracebacks, and the exit codes;
(b) ``kill``: the recorder on a live 500 Hz stream, killed with SIGKILL at several moments
    after it is up (its first Health); the file read back (repaired when cut): data lost =
    kill time - last recorded message [s];
(c) ``gaps``: ``recording info``'s sequence gaps on the crafted fuzzed-sequence file.

``--code-from DIR`` runs the tools and the recorder of another tree (e.g. ``git archive
<commit> dammrl services schemas | tar -x -C DIR``) for a before/after comparison.

    PYTHONPATH=. python benchmarks/recorder_faults.py [crafted|kill|gaps ...]
        [--kill-at 0.5,2,5,12] [--code-from DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import zenoh

from schemas import Header, RobotState, encode
from services.common.bus import zenoh_config
from services.common.config import BusSettings
from tests.test_recorder_faults import crafted_files

TOOLS = {
    "info": ["recording", "info", "{file}"],
    "repair": ["recording", "repair", "{file}", "-o", "{out}/repaired.mcap"],
    "export json": ["recording", "export", "{file}", "--format", "json", "-o", "{out}/x.mcap"],
    "export csv": ["recording", "export", "{file}", "--format", "csv", "-o", "{out}/csv"],
    "human": ["recording", "human", "{file}"],
    "plot": ["recording", "plot", "{file}", "-o", "{out}/plot.png"],
    "replay": ["replay", "{file}", "--rate", "0", "--namespace", "crafted", "--connect", "{bus}"],
}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def run_tool(argv: list[str], code_from: Path | None = None) -> tuple[int, str]:
    """Exit code and the last line of stderr (the whole of it when it is a traceback)."""
    done = subprocess.run([sys.executable, "-m", "dammrl", *argv], capture_output=True,
                          text=True, timeout=120, stdin=subprocess.DEVNULL,
                          cwd=code_from)  # fmt: skip
    err = done.stderr.strip()
    if "Traceback" in err:
        return done.returncode, "TRACEBACK " + err.splitlines()[-1]
    return done.returncode, (err.splitlines() or [""])[-1]


def crafted(workdir: Path, code_from: Path | None) -> None:
    port = free_port()
    bus = f"tcp/127.0.0.1:{port}"
    router = BusSettings(listen=[bus], mode="router", namespace="crafted")
    tracebacks, codes = 0, Counter[int]()
    with zenoh.open(zenoh_config(router)):
        for name, path in crafted_files(workdir).items():
            print(f"{name}:")
            for tool, template in TOOLS.items():
                out = Path(tempfile.mkdtemp(dir=workdir))
                argv = [a.format(file=path, out=out, bus=bus) for a in template]
                code, line = run_tool(argv, code_from)
                tracebacks += line.startswith("TRACEBACK")
                codes[code] += 1
                print(f"    {tool:12s} exit {code:3d}  {line[:110]}")
    cases = len(TOOLS) * len(crafted_files(workdir))
    print(f"(a) crafted files: {tracebacks} tracebacks in {cases} cases; exit codes {dict(codes)}")


def publish_states(endpoint: str, rate_hz: float, stop: threading.Event) -> None:
    """RobotState at ``rate_hz`` with a fresh header, as the sim publishes it."""
    j6 = (0.0,) * 6
    with zenoh.open(zenoh_config(BusSettings(connect=[endpoint]))) as session:
        publisher = session.declare_publisher("dammrl/robot/state")
        seq, start = 0, time.perf_counter()
        while not stop.is_set():
            header = Header(stamp_ns=time.time_ns(), seq=seq, source="sim")
            publisher.put(encode(RobotState(header=header, episode=1, t_s=seq / rate_hz,
                q_rad=j6, dq_rad_s=j6, tau_nm=j6, ee_pos_m=(0.4, 0, 0), ee_vel_m_s=(0, 0, 0),
                button_pressed=False, button_travel_m=0.0, holding=False)))  # fmt: skip
            seq += 1
            time.sleep(max(0.0, start + seq / rate_hz - time.perf_counter()))


def last_recorded_ns(path: Path) -> tuple[int | None, str]:
    """The log time of the last message readable in ``path`` (repaired first when cut)."""
    from dammrl.stack.recording import RecordingError, read_recording, repair

    try:
        recording = read_recording(path)
        if not recording.complete:
            repair(path, path.with_suffix(".repaired.mcap"))
    except RecordingError as exc:
        return None, str(exc)
    times = [m.log_time for m in recording.messages]
    return (max(times) if times else None), f"{len(times)} messages, {path.stat().st_size} B"


def kill(workdir: Path, moments_s: list[float], code_from: Path | None) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    stop = threading.Event()
    with zenoh.open(zenoh_config(BusSettings(listen=[endpoint], mode="router"))) as session:
        healthy: list[int] = []
        session.declare_subscriber("dammrl/health/recorder", lambda s: healthy.append(1))
        publisher = threading.Thread(target=publish_states, args=(endpoint, 500.0, stop))
        publisher.start()
        try:
            for at_s in moments_s:
                healthy.clear()
                kill_once(workdir, endpoint, at_s, healthy, code_from)
        finally:
            stop.set()
            publisher.join()


def kill_once(
    workdir: Path, endpoint: str, at_s: float, healthy: list[int], code_from: Path | None
) -> None:
    path = workdir / f"killed-at-{at_s:g}s.mcap"
    env = os.environ | {
        "DAMMRL_BUS_CONNECT": json.dumps([endpoint]),
        "DAMMRL_RECORDER_OUT": str(path),
        "DAMMRL_LOG_LEVEL": "WARNING",
    }
    if code_from is not None:
        env["PYTHONPATH"] = str(code_from)
    recorder = subprocess.Popen(  # python -m puts the working directory first on the path
        [sys.executable, "-m", "services.recorder"], env=env, cwd=code_from
    )
    with contextlib.suppress(TimeoutError):
        wait_until(lambda: bool(healthy), 30)  # up and subscribed
    time.sleep(at_s)
    killed_ns = time.time_ns()
    recorder.send_signal(signal.SIGKILL)
    recorder.wait(10)
    last_ns, what = last_recorded_ns(path)
    lost = f"all ({at_s:g} s)" if last_ns is None else f"{(killed_ns - last_ns) * 1e-9:.2f} s"
    print(f"(b) kill -9 {at_s:5.1f} s after the recorder is up: data lost {lost} ({what})")


def wait_until(condition: object, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        if time.monotonic() > deadline:
            raise TimeoutError
        time.sleep(0.05)


def gaps(workdir: Path, code_from: Path | None) -> None:
    path = crafted_files(workdir)["fuzzed sequence number"]
    done = subprocess.run([sys.executable, "-m", "dammrl", "recording", "info", str(path),
                           "--json"], capture_output=True, text=True, cwd=code_from)  # fmt: skip
    code = done.returncode
    summary = json.loads(done.stdout) if done.returncode == 0 else {}
    print(f"(c) fuzzed seq (9 real messages 1..9, one claiming 2**32-1): exit {code}, "
          f"sequence_gaps {summary.get('sequence_gaps')}, "
          f"anomalies {summary.get('sequence_anomalies')}")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("parts", nargs="*", default=["crafted", "kill", "gaps"])
    parser.add_argument("--kill-at", default="0.5,2,5,12", help="seconds, comma-separated")
    parser.add_argument("--code-from", type=Path, help="a tree whose tools and recorder to run")
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="dammrl-faults-"))
    if "crafted" in args.parts:
        crafted(workdir, args.code_from)
    if "kill" in args.parts:
        kill(workdir, [float(s) for s in args.kill_at.split(",")], args.code_from)
    if "gaps" in args.parts:
        gaps(workdir, args.code_from)


if __name__ == "__main__":
    main()
