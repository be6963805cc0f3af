"""Docs name papers and data by name or by repository-relative path, never by one machine's path.

An absolute path such as ``/work/shared/papers/...`` or ``/home/<user>/data`` only exists on
the machine it was copied from. Pages in ``docs/``, ``README.md``, ``examples/*.md`` and the
docstrings and comments under ``minegeo/`` must cite ``../shared/data/<name>``-style relative
paths or names instead. Scratch paths in example commands (``/tmp/...``) are allowed.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: A path rooted in one machine's directories (POSIX or Windows).
MACHINE_PATH = re.compile(r"(?<![\w.~-])/(?:work|home|root|Users|mnt|media|srv)/[\w.-]+"
                          r"|\b[A-Za-z]:\\(?:Users|work|home)\\", re.IGNORECASE)


def prose(text: str) -> list[tuple[int, str]]:
    """``(line, text)`` of every comment and string-expression statement (docstrings) of Python ``text``."""
    out = [(tok.start[0], tok.string) for tok in tokenize.generate_tokens(io.StringIO(text).readline)
           if tok.type == tokenize.COMMENT]
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) \
                and isinstance(node.value.value, str):
            out += [(node.lineno + i, line) for i, line in enumerate(node.value.value.splitlines())]
    return out


def machine_paths(lines) -> list[str]:
    """``line: path`` of every machine path in ``(line, text)`` pairs."""
    return [f"{n}: {m[0]}" for n, text in lines for m in MACHINE_PATH.finditer(text)]


def _pages() -> list[Path]:
    pages = sorted((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"]
    return pages + sorted((ROOT / "examples").rglob("*.md"))


@pytest.mark.parametrize("page", _pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_pages_cite_no_machine_path(page):
    lines = enumerate(page.read_text(encoding="utf-8").splitlines(), start=1)
    bad = machine_paths(lines)
    assert not bad, f"{page.relative_to(ROOT)} cites absolute machine paths:\n" + "\n".join(bad)


def test_docstrings_and_comments_cite_no_machine_path():
    bad = []
    for path in sorted((ROOT / "minegeo").rglob("*.py")):
        if "__pycache__" in path.parts:
            continue
        bad += [f"{path.relative_to(ROOT)}:{hit}" for hit in machine_paths(prose(path.read_text(encoding="utf-8")))]
    assert not bad, "docstrings or comments cite absolute machine paths:\n" + "\n".join(bad)


def test_checker_catches_machine_paths():
    root = "/" + "work"  # split so this file does not carry the pattern it looks for
    home = "/" + "home"
    text = (f'"""Paper at {root}/shared/papers/baek2022.txt."""\n'
            f"x = 1  # data in {home}/alice/mine.ply\n"
            f'y = "{root}/ignored: a string literal, not prose"\n')
    assert sorted(h.split(": ")[1] for h in machine_paths(prose(text))) == [f"{home}/alice", f"{root}/shared"]
    assert machine_paths([(1, "C:\\Users\\bob\\scan.ply")])
    for ok in ("../shared/papers/baek2022.txt", "shared/data/krumm", "/tmp/paper", "`minegeo synth /tmp/x`",
               "https://example.org/home/page", "docs/work/notes"):
        assert not machine_paths([(1, ok)]), ok
