"""LSQ engine vs. the naive textbook twin; determinism of ``minegeo adjust``."""

from __future__ import annotations

import json

import numpy as np
from helpers import shared_data
from hypothesis import given, settings
from hypothesis import strategies as st
from reference.naive_lsq import naive_gauss_markov

from minegeo.cli import main
from minegeo.survey import adjust_linear


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 100_000), st.integers(4, 12), st.integers(1, 3), st.booleans())
def test_linear_adjustment_matches_naive_twin(seed, n, u, correlated):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, u))
    l = A @ rng.normal(size=u) + rng.normal(scale=0.1, size=n)
    if correlated:
        L = rng.normal(size=(n, n)) * 0.1 + np.eye(n)
        W = np.linalg.inv(L @ L.T)
        W = 0.5 * (W + W.T)
    else:
        W = rng.uniform(0.5, 5.0, n)
    x, v, s02, Qxx, _Qvv, red, w = naive_gauss_markov(A, l, W)
    r = adjust_linear(A, l, W)
    np.testing.assert_allclose(r.x, x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r.v, v, rtol=1e-8, atol=1e-11)
    np.testing.assert_allclose(r.sigma0_sq, s02, rtol=1e-9)
    np.testing.assert_allclose(r.Qxx, Qxx, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(r.redundancy, red, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(r.w, w, rtol=1e-6, atol=1e-9)
    assert abs(r.redundancy.sum() - (n - u)) < 1e-8


def test_adjust_is_bit_identical_between_runs(tmp_path):
    dat = shared_data("krumm_gama_adjustment_examples", "2D", "Wolf_DistanceDirectionAngle_free.dat")
    outs = []
    for k in range(2):
        assert main(["adjust", str(dat), "--out", str(tmp_path / f"r{k}")]) == 0
        d = json.loads((tmp_path / f"r{k}" / "result.json").read_text(encoding="utf-8"))
        d.pop("provenance")
        d["parameters"].pop("timings_s")
        outs.append(json.dumps(d, sort_keys=True))
    assert outs[0] == outs[1]
    assert (tmp_path / "r0" / "report.txt").read_bytes() == (tmp_path / "r1" / "report.txt").read_bytes()
