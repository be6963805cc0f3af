"""Every benchmark figure in README.md and docs/*.md is the one its committed results file holds.

The figures live between ``<!-- figures: NAME -->`` and ``<!-- /figures -->``;
``benchmarks/render_docs_figures.py`` renders each block from its file under
``benchmarks/results`` (``--write``), and this test fails, with the diff, when the text of a page
and the file disagree (``--check``).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from helpers import load_script

ROOT = Path(__file__).resolve().parents[2]


render = load_script("benchmarks/render_docs_figures.py", "render_docs_figures")


def test_every_figures_block_agrees_with_its_results_file():
    diffs = render.check()
    assert not diffs, ("pages disagree with their results files (run `python benchmarks/"
                       "render_docs_figures.py --write` after committing new results):\n" + "\n".join(diffs))


def test_every_renderer_is_used_and_states_its_conditions():
    used = {name for page in render.pages() for name, _, _ in render.blocks(page.read_text(encoding="utf-8"))}
    assert used == set(render.RENDERERS), f"renderers without a page: {set(render.RENDERERS) - used}"
    for name, fn in render.RENDERERS.items():
        head = fn(render.RESULTS).splitlines()[0]
        for word in ("Results file `benchmarks/results/", "measured", "commit", "threads", "load"):
            assert word in head, f"{name}: conditions line lacks '{word}': {head}"


def _copy_tree(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    (root / "docs").mkdir(parents=True)
    for page in render.pages():
        shutil.copy(page, root / page.relative_to(ROOT))
    return root


def test_a_changed_figure_on_a_page_fails(tmp_path):
    root = _copy_tree(tmp_path)
    page = root / "docs" / "benchmarks.md"
    text = page.read_text(encoding="utf-8")
    assert "| 37/40 |" in text
    page.write_text(text.replace("| 37/40 |", "| 38/40 |", 1), encoding="utf-8")
    diffs = render.check(root, render.RESULTS)
    assert len(diffs) == 1 and "-| 1 |" in diffs[0] and "38/40" in diffs[0]


def test_a_changed_results_file_fails(tmp_path):
    root = _copy_tree(tmp_path)
    results = tmp_path / "results"
    shutil.copytree(render.RESULTS, results)
    f = results / render.POSEGRAPH_FILE
    d = json.loads(f.read_text(encoding="utf-8"))
    d["results"]["torus3D.g2o"]["minegeo"]["1"]["iterations"] = 198
    f.write_text(json.dumps(d), encoding="utf-8")
    diffs = render.check(root, results)
    assert diffs and all("199" in d_ and "198" in d_ for d_ in diffs)


@pytest.mark.parametrize("bad", ["<!-- figures: nosuch -->\n<!-- /figures -->\n",
                                 "<!-- figures: batch -->\ntext\n",
                                 "<!-- /figures -->\n",
                                 "<!-- figures: batch -->\n<!-- figures: batch -->\n<!-- /figures -->\n"])
def test_a_malformed_block_is_refused(bad):
    with pytest.raises(ValueError):
        render.render_page(bad)
