"""The participant display's screenshots in the docs (docs/guide/display_*.png): every
screen of a real session, as tests/test_session_display.py sees them.

    PYTHONPATH=. python benchmarks/display_screenshots.py [--out docs/guide]

A short session (two blocks, the service stack in real time, the emulated pad pressed by
the simulated patient) on the participant's page in headless Chromium (Debian's package,
1280 x 800), with a therapist at the console who takes the decisions over, pauses a
reach, stops one with the emergency stop and runs it again (tests/display_tour.py). One
PNG per screen: cue, moving, outcome, taken, paused, stopped, comfort, rest, end (and the
others met on the way). It takes a few minutes.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

from tests.display_tour import SCREENS, tour

DOCUMENTED = (*SCREENS, "paused")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs/guide"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="dammrl-screens-"))
    try:
        seen = tour(work, work / "shots")
        missing = [kind for kind in DOCUMENTED if kind not in seen.shots]
        for kind in DOCUMENTED:
            if kind in seen.shots:
                shutil.copyfile(seen.shots[kind], args.out / f"display_{kind}.png")
                print(f"wrote {args.out / f'display_{kind}.png'}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if seen.code != 0 or missing or seen.error:
        raise SystemExit(f"the session ended with {seen.code}; screens not caught: {missing}"
                         f"{'; ' + seen.error if seen.error else ''}")  # fmt: skip


if __name__ == "__main__":
    main()
