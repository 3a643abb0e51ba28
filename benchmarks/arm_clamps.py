"""Clamps of the stack's own commands by the arm's caps, idle and under load (prints figures).

``dammrl up --record`` runs N ordinary episodes (no attack) on a quiet machine and beside
two busy programs (another workload on the lab's PC). From each recording: the commands
the sim's caps clamped (its Health), the states the controller skipped because a newer
one was already waiting (its Health), episodes ended by a stale hold, and the fastest
measured joint speed as a fraction of its URDF limit.

    PYTHONPATH=. python benchmarks/arm_clamps.py [--episodes 10]
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from dammrl.stack.recording import read_recording
from dammrl_core.robot import RobotDescription
from schemas import EpisodeResult, Health, RobotState
from tests.busutil import free_port

HOG = "while True: pass"  # another program on the lab's PC, at the default priority
CONFIGS = {"idle": 0, "2 CPU hogs": 2}


def _run(episodes: int, hogs: int, out: Path) -> Path:
    record = out / f"hogs{hogs}.mcap"
    busy = [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(hogs)]
    try:
        subprocess.run(
            [sys.executable, "-m", "dammrl", "up", "--episodes", str(episodes), "--insecure",
             "--bus-port", str(free_port()), "--record", str(record)],
            check=True, capture_output=True, timeout=60 * episodes + 120,
        )  # fmt: skip
    finally:
        for hog in busy:
            hog.kill()
    return record


def _last_count(healths: list[Health], service: str, pattern: str) -> int:
    details = [h.detail for h in healths if h.service == service]
    counts = [int(m.group(1)) for d in details if (m := re.search(pattern, d))]
    return max(counts, default=0)


def _figures(record: Path, episodes: int) -> dict[str, float]:
    recording = read_recording(record)
    decoded = [m for _, m in recording.decoded(Health, EpisodeResult, RobotState)]
    healths = [m for m in decoded if isinstance(m, Health)]
    results = [m for m in decoded if isinstance(m, EpisodeResult)]
    states = [m for m in decoded if isinstance(m, RobotState)]
    speeds = np.abs([s.dq_rad_s for s in states]) / RobotDescription.from_urdf().dq_max
    return {
        "clamps per episode": _last_count(healths, "sim", r"(\d+) commands clamped") / episodes,
        "states superseded per episode": _last_count(
            healths, "controller", r"(\d+) states superseded"
        )
        / episodes,
        "stale holds": sum("stale" in r.reason or "stalled" in r.reason for r in results),
        "successes": sum(r.success for r in results),
        "fastest joint / limit": float(speeds.max()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        for name, hogs in CONFIGS.items():
            figures = _figures(_run(args.episodes, hogs, Path(folder)), args.episodes)
            shown = ", ".join(
                f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in figures.items()
            )
            print(f"{name} ({args.episodes} episodes): {shown}", flush=True)


if __name__ == "__main__":
    main()
