"""First use (issue 28): a verb that compiles Numba kernels says so before the wait and gives the compile
seconds apart after it (never with ``-q``), and ``minegeo warmup`` shows its progress per subpackage.

Each compiling run is its own process with an empty ``NUMBA_CACHE_DIR`` (Numba's user-provided cache
folder comes before the checkout's ``__pycache__``), i.e. a fresh install; ``minegeo evaluate`` on two
short trajectories is the verb (its kernels: the text reader, moments and Umeyama, ~10 s cold).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
NOTICE = re.compile(r"^minegeo evaluate: compiling numerical kernels for first use \(once[^)]*\) \.\.\.$", re.M)
LINE = re.compile(r"^minegeo evaluate: (\d+\.\d) s of this run was one-time Numba compilation "
                  r"\(cached for later runs\)$", re.M)


def _tum(path: Path, xyz: np.ndarray) -> None:
    """Poses at 10 Hz with the identity rotation (TUM: t x y z qx qy qz qw)."""
    path.write_text("".join(f"{0.1 * i:.3f} {x:.6f} {y:.6f} {z:.6f} 0 0 0 1\n" for i, (x, y, z) in enumerate(xyz)))


def _minegeo(argv: list[str], cwd: Path, cache: Path | None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_NUM_THREADS": "1"}
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return subprocess.run([sys.executable, "-m", "minegeo", *argv], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


@pytest.fixture(scope="module")
def trajectories(tmp_path_factory):
    d = tmp_path_factory.mktemp("first_use")
    rng = np.random.default_rng(0)
    gt = np.c_[np.arange(20) * 0.5, np.sin(np.arange(20) * 0.3), np.zeros(20)]
    _tum(d / "gt.tum", gt)
    _tum(d / "est.tum", gt + 0.01 * rng.standard_normal(gt.shape))
    return d


@pytest.fixture(scope="module")
def cold(trajectories):
    """The same evaluate, once without and once with -q, each on its own empty Numba cache."""
    d = trajectories
    runs = {}
    for name, quiet in (("loud", []), ("quiet", ["-q"])):
        (d / f"cache_{name}").mkdir()
        runs[name] = _minegeo([*quiet, "evaluate", "--est", "est.tum", "--gt", "gt.tum", "--out", f"out_{name}"],
                              d, d / f"cache_{name}")
    return runs


def test_a_cold_run_announces_compilation_and_states_its_seconds(cold, trajectories):
    r = cold["loud"]
    assert r.returncode == 0, r.stderr
    assert len(NOTICE.findall(r.stderr)) == 1, r.stderr          # once, before the wait
    m = LINE.findall(r.stderr)
    assert len(m) == 1, r.stderr
    assert NOTICE.search(r.stderr).start() < LINE.search(r.stderr).start()
    import json

    rec = json.loads((trajectories / "out_loud" / "result.json").read_text())
    # the seconds printed are the run's own compile time, as result.json states it (to the 0.1 s shown)
    assert float(m[0]) == pytest.approx(rec["timings_s"]["compile_s"], abs=0.051)
    assert float(m[0]) >= 0.5
    assert any(Path(p).suffix == ".nbi" for p in os.listdir(next((trajectories / "cache_loud").iterdir())))


def test_quiet_cold_run_says_nothing_about_compilation(cold):
    r = cold["quiet"]
    assert r.returncode == 0, r.stderr
    assert not NOTICE.search(r.stderr) and not LINE.search(r.stderr), r.stderr
    assert "compil" not in r.stderr


def test_a_warm_run_says_nothing_about_compilation(cold, trajectories):
    """The loud run's cache is now filled: the same command compiles nothing and says nothing of it."""
    r = _minegeo(["evaluate", "--est", "est.tum", "--gt", "gt.tum", "--out", "out_warm"], trajectories,
                 trajectories / "cache_loud")
    assert r.returncode == 0, r.stderr
    assert "compil" not in r.stderr, r.stderr


def test_warmup_shows_progress_per_module(tmp_path):
    """``minegeo warmup --module`` of two subpackages: a start line on stderr and a done line with its
    seconds on stdout per subpackage, counted 1/2, 2/2, in the order asked, then the total."""
    r = _minegeo(["warmup", "--module", "minegeo.survey", "--module", "minegeo.io"], tmp_path, None)
    assert r.returncode == 0, r.stderr
    assert re.findall(r"^\[(\d)/(\d)\] (\S+) \.\.\.$", r.stderr, re.M) == [("1", "2", "minegeo.survey"),
                                                                          ("2", "2", "minegeo.io")], r.stderr
    done = re.findall(r"^\[(\d)/(\d)\] (\S+) +(\d+\.\d\d) s$", r.stdout, re.M)
    assert [d[:3] for d in done] == [("1", "2", "minegeo.survey"), ("2", "2", "minegeo.io")], r.stdout
    total = re.findall(r"^ +total +(\d+\.\d\d) s$", r.stdout, re.M)
    assert len(total) == 1
    assert float(total[0]) == pytest.approx(sum(float(d[3]) for d in done), abs=0.011)


def test_warmup_progress_callback_order():
    """``minegeo.warmup(progress=...)``: start then done per subpackage, i counting 1..n."""
    import minegeo

    calls = []
    times = minegeo.warmup(modules=["minegeo.survey", "minegeo.io"], progress=lambda *a: calls.append(a))
    assert [(c[0], c[1], c[2], c[3] is None) for c in calls] == [
        ("minegeo.survey", 1, 2, True), ("minegeo.survey", 1, 2, False),
        ("minegeo.io", 2, 2, True), ("minegeo.io", 2, 2, False)]
    assert [c[3] for c in calls if c[3] is not None] == [times["minegeo.survey"], times["minegeo.io"]]
