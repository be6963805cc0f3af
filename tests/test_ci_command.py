"""The README's test command is the one `.ci/run` runs: the same extras installed, then pytest."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _extras(text: str) -> list[str]:
    m = re.findall(r"pip install (?:-q )?-e '\.\[([a-z0-9_,]+)\]'", text)
    assert len(m) == 1, f"expected one editable install command, found {m}"
    return sorted(m[0].split(","))


def test_readme_test_command_installs_what_ci_installs():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert _extras(readme) == _extras(ci)
    assert "python -m pytest" in readme and re.search(r"^python -m pytest", ci, re.M)
    # the same worker processes (pytest-xdist, in the test extra): the README's run is the CI's
    workers = re.compile(r"python -m pytest (-n \d+ --dist \w+)")
    assert workers.search(readme) and workers.search(readme).group(1) == workers.search(ci).group(1)


def test_every_extra_is_installed_by_the_test_command():
    """An extra left out of the command would let its tests skip silently (they fail only when installed
    flags are set for what is installed)."""
    toml = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    block = toml.split("[project.optional-dependencies]", 1)[1].split("\n[", 1)[0]
    declared = sorted(re.findall(r"^([a-z0-9_]+)\s*=", block, re.M))
    assert _extras((ROOT / ".ci" / "run").read_text(encoding="utf-8")) == declared
