"""docs/study/publish.sh, the commands that produce the published study, stays runnable:
every `dammrl` line in it is one the CLI accepts, with known conditions, pages that carry
their generated sections, and a side-by-side of studies the script itself writes."""

from __future__ import annotations

import shlex
from pathlib import Path

from dammrl.cli import parser
from dammrl.study.configs import CONDITIONS
from dammrl.study.report import RANGES, check_page

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "docs" / "study" / "publish.sh"


def _commands() -> list[list[str]]:
    """Each `dammrl ...` command of the script, continuation lines joined, variables set."""
    text = SCRIPT.read_text().replace("\\\n", " ")
    text = text.replace("$JOBS", "1").replace("$RUNS", "runs").replace("$R", "1")
    lines = [line.strip() for line in text.splitlines()]
    return [shlex.split(line)[1:] for line in lines if line.startswith("dammrl ")]


def test_every_command_of_the_publication_is_one_the_cli_accepts() -> None:
    commands = _commands()
    assert [c[0] for c in commands] == ["train", "study", "study", "study", "verdicts"]
    outs = []
    for argv in commands:
        args = parser().parse_args(argv)
        if argv[0] == "train":
            assert args.seeds == 12 and args.ship_seeds is not None  # the design's 12 runs
        if argv[0] == "study":
            conditions = args.conditions or ()
            assert set(conditions) <= set(CONDITIONS), conditions
            for page in args.results:
                check_page(ROOT / page)
            outs.append(args.out)
        if argv[0] == "verdicts":
            assert args.studies == outs[:2]  # both ranges, as run above
            for page in args.results:
                check_page(ROOT / page, (RANGES,))


def test_the_two_ranges_are_disjoint_and_fresh() -> None:
    """The second range shares no seed with the first, and neither any seed the training
    runs were evaluated or validated on, or the best-fixed search was tuned on."""
    seen_before = {*range(7_000_000, 7_000_100), *range(7_900_000, 7_900_020),
                   *range(7_950_000, 7_950_050)}  # fmt: skip
    studies = [parser().parse_args(argv) for argv in _commands() if argv[0] == "study"]
    first, second = set(studies[0].seeds), set(studies[1].seeds)
    assert len(first) == len(second) == 300 and not first & second
    assert not (first | second) & seen_before
    assert set(studies[2].seeds) <= first  # the solve-time sweep: the first range's first 100
