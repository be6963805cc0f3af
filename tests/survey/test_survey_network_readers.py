"""The network file formats live in :mod:`minegeo.io`, the adjustment in :mod:`minegeo.survey`.

The readers (Krumm text, JSON, ``.adj``) import nothing from :mod:`minegeo.survey` (which imports
them), the public names of :mod:`minegeo.survey` are the readers' own objects, and the two
formats give the same network for the same content.
"""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

import minegeo.io.network_types as types
import minegeo.survey as survey
import minegeo.survey.network as model
from minegeo.errors import InputError
from minegeo.io.network import read_network
from minegeo.io.network_json import network_from_dict
from minegeo.io.network_krumm import parse_krumm
from minegeo.survey.restrictions import compile_restriction


def test_readers_load_without_the_survey_package():
    code = ("import sys, minegeo.io.network, minegeo.io.adj; "
            "print(sorted(m for m in sys.modules if m.split('.')[:2] == ['minegeo', 'survey']))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_survey_exports_the_io_readers_and_records():
    assert survey.parse_krumm is parse_krumm
    assert survey.network_from_dict is network_from_dict
    assert survey.read_network is read_network
    for name in ("Network", "Observation", "Datum"):
        assert getattr(survey, name) is getattr(types, name) is getattr(model, name)


KRUMM = """[Coordinates]
A 1000 2000
B 1100 2000
C 1050 2080
[Datum]
fix A B
[Distances]
A C 94.340 0.005
B C 94.340
[Angles,dms,s]
C A B 295°59'21" 5
"""

JSON = {
    "points": {"A": {"x": 1000, "y": 2000}, "B": {"x": 1100, "y": 2000}, "C": {"x": 1050, "y": 2080}},
    "datum": {"type": "fix", "coordinates": ["A", "B"]},
    "observations": [
        {"type": "distance", "from": "A", "to": "C", "value_m": 94.340, "sigma_m": 0.005},
        {"type": "distance", "from": "B", "to": "C", "value_m": 94.340, "sigma_m": 0.005},
        {"type": "angle", "at": "C", "from": "A", "to": "B", "value_dms": "295°59'21\"", "sigma_arcsec": 5},
    ],
}


def test_krumm_and_json_give_the_same_network():
    a, b = parse_krumm(KRUMM), network_from_dict(JSON)
    assert a.dim == b.dim == 2
    assert a.points == b.points
    assert a.datum == b.datum
    assert [(o.kind, o.station, o.target, o.backsight) for o in a.observations] == \
        [(o.kind, o.station, o.target, o.backsight) for o in b.observations]
    for oa, ob in zip(a.observations, b.observations, strict=True):
        assert math.isclose(oa.value, ob.value, rel_tol=0, abs_tol=1e-15)
        assert math.isclose(oa.sigma, ob.sigma, rel_tol=1e-15)
    ra, rb = survey.adjust_network(a), survey.adjust_network(b)
    assert ra.points["C"].x == pytest.approx(rb.points["C"].x, abs=1e-12)


def test_restriction_compiler_refuses_anything_but_arithmetic():
    code, syms = compile_restriction("(xB - xA)^2 - 4", {"A", "B"})
    assert sorted(syms.values()) == [("A", "x"), ("B", "x")]
    assert eval(code, {"__builtins__": {}}, {"_v0": 3.0, "_v1": 1.0}) == 0.0  # noqa: S307
    with pytest.raises(InputError, match="unknown symbol"):
        compile_restriction("xQ - 1", {"A"})
    with pytest.raises(InputError, match="only numbers"):
        compile_restriction("xA < 1", {"A"})
