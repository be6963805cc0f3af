"""Krumm text format details and the JSON equivalent (datum kinds, units, errors)."""

from __future__ import annotations

import math

import pytest
from helpers import shared_data

from minegeo.errors import FileFormatError, InputError
from minegeo.survey import adjust_network, network_from_dict, parse_krumm, read_network


def _traverse_json(datum):
    return {
        "points": {
            "B": {"x": 8478.139, "y": 2483.826},
            "C": {"x": 8231.2898089314, "y": 2347.83058429498},
            "D": {"x": 7982.4553931562, "y": 2239.73283443029},
            "E": {"x": 7709.336, "y": 2263.411},
        },
        "datum": datum,
        "known_azimuths": [
            {"from": "B", "to": "A", "value_dms": "68°15'20.7\""},
            {"from": "E", "to": "F", "value_dms": "300°11'30.5\""},
        ],
        "observations": [
            {"type": "distance", "from": "B", "to": "C", "value_m": 281.832, "sigma_m": 0.016},
            {"type": "distance", "from": "C", "to": "D", "value_m": 271.300, "sigma_m": 0.016},
            {"type": "distance", "from": "D", "to": "E", "value_m": 274.100, "sigma_m": 0.016},
            {
                "type": "angle",
                "at": "C",
                "from": "B",
                "to": "D",
                "value_dms": "185°22'14\"",
                "sigma_arcsec": 10,
            },
            {
                "type": "angle",
                "at": "D",
                "from": "C",
                "to": "E",
                "value_dms": "208°26'19\"",
                "sigma_arcsec": 10,
            },
            {
                "type": "angle",
                "at": "B",
                "from": "A",
                "to": "C",
                "value_dms": "172°53'34\"",
                "sigma_arcsec": 10,
            },
            {
                "type": "angle",
                "at": "E",
                "from": "D",
                "to": "F",
                "value_dms": "205°13'51\"",
                "sigma_arcsec": 10,
            },
        ],
    }


@pytest.mark.parametrize(
    "name, datum",
    [
        ("Krumm_Traverse1", {"type": "fix", "coordinates": ["B", "E"]}),
        ("Krumm_Traverse2", {"type": "dyn", "sigma_m": {"xB": 0.01, "yB": 0.01, "xE": 0.01, "yE": 0.01}}),
        ("Krumm_Traverse3", {"type": "free", "coordinates": []}),
    ],
)
def test_json_datum_kinds_match_text_files(name, datum):
    base = shared_data("krumm_gama_adjustment_examples")
    ref = adjust_network(read_network(base / "2D" / f"{name}.dat"))
    res = adjust_network(network_from_dict(_traverse_json(datum)))
    for pid in ("C", "D"):
        a, b = ref.points[pid], res.points[pid]
        assert abs(a.x - b.x) < 1e-9 and abs(a.y - b.y) < 1e-9
        assert abs(a.sx_m - b.sx_m) < 1e-12 and abs(a.sy_m - b.sy_m) < 1e-12
    assert ref.dof == res.dof


def test_sigma_inheritance_units_and_comments():
    net = parse_krumm(
        """
[Coordinates]
A 0 0        % comment
B 100 0
Six#Mile 50 80   # gama-style trailing comment
[Datum]
fix A B
[Angles,dms,s]
A B Six#Mile 302°00'00" 3"
B Six#Mile A 58°00'00"
[Distances]
A Six#Mile 94.340 0.002 0.0001
B Six#Mile 94.340
"""
    )
    ang = [o for o in net.observations if o.kind == "angle"]
    assert math.isclose(ang[1].sigma, ang[0].sigma) and math.isclose(ang[0].sigma * 206264.80624709636, 3.0)
    d = [o for o in net.observations if o.kind == "distance"]
    assert math.isclose(d[0].sigma, math.sqrt(0.002**2 + 94.34 * 0.0001**2))
    assert math.isclose(d[1].sigma, d[0].sigma)
    assert "Six#Mile" in net.points


def test_format_errors_name_the_line():
    with pytest.raises(FileFormatError, match="line 7: no standard deviation"):
        parse_krumm("[Coordinates]\nA 0 0\nB 1 1\n[Datum]\nfix A\n[Distances]\nA B 1.4\n")
    with pytest.raises(FileFormatError, match="Datum"):
        parse_krumm("[Coordinates]\nA 0 0\nB 1 1\n[Datum]\nfix Q\n[Distances]\nA B 1.4 0.01\n")
    with pytest.raises(FileFormatError, match="no \\[Datum\\]"):
        parse_krumm("[Coordinates]\nA 0 0\nB 1 1\n[Distances]\nA B 1.4 0.01\n")
    with pytest.raises(InputError, match="no \\(approximate\\) coordinates"):
        adjust_network(
            parse_krumm("[Coordinates]\nA 0 0\nB 1 1\n[Datum]\nfix A\n[Distances]\nA C 1.4 0.01\nA B 1.4\n")
        )
    with pytest.raises(FileFormatError, match="unknown section"):
        parse_krumm("[Coordinates]\nA 0 0\n[Datum]\nfix A\n[Foo]\n1\n")
