"""The registered claim rules: the SHA-256 of every file that turns reaches into verdicts
(``claims.RULE_FILES``), by rules version, in ``registered_rules.json``.

A version is registered by committing its hashes before any study runs under it; a study
report names the version, the rules' digest and whether the files still match. Changing a
rule file without registering a new version fails ``tests/test_registered_rules.py``.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
from importlib.util import find_spec
from pathlib import Path

from dammrl.study.claims import CLAIMS_VERSION, RULE_FILES

REGISTRY = Path(__file__).with_name("registered_rules.json")


def rule_path(name: str) -> Path:
    """Where a rule file (named from the repository root, ``package/...``) is installed."""
    package, _, rest = name.partition("/")
    spec = find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(f"the rule file {name}: no package {package}")
    return Path(next(iter(spec.submodule_search_locations))) / rest


def file_hashes(root: Path | None = None) -> dict[str, str]:
    """Each rule file's SHA-256 (``root``: a repository checkout to read them from instead
    of the installed packages)."""
    return {name: hashlib.sha256(((root / name) if root else rule_path(name)).read_bytes())
            .hexdigest() for name in RULE_FILES}  # fmt: skip


def digest(hashes: dict[str, str]) -> str:
    """One SHA-256 for a set of files: over their names and hashes, in name order."""
    text = "".join(f"{name} {sha}\n" for name, sha in sorted(hashes.items()))
    return hashlib.sha256(text.encode()).hexdigest()


def registered(version: int = CLAIMS_VERSION, registry: Path = REGISTRY) -> dict[str, str]:
    """The hashes registered for ``version`` ({} when it was never registered)."""
    try:
        entry = json.loads(registry.read_text()).get(str(version), {})
    except (OSError, ValueError):
        return {}
    return dict(entry.get("files", {}))


def unregistered_changes(hashes: dict[str, str], version: int = CLAIMS_VERSION,
                         registry: Path = REGISTRY) -> list[str]:  # fmt: skip
    """The rule files whose hash differs from the registered one (every file when the
    version was never registered)."""
    known = registered(version, registry)
    return [name for name, sha in hashes.items() if known.get(name) != sha]


def register(version: int = CLAIMS_VERSION, registry: Path = REGISTRY) -> dict[str, str]:
    """Register the rule files' current hashes as ``version`` (a version once registered
    is never changed: a new one is added)."""
    document = json.loads(registry.read_text()) if registry.exists() else {}
    if str(version) in document:
        raise ValueError(f"claim rules version {version} is registered already: add a version")
    hashes = file_hashes()
    document[str(version)] = {"digest": digest(hashes), "files": hashes}
    registry.write_text(json.dumps(document, indent=1, sort_keys=True) + "\n")
    return hashes


def identity() -> str:
    """The rules a report was judged by: version, digest, the commit that last changed
    any rule file, and whether they match the registration."""
    hashes = file_hashes()
    changed = unregistered_changes(hashes)
    state = (
        "registered"
        if not changed
        else f"NOT the registered version {CLAIMS_VERSION}: {', '.join(changed)} differ"
    )
    return (f"Claim rules version {CLAIMS_VERSION} (digest `{digest(hashes)[:16]}` of "
            f"{len(hashes)} files: {', '.join(f'`{n}`' for n in sorted(hashes))}; "
            f"{_last_commit()}; {state}).")  # fmt: skip


def _last_commit() -> str:
    here = Path(__file__).parent
    paths = [str(rule_path(name)) for name in RULE_FILES]
    try:
        done = subprocess.run(["git", "log", "-1", "--format=last changed in commit %h of %cs",
                               "--", *paths], cwd=here, capture_output=True, text=True,
                              timeout=10)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return "no git history here"
    return done.stdout.strip() if done.returncode == 0 and done.stdout.strip() else (
        "no git history here (an installed package)")  # fmt: skip


if __name__ == "__main__":  # python -m dammrl.study.registry: register the current version
    print(json.dumps(register(), indent=1))
