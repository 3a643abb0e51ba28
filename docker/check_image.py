"""The image is whole, or its build stops with one line naming what is missing.

Run by the Dockerfile, twice:

    python docker/check_image.py wheel WHEEL   # build stage, in the build context
    python docker/check_image.py installed     # runtime stage, on the installed package

``wheel``: every package folder of the build context (a top-level folder with an
``__init__.py``) is in the wheel, with every file under it (the URDF, the shipped
policies, the protocols), so nothing pip would install is left out of the image.
``installed``: every file of the installed distribution is on disk; every module of every
top-level package imports (a missing shared library, such as pinocchio's libgomp, fails
here rather than in a service); the URDF builds the MuJoCo scene and pinocchio's model;
every shipped policy loads.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import pkgutil
import sys
import zipfile
from pathlib import Path

DISTRIBUTION = "dammrl"


def check_wheel(wheel: Path, context: Path) -> list[str]:
    """What the build context has and the wheel lacks."""
    names = set(zipfile.ZipFile(wheel).namelist())
    packages = sorted(p.name for p in context.iterdir() if (p / "__init__.py").is_file())
    if not packages:
        return [f"no package folder in the build context {context}"]
    files = [
        p.relative_to(context).as_posix()
        for package in packages
        for p in (context / package).rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    ]
    return [f"{name} is not in the wheel" for name in files if name not in names]


def check_installed() -> list[str]:
    """What the installed distribution lacks, or cannot import or load."""
    dist = importlib.metadata.distribution(DISTRIBUTION)
    problems = [f"{f} is listed in the wheel but not on disk"
                for f in dist.files or [] if not Path(str(f.locate())).exists()]  # fmt: skip
    tops = (dist.read_text("top_level.txt") or "").split()
    if not tops:
        problems.append("the installed distribution names no top-level package")
    for top in tops:
        problems += _import_all(top)
    return problems or _load_shipped_data()


def _import_all(top: str) -> list[str]:
    """Import ``top`` and every module below it but the ``__main__`` ones (they run)."""
    failed: list[str] = []
    try:
        package = importlib.import_module(top)
    except Exception as exc:  # any failure to import is what this check reports
        return [f"import {top}: {exc!r}"]
    for module in pkgutil.walk_packages(package.__path__, f"{top}.", failed.append):
        if module.name.rsplit(".", 1)[-1] == "__main__":
            continue
        try:
            importlib.import_module(module.name)
        except Exception as exc:
            failed.append(f"{module.name}: {exc!r}")
    return [f"import {name}" if "." not in name else name for name in failed]


def _load_shipped_data() -> list[str]:
    from dammrl_core.models import ModelSet
    from dammrl_core.policy.learned import SHIPPED_RUNS, LearnedPolicy
    from dammrl_core.robot.description import RobotDescription
    from dammrl_core.robot.scene import SceneLayout, build_scene

    try:
        robot = RobotDescription.from_urdf()
        build_scene(robot, SceneLayout())
        for run in SHIPPED_RUNS:
            LearnedPolicy(ModelSet(), Path(run))
    except Exception as exc:
        return [f"shipped data: {exc!r}"]
    return []


def main(argv: list[str]) -> int:
    if argv[:1] == ["wheel"] and len(argv) == 2:
        problems = check_wheel(Path(argv[1]), Path.cwd())
    elif argv == ["installed"]:
        problems = check_installed()
    else:
        print("usage: check_image.py wheel WHEEL | installed", file=sys.stderr)
        return 2
    for problem in problems:
        print(f"image check: {problem}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
