"""Every documented command runs as the page says, and prints the figures the page states.

The convention (README.md, docs/*.md): every fenced ```` ```bash ```` block is a command a user
standing in the root of a fresh clone types. The blocks of one page run in order, each with
``bash -e -o pipefail``, in one fresh temporary folder that holds ``examples/`` of the checkout
(as a clone would) and has the shared data at ``../shared/data`` (and in ``$MINEGEO_SHARED_DATA``).
A block's exit status must be 0, or the ``N`` of a ``<!-- docs-test: exit N -->`` line right
before it. ```` ```console ```` and ```` ```text ```` blocks are not run.

A ```` ```text ```` block preceded by ``<!-- docs-test: output -->`` is the expected output of the
``bash`` block before it: each of its lines (except lines that are only ``...``) must appear in
that block's output (stdout and stderr as they interleave), in order. In a line, ``...`` stands for any text, runs of spaces for
any white space, and every number must equal the printed one within one unit of its last printed
digit (``0.018`` accepts 0.017 to 0.019; ``37`` accepts 36 to 38), so a figure off by more than
its printed precision fails the test. One test case per page.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from helpers import REQUIRE_SHARED, SHARED_DATA

ROOT = Path(__file__).resolve().parents[2]

#: A generous limit against a hang (not a speed bound): no documented block may run this long.
HANG_TIMEOUT_S = 600

FENCE = re.compile(r"^(?P<indent>\s*)(?P<ticks>`{3,})(?P<lang>[\w+-]*)\s*$")
MARK_EXIT = re.compile(r"^\s*<!--\s*docs-test:\s*exit\s+(?P<status>\d+)\s*-->\s*$")
MARK_OUTPUT = re.compile(r"^\s*<!--\s*docs-test:\s*output\s*-->\s*$")
MARK_ANY = re.compile(r"<!--\s*docs-test:")
NUMBER = re.compile(r"[-+]?(?:\d[\d,]*\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


@dataclass
class Block:
    """One fenced block of a page: its language, first line (1-based) and text."""

    lang: str
    line: int
    text: str
    exit_status: int = 0
    expected_output: list[str] = field(default_factory=list)
    output_line: int = 0


def parse_page(text: str) -> list[Block]:
    """The ``bash`` blocks of a Markdown page with their expected status and output.

    Raises ``ValueError`` on a misused marker (an exit marker not before a ``bash`` block, an
    output marker not before a ``text`` block that follows a ``bash`` block).
    """
    lines = text.splitlines()
    blocks: list[Block] = []
    pending: tuple[str, int, int] | None = None  # (kind, status, line of the marker)
    i = 0
    while i < len(lines):
        line = lines[i]
        m = FENCE.match(line)
        if m is None:
            if MARK_EXIT.match(line):
                pending = ("exit", int(MARK_EXIT.match(line)["status"]), i + 1)
            elif MARK_OUTPUT.match(line):
                pending = ("output", 0, i + 1)
            elif MARK_ANY.search(line):
                raise ValueError(f"line {i + 1}: unknown docs-test marker: {line.strip()}")
            elif line.strip() and pending is not None:
                raise ValueError(f"line {pending[2]}: docs-test marker not directly before a fenced block")
            i += 1
            continue
        indent, ticks, lang = m["indent"], m["ticks"], m["lang"]
        body = []
        j = i + 1
        while j < len(lines) and not re.match(rf"^\s*{ticks}\s*$", lines[j]):
            body.append(lines[j][len(indent):] if lines[j].startswith(indent) else lines[j].lstrip())
            j += 1
        if j == len(lines):
            raise ValueError(f"line {i + 1}: fenced block never closed")
        if pending is not None and pending[0] == "exit":
            if lang != "bash":
                raise ValueError(f"line {pending[2]}: exit marker before a '{lang}' block, not a bash block")
        if pending is not None and pending[0] == "output":
            if lang != "text" or not blocks or blocks[-1].expected_output:
                raise ValueError(f"line {pending[2]}: output marker must precede a text block that follows "
                                 "a bash block")
            blocks[-1].expected_output = body
            blocks[-1].output_line = i + 1
        if lang == "bash":
            status = pending[1] if pending is not None and pending[0] == "exit" else 0
            blocks.append(Block(lang, i + 1, "\n".join(body), exit_status=status))
        pending = None
        i = j + 1
    if pending is not None:
        raise ValueError(f"line {pending[2]}: docs-test marker at the end of the page")
    return blocks


def _line_pattern(expected: str) -> tuple[re.Pattern, list[str]]:
    """A regex for one expected line (numbers captured, ``...`` any text) and its numbers."""
    parts, numbers, pos = [], [], 0
    # a number is compared as a number only when it stands apart from letters (a hash, an id such
    # as GCP05 or a name such as scan_00 is compared as text)
    token = re.compile(r"\.\.\.|(?<![A-Za-z_\d])" + NUMBER.pattern + r"(?![A-Za-z_\d])|\s+")
    for m in token.finditer(expected):
        parts.append(re.escape(expected[pos:m.start()]))
        tok = m.group(0)
        if tok == "...":
            parts.append(".*?")
        elif tok.isspace():
            parts.append(r"\s+")
        else:
            parts.append(f"({NUMBER.pattern})")
            numbers.append(tok)
        pos = m.end()
    parts.append(re.escape(expected[pos:]))
    return re.compile(r"\s*" + "".join(parts) + r"\s*"), numbers


def _unit(printed: str) -> float:
    """One unit of the last printed digit of a number (``0.018`` -> 0.001, ``1.5e-3`` -> 1e-4)."""
    mant, _, exp = printed.replace(",", "").lower().partition("e")
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    return 10.0 ** (-decimals + (int(exp) if exp else 0))


def _to_float(printed: str) -> float:
    return float(printed.replace(",", ""))


def line_matches(expected: str, actual: str) -> bool:
    """Whether ``actual`` is ``expected`` with every number within one unit of its last printed digit."""
    pattern, numbers = _line_pattern(expected)
    m = pattern.fullmatch(actual)
    if m is None:
        return False
    for want, got in zip(numbers, m.groups(), strict=True):
        try:
            if abs(_to_float(got) - _to_float(want)) > _unit(want) * (1 + 1e-9):
                return False
        except ValueError:
            if got != want:
                return False
    return True


def output_mismatch(expected: list[str], output: str) -> str | None:
    """``None`` when every expected line appears in ``output`` in order; else the first one missing."""
    actual = output.splitlines()
    k = 0
    for want in expected:
        if not want.strip() or want.strip() == "...":
            continue
        while k < len(actual) and not line_matches(want, actual[k]):
            k += 1
        if k == len(actual):
            return want
        k += 1
    return None


def _pages() -> list[Path]:
    return [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))


def _sandbox(tmp_path: Path) -> tuple[Path, dict]:
    """A fresh folder standing for the root of a clone, next to ``shared/data``, and its environment."""
    clone = tmp_path / "clone"
    clone.mkdir(parents=True)
    (clone / "examples").symlink_to(ROOT / "examples", target_is_directory=True)
    (tmp_path / "shared").mkdir()
    if SHARED_DATA.is_dir():
        (tmp_path / "shared" / "data").symlink_to(SHARED_DATA.resolve(), target_is_directory=True)
    env = dict(os.environ)
    env["MINEGEO_SHARED_DATA"] = str(tmp_path / "shared" / "data")
    env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env.get("PATH", "")
    # the checkout under test is the package the commands import (as after `pip install .` of it)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [env.get("PYTHONPATH")] if p])
    return clone, env


def run_page(page: Path, tmp_path: Path) -> list[str]:
    """Run every bash block of ``page``; the list of failures (empty when all hold)."""
    rel = page.relative_to(ROOT) if page.is_relative_to(ROOT) else page
    blocks = parse_page(page.read_text(encoding="utf-8"))
    if not blocks:
        return []
    if any("MINEGEO_SHARED_DATA" in b.text for b in blocks) and not SHARED_DATA.is_dir():
        msg = f"shared real data not found: {SHARED_DATA} (set MINEGEO_SHARED_DATA or place ../shared/data)"
        if REQUIRE_SHARED:
            pytest.fail(msg + " and MINEGEO_REQUIRE_SHARED_DATA=1")
        pytest.skip(msg)
    clone, env = _sandbox(tmp_path)
    failures = []
    for b in blocks:
        proc = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", b.text], cwd=clone, env=env,
                              stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, timeout=HANG_TIMEOUT_S)
        out = proc.stdout
        if proc.returncode != b.exit_status:
            failures.append(f"{rel}:{b.line}: exit {proc.returncode}, the page says {b.exit_status}\n"
                            f"--- block ---\n{b.text}\n--- output (last 30 lines) ---\n"
                            + "\n".join(out.splitlines()[-30:]))
            break  # later blocks build on this one
        missing = output_mismatch(b.expected_output, out) if b.expected_output else None
        if missing is not None:
            failures.append(f"{rel}:{b.output_line}: the page states\n    {missing}\nwhich the command "
                            f"did not print (numbers within their printed precision); it printed:\n" + out)
    return failures


@pytest.mark.parametrize("page", _pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_documented_commands_run_as_documented(page, tmp_path):
    failures = run_page(page, tmp_path)
    assert not failures, "\n\n".join(failures)


# -- the checker itself, on hand-written pages (independent of the docs) ------------------------------

def test_parse_page_reads_status_and_expected_output():
    page = ("text\n\n```console\npip install .\n```\n\n<!-- docs-test: exit 2 -->\n```bash\nfalse\n```\n"
            "\n```bash\necho a 0.018\n```\n<!-- docs-test: output -->\n```text\na 0.018\n```\n")
    blocks = parse_page(page)
    assert [(b.text, b.exit_status, b.expected_output) for b in blocks] == [
        ("false", 2, []), ("echo a 0.018", 0, ["a 0.018"])]


@pytest.mark.parametrize("bad", ["<!-- docs-test: exit 2 -->\n```console\nx\n```\n",
                                 "<!-- docs-test: output -->\n```text\nx\n```\n",
                                 "```bash\nx\n```\n<!-- docs-test: output -->\n```bash\nx\n```\n",
                                 "<!-- docs-test: exits 2 -->\n```bash\nx\n```\n",
                                 "<!-- docs-test: exit 2 -->\nprose\n```bash\nx\n```\n"])
def test_parse_page_refuses_a_misused_marker(bad):
    with pytest.raises(ValueError):
        parse_page(bad)


@pytest.mark.parametrize("expected, actual, ok", [
    ("radius 0.018 m", "radius 0.018 m", True),
    ("radius 0.018 m", "radius 0.019 m", True),
    ("radius 0.018 m", "radius 0.020 m", False),
    ("ok 37 of 40", "ok 36 of 40", True),
    ("ok 37 of 40", "ok 35 of 40", False),
    ("time ... s), ok", "time 4.2 s (compile 1 s), ok", True),
    ("sigma0 = 0.6030", "  sigma0  =  0.6031 ", True),
    ("sigma0 = 0.6030", "sigma0 = 0.6033", False),
    ("cost 8,363.6", "cost 8,363.7", True),
    ("status: OK", "status: FAILED", False),
    ("sha256 0fe24c3d", "sha256 0fe24c3e", False),
    ("GCP05 ok", "GCP06 ok", False),
])
def test_line_matches_numbers_within_printed_precision(expected, actual, ok):
    assert line_matches(expected, actual) is ok


def test_a_broken_command_and_a_changed_figure_fail(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("```bash\necho 'sigma0 = 0.6030' && ls examples/quickstart_synthetic_mine.py\n```\n"
                    "<!-- docs-test: output -->\n```text\nsigma0 = 0.6030\n```\n", encoding="utf-8")
    assert run_page(page, tmp_path / "ok") == []
    page.write_text(page.read_text().replace("0.6030\n```\n<", "0.6130\n```\n<").replace(
        "text\nsigma0 = 0.6030", "text\nsigma0 = 0.6130"), encoding="utf-8")
    assert "did not print" in run_page(page, tmp_path / "figure")[0]
    page.write_text("```bash\nls --no-such-flag examples\n```\n", encoding="utf-8")
    assert "exit 2, the page says 0" in run_page(page, tmp_path / "flag")[0]
