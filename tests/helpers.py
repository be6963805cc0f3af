"""Shared test helpers (import as ``from helpers import shared_data, require_oracle``).

Real validation data live in ``../shared/data`` beside the repository (override with
``MINEGEO_SHARED_DATA``). Tests that need it call :func:`shared_data`; when the data are
missing they are skipped with a clear reason, unless ``MINEGEO_REQUIRE_SHARED_DATA=1``
(set by ``.ci/run``), in which case they fail.

Oracle libraries (the ``oracle`` extra: Open3D, small_gicp, kiss-icp) are imported only through
:func:`require_oracle`: missing, a test is skipped with the reason, unless
``MINEGEO_REQUIRE_ORACLE=1`` (set by ``.ci/run``), in which case it fails.

Optional extras of minegeo itself (``las``: laspy, ``e57``: pye57, ``dxf``: ezdxf, ``dask``:
distributed) are imported only through :func:`require_extra`: missing, a test is skipped with the
extra to install, unless ``MINEGEO_REQUIRE_EXTRAS=1`` (set by ``.ci/run``), in which case it fails.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MINEGEO_SHARED_DATA", REPO.parent / "shared" / "data"))
REQUIRE_SHARED = os.environ.get("MINEGEO_REQUIRE_SHARED_DATA", "") == "1"
#: The oracle extra's import names (pyproject ``oracle``: open3d, small-gicp, kiss-icp, gtsam, evo).
ORACLES = ("open3d", "small_gicp", "kiss_icp", "gtsam", "evo")


def oracle_required() -> bool:
    """True when a missing oracle library must fail the test (``MINEGEO_REQUIRE_ORACLE=1``)."""
    return os.environ.get("MINEGEO_REQUIRE_ORACLE", "") == "1"


def shared_data(*parts: str) -> Path:
    """Path inside the shared real-data folder; skip (or fail under CI) when it is missing."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        msg = f"shared real data not found: {p} (set MINEGEO_SHARED_DATA or place ../shared/data)"
        if REQUIRE_SHARED:
            pytest.fail(msg + " and MINEGEO_REQUIRE_SHARED_DATA=1")
        pytest.skip(msg)
    return p


def require_oracle(name: str):
    """Import the oracle library ``name`` (one of :data:`ORACLES`) and return the module; when it
    cannot be imported, skip with the reason, or fail under ``MINEGEO_REQUIRE_ORACLE=1``."""
    import importlib

    if name not in ORACLES:
        raise ValueError(f"{name!r} is not an oracle of the test suite {ORACLES}")
    try:
        return importlib.import_module(name)
    except Exception as exc:  # ImportError, or OSError from a missing system library (libusb for Open3D)
        msg = f"oracle {name} not importable: {type(exc).__name__}: {exc} (pip install -e '.[oracle]'"
        msg += "; Open3D also needs libusb-1.0-0)" if name == "open3d" else ")"
        if oracle_required():
            pytest.fail(msg + " and MINEGEO_REQUIRE_ORACLE=1", pytrace=False)
        pytest.skip(msg)


#: minegeo's optional extras as (import name -> extra of pyproject.toml).
EXTRAS = {"laspy": "las", "pye57": "e57", "ezdxf": "dxf", "distributed": "dask", "dask": "dask", "rosbags": "bag"}


def extras_required() -> bool:
    """True when a missing optional extra must fail the test (``MINEGEO_REQUIRE_EXTRAS=1``)."""
    return os.environ.get("MINEGEO_REQUIRE_EXTRAS", "") == "1"


def require_extra(name: str):
    """Import the optional package ``name`` (a key of :data:`EXTRAS`) and return the module; when it
    cannot be imported, skip naming the extra to install, or fail under ``MINEGEO_REQUIRE_EXTRAS=1``."""
    import importlib

    if name not in EXTRAS:
        raise ValueError(f"{name!r} is not an optional extra of minegeo {tuple(EXTRAS)}")
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        msg = f"the {EXTRAS[name]} extra ({name}) is not installed: {exc} (pip install -e '.[{EXTRAS[name]}]')"
        if extras_required():
            pytest.fail(msg + " and MINEGEO_REQUIRE_EXTRAS=1", pytrace=False)
        pytest.skip(msg, allow_module_level=True)


def require_open3d():
    """``require_oracle("open3d")`` (kept for the oracle tests that call it by this name)."""
    return require_oracle("open3d")


def cli_localize_params(levelled: bool):
    """(PrepareParams, LocalizeParams) exactly as ``minegeo localize --profile fast [--levelled 3]`` builds them."""
    from minegeo.cli import build_parser
    from minegeo.cli.localize import params_from_args

    opts = ["--profile", "fast"] + (["--levelled", "3"] if levelled else [])
    args = build_parser(["localize"]).parse_args(["localize", "--map", "m", "--scan", "s", "--out", "o", *opts])
    return params_from_args(args)


def load_script(relpath: str, name: str):
    """The script ``REPO/relpath`` (a benchmark or a docs tool, not a package module) imported as the
    module ``name`` (registered in ``sys.modules``, as dataclasses need)."""
    spec = importlib.util.spec_from_file_location(name, REPO / relpath)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
