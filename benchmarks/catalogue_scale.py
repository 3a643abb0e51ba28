"""How the catalogue, the reports and the BIDS export grow with the sessions (prints
seconds, and each as a ratio to the smallest set's in the same run).

Real sessions (``--from``: a sessions' folder, e.g. what
``benchmarks/session_ledger_under_load.py --root`` kept) are cloned into sets of
``--sizes`` sessions, two a participant: each clone's recordings rewritten with the
study tag of its new folder (else the catalogue rightly passes them over), its trial log
and events copied. For each set: a fresh ``dammrl sessions catalogue``, ``report --all``
and ``bids``, in process, the fastest of ``--repeats``: its CPU time (this process's;
steady on a shared machine) and its wall time. Linear growth doubles a time when the
sessions double.

    python benchmarks/catalogue_scale.py --from SESSIONS [--sizes 10 20 40] [--repeats 2]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from mcap.writer import CompressionType, Writer

from dammrl.data.bids import export
from dammrl.data.catalogue import build
from dammrl.data.outcomes import every_participant_report
from dammrl.stack.recording import read_recording


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--from", dest="source", type=Path, required=True)
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 20, 40])
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    sessions = sorted(p for p in args.source.glob("*/ses-*") if (p / "trials.jsonl").exists())
    work = Path(tempfile.mkdtemp(prefix="scale-"))
    print(f"{len(sessions)} real sessions cloned from {args.source}")
    rows = []
    for size in args.sizes:
        root = work / f"n{size}"
        megabytes = _clone(sessions, root, size)
        cpu, wall = _timed(root, work, args.repeats)
        rows.append((size, megabytes, cpu))
        print(f"{size} sessions ({megabytes:.0f} MB of recordings), CPU (wall) s: catalogue "
              f"{cpu[0]:.1f} ({wall[0]:.1f}), report --all {cpu[1]:.1f} ({wall[1]:.1f}), "
              f"bids {cpu[2]:.1f} ({wall[2]:.1f})", flush=True)  # fmt: skip
    base = rows[0]
    print(f"\nCPU seconds (ratio to {base[0]} sessions)")
    print("sessions    MB   catalogue        report --all     bids")
    for size, mb, times in rows:
        cells = "  ".join(f"{t:6.1f} s ({t / b:4.2f})" for t, b in zip(times, base[2], strict=True))
        print(f"{size:8d}  {mb:4.0f}  {cells}   sessions x{size / base[0]:.1f}")
    shutil.rmtree(work, ignore_errors=True)


def _timed(root: Path, work: Path, repeats: int) -> tuple[list[float], list[float]]:
    steps: list[Callable[[], object]] = [
        lambda: (shutil.rmtree(root / "catalogue", ignore_errors=True), build(root)),
        lambda: every_participant_report(root, work / "reports"),
        lambda: (shutil.rmtree(work / "bids", ignore_errors=True), export(root, work / "bids")),
    ]
    cpu, wall = [], []
    for step in steps:
        times = []
        for _ in range(repeats):
            started = (time.process_time(), time.perf_counter())
            step()
            times.append((time.process_time() - started[0], time.perf_counter() - started[1]))
        cpu.append(min(t[0] for t in times))
        wall.append(min(t[1] for t in times))
    shutil.rmtree(work / "reports", ignore_errors=True)
    shutil.rmtree(work / "bids", ignore_errors=True)
    return cpu, wall


def _clone(sessions: list[Path], root: Path, size: int) -> float:
    """``size`` sessions under ``root``, two a participant; MB of recordings."""
    total = 0
    for n in range(size):
        source = sessions[n % len(sessions)]
        participant, session = f"P{n // 2 + 1:03d}", f"ses-{n % 2 + 1:02d}"
        target = root / participant / session
        (target / "recordings").mkdir(parents=True)
        for name in ("trials.jsonl", "events.jsonl", "session.json", "protocol.yaml"):
            if (source / name).exists():
                shutil.copy2(source / name, target / name)
        for recording in sorted((source / "recordings").glob("*.mcap")):
            total += _retagged(recording, target / "recordings" / recording.name,
                               participant, session)  # fmt: skip
    return total / 1e6


def _retagged(path: Path, out: Path, participant: str, session: str) -> int:
    """``path`` rewritten to ``out`` with its study tag naming ``participant``/``session``."""
    recording = read_recording(path)
    with open(out, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="dammrl", library="benchmarks/catalogue_scale.py")
        for name, data in recording.metadata.items():
            if name == "dammrl.session" and "study" in data:
                study = json.loads(data["study"]) | {"participant": participant, "session": session}
                data = data | {"study": json.dumps(study)}
            writer.add_metadata(name, data)
        schemas = {sid: writer.register_schema(s.name, s.encoding, s.data)
                   for sid, s in recording.schemas.items()}  # fmt: skip
        channels = {cid: writer.register_channel(c.topic, c.message_encoding,
                                                 schemas.get(c.schema_id, 0), c.metadata)
                    for cid, c in recording.channels.items()}  # fmt: skip
        for m in recording.messages:
            writer.add_message(channels[m.channel_id], m.log_time, m.data, m.publish_time,
                               m.sequence)  # fmt: skip
        writer.finish()  # type: ignore[no-untyped-call]
    return out.stat().st_size


if __name__ == "__main__":
    main()
