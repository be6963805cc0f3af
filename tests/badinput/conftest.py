"""Small inputs for the bad-input modules: one synthetic mine per session, copied per module.

Each module gets its own copy (``mine``), so an input damaged by a bug in one test cannot
change what another module reads; every test checks its inputs are unchanged anyway.
"""

from __future__ import annotations

import shutil

import pytest

SEED = 7

#: Ghilani (2010) Ex. 15.5 resection (angles in gon), as in tests/test_cli_contracts.py
GHILANI = (
    "[Coordinates]\nP 1303.599 1458.615\nQ 1636.436 1310.468\nR 1503.395 888.362\n"
    "S 1506.262 785.061\nU 1000.030 999.960\n[Datum]\nfix xP yP xQ yQ xR yR xS yS\n"
    "[Angles]\nU P Q 33.8805555555556 0.00154320987654321\n"
    "U Q R 42.7873456790123 0.00185185185185185\nU R S 11.6657407407407 0.00185185185185185\n"
)


@pytest.fixture(scope="session")
def _world_src(tmp_path_factory):
    from minegeo.synth import write_world

    d = tmp_path_factory.mktemp("world_src")
    write_world(d, "small", SEED)
    return d


@pytest.fixture(scope="module")
def mine(_world_src, tmp_path_factory):
    """A private copy of the small synthetic mine (map.ply, scans/, trajectories/, gcps.csv, truth.json)."""
    d = tmp_path_factory.mktemp("mine") / "mine"
    shutil.copytree(_world_src, d)
    return d


@pytest.fixture(scope="module")
def mast_scene(tmp_path_factory):
    from minegeo.mast.scenario import write_mast_scenario

    d = tmp_path_factory.mktemp("mast") / "scene"
    return write_mast_scenario(d, seed=SEED)


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    p = tmp_path_factory.mktemp("net") / "ghilani15_5.dat"
    p.write_text(GHILANI, encoding="utf-8")
    return p


@pytest.fixture(scope="module")
def geo_map(mine, tmp_path_factory):
    """``minegeo georef`` output of the module's mine: geo/map_geo.ply + sidecar (report in rep/)."""
    from minegeo.cli import main

    d = tmp_path_factory.mktemp("georef")
    out = d / "geo" / "map_geo.ply"
    assert main(["-q", "georef", "--map", str(mine / "map.ply"), "--gcps", str(mine / "gcps.csv"),
                 "--out", str(out), "--report", str(d / "rep")]) == 0
    return out
