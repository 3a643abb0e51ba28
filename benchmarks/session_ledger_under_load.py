"""Sessions run beside CPU hogs, then every trial they logged looked for in the catalogue
(prints counts; exits 1 when a logged trial is neither catalogued nor reported).

Runs ``--sessions`` sessions of the shipped protocol (its rests left out) through
``dammrl session run`` with the simulated participant, one participant each, while
``--hogs`` processes of ``yes > /dev/null`` take the CPU; then builds the catalogue and
reconciles: each line of each session's ``trials.jsonl`` is recorded whole, in part,
missing with its reason, or skipped (no reach). Every process it starts, it ends.

    python benchmarks/session_ledger_under_load.py [--sessions 10] [--hogs 2] [--lockstep]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import yaml

from dammrl.data.catalogue import build, query
from tests.busutil import free_port

SHIPPED = (
    Path(__file__).resolve().parents[1] / "dammrl" / "people" / "protocols" / "event-vs-fixed.yaml"
)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=10)
    parser.add_argument("--hogs", type=int, default=2)
    parser.add_argument("--lockstep", action="store_true", help="sessions on the robot clock")
    parser.add_argument("--root", type=Path, help="keep the sessions here (default: a temp dir)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="ledger-"))
    root = args.root or work / "sessions"
    protocol = work / "protocol.yaml"
    shipped = yaml.safe_load(SHIPPED.read_text())
    for block in shipped["blocks"]:
        block.pop("rest_s", None)
    protocol.write_text(yaml.safe_dump(shipped))
    hogs = [subprocess.Popen("exec yes > /dev/null", shell=True) for _ in range(args.hogs)]
    started = time.monotonic()
    try:
        codes = [_session(root, protocol, n, args.lockstep) for n in range(1, args.sessions + 1)]
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
    ran_s = time.monotonic() - started
    built = build(root)
    return _report(root, codes, ran_s, built.incomplete, args)


def _session(root: Path, protocol: Path, n: int, lockstep: bool) -> int:
    command = [sys.executable, "-m", "dammrl", "session", "run", "--participant", f"P{n:03d}",
               "--protocol", str(protocol), "--root", str(root), "--no-display",
               "--bus-port", str(free_port())] + (["--lockstep"] if lockstep else [])  # fmt: skip
    done = subprocess.run(command, stdin=subprocess.DEVNULL, capture_output=True, text=True)
    said = [line for line in done.stderr.splitlines() if "recorder did not confirm" in line
            or "recorded without" in line]  # fmt: skip
    print(f"P{n:03d}: exit {done.returncode}" + "".join(f"\n  {line}" for line in said))
    return done.returncode


def _report(root: Path, codes: list[int], ran_s: float, incomplete: list[str],
            args: argparse.Namespace) -> int:  # fmt: skip
    lines = sum(len(p.read_text().splitlines()) for p in root.glob("*/ses-*/trials.jsonl"))
    _, rows = query(root, "SELECT status, count(*) FROM completeness WHERE line IS NOT NULL "
                          "GROUP BY 1 ORDER BY 1")  # fmt: skip
    statuses = Counter(dict(rows))
    _, unlogged = query(root, "SELECT count(*) FROM completeness WHERE status = 'unlogged'")
    _, catalogued = query(root, "SELECT count(*) FROM trials")
    unexplained_sql = ("SELECT count(*) FROM completeness WHERE status IN ('missing', "
                       "'partial') AND coalesce(reason, '') = ''")  # fmt: skip
    _, unexplained = query(root, unexplained_sql)
    mode = "lockstep" if args.lockstep else "real time"
    print(
        f"{len(codes)} sessions ({mode}) beside {args.hogs} CPU hogs in {ran_s:.0f} s; "
        f"exit codes {dict(Counter(codes))}"
    )
    print(
        f"trials.jsonl lines: {lines}; reconciled: {sum(statuses.values())} "
        f"({', '.join(f'{k} {v}' for k, v in sorted(statuses.items()))}); "
        f"reaches in the catalogue: {catalogued[0][0]}; recorded but not logged: "
        f"{unlogged[0][0]}"
    )
    for line in incomplete:
        print(f"  {line}")
    accounted = sum(statuses.values()) == lines and unexplained[0][0] == 0
    print("every logged trial is catalogued or reported with its reason: "
          + ("yes" if accounted else "NO"))  # fmt: skip
    print(json.dumps({"lines": lines, **statuses, "root": str(root)}))
    return 0 if accounted else 1


if __name__ == "__main__":
    sys.exit(main())
