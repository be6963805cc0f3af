"""The equation index ``docs/equations.md`` matches the code both ways (issue 16, item 6).

Every equation tag in ``minegeo/`` (``[Baek2022 Eq. 8]``, see ``tests/test_equation_tags.py``)
has a row in the index, and every row names functions (``file::function``) that exist and
whose source carries the tag. After code moved, ``python docs/_equations_index.py`` refreshes
the "Computed in" column (the hand-written columns are kept).
"""

from __future__ import annotations

import pytest
from helpers import load_script

IX = load_script("docs/_equations_index.py", "_equations_index")


@pytest.fixture(scope="module")
def index_and_code():
    _, rows, _ = IX.read_index()
    return rows, IX.scan()


def test_every_tag_in_the_code_has_a_row(index_and_code):
    rows, found = index_and_code
    missing = sorted(t for t in found if t not in rows)
    assert not missing, ("equation tags without a row in docs/equations.md (run `python "
                         "docs/_equations_index.py` and describe them):\n" + "\n".join(missing))


def test_every_row_points_at_code_carrying_its_tag(index_and_code):
    rows, found = index_and_code
    bad = IX.problems(rows, found)
    assert not bad, "docs/equations.md disagrees with the code (`python docs/_equations_index.py` " \
                    "refreshes the 'Computed in' column):\n" + "\n".join(bad)


def test_index_rows_are_complete(index_and_code):
    rows, _ = index_and_code
    assert len(rows) >= 40
    for tag, (eq, words, cell) in rows.items():
        assert IX.TAG.fullmatch(tag), tag
        assert eq and eq != "TODO" and words and words != "TODO" and cell, tag


def test_the_check_fails_on_a_removed_tag_and_a_wrong_function(index_and_code):
    rows, found = index_and_code
    tag = "[Baek2022 Eq. 8]"
    # 1. a tag used in the code but missing from the index
    fewer = {t: r for t, r in rows.items() if t != tag}
    assert any(m.startswith(f"{tag}: in the code") for m in IX.problems(fewer, found))
    # 2. a row whose tag was removed from the code
    no_code = {t: p for t, p in found.items() if t != tag}
    assert any("is in no code" in m for m in IX.problems(rows, no_code))
    # 3. a row naming a function that does not exist
    eq, words, _ = rows[tag]
    wrong = dict(rows, **{tag: [eq, words, "`minegeo/survey/lsq.py::no_such_function`"]})
    assert any("no_such_function does not exist" in m for m in IX.problems(wrong, found))
    # 4. a row naming a real function whose source does not carry the tag
    other = dict(rows, **{tag: [eq, words, "`minegeo/survey/lsq.py::tau_critical`"]})
    assert any("does not carry the tag" in m for m in IX.problems(other, found))
    # 5. a file that does not exist
    gone = dict(rows, **{tag: [eq, words, "`minegeo/no_such_module.py::f`"]})
    assert any("does not exist" in m for m in IX.problems(gone, found))


def test_scan_finds_tags_in_functions_and_module_docstrings(tmp_path, monkeypatch):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "m.py").write_text(
        '"""Module about [Ren2019 Eq. 4]."""\n\n'
        "class A:\n"
        "    def f(self):\n"
        "        return 1  # [Baek2022 Eq. 8]\n\n"
        "def g():\n"
        '    """[Ren2019 Eq. 4] and [Baek2022 Eqs. 10-13]."""\n',
        encoding="utf-8",
    )
    monkeypatch.setattr(IX, "ROOT", tmp_path)
    found = IX.scan("pkg")
    assert found == {"[Baek2022 Eq. 8]": ["pkg/m.py::A.f"],
                     "[Ren2019 Eq. 4]": ["pkg/m.py::g"],  # module docstring dropped: a function has it
                     "[Baek2022 Eqs. 10-13]": ["pkg/m.py::g"]}
    assert "[Baek2022 Eq. 8]" in IX.source_of("pkg/m.py::A.f")
    assert IX.source_of("pkg/m.py::h") is None


def test_refresh_keeps_the_hand_written_columns(tmp_path):
    page = tmp_path / "equations.md"
    page.write_text(IX.INDEX.read_text(encoding="utf-8"), encoding="utf-8")
    _, rows, _ = IX.read_index(page)
    text = IX.refreshed(page)
    page.write_text(text, encoding="utf-8")
    _, rows2, _ = IX.read_index(page)
    assert {t: r[:2] for t, r in rows2.items() if t in rows} == {t: r[:2] for t, r in rows.items() if t in rows2}
    assert all(r[:2] == ["TODO", "TODO"] for t, r in rows2.items() if t not in rows)  # new tags: to describe
