import json
import subprocess
import sys

import pytest

import minegeo
from minegeo import errors
from minegeo._provenance import StageTimer, to_jsonable, write_json_atomic
from minegeo.cli import main


def test_version_cli(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert minegeo.__version__ in capsys.readouterr().out


def test_error_hierarchy():
    for cls in (errors.InputError, errors.TooFewPointsError, errors.DegenerateGeometryError,
                errors.FileFormatError, errors.CRSError, errors.ConvergenceError):
        assert issubclass(cls, errors.MinegeoError)
    e = errors.FileFormatError("a.ply", "truncated: expected 10 vertices, found 3")
    assert "a.ply" in str(e) and "truncated" in str(e)


def test_show_versions_mentions_numpy():
    assert "numpy" in minegeo.show_versions()


def test_atomic_json_roundtrip(tmp_path):
    import numpy as np

    p = write_json_atomic(tmp_path / "sub" / "r.json", {"a": np.arange(3), "b": np.float64(np.nan)})
    assert json.loads(p.read_text()) == {"a": [0, 1, 2], "b": None}
    assert not [f for f in p.parent.iterdir() if f.name.endswith(".tmp")]
    assert to_jsonable((np.int64(2),)) == [2]


def test_stage_timer():
    t = StageTimer()
    with t("a"):
        pass
    d = t.as_dict()
    assert d["total"] >= d["a"] >= 0


def test_cli_module_entry_point():
    r = subprocess.run([sys.executable, "-m", "minegeo", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and "minegeo" in r.stdout
