"""Shared pytest fixtures; helper functions live in ``tests/helpers.py``.

Hypothesis: under CI (``CI`` set, as ``.ci/run`` runs) every property test is derandomized
(the examples are a fixed function of the test), so a bound set from observed data cannot make
CI red by chance; locally the default profile explores new examples on every run. Choose a
profile explicitly with ``HYPOTHESIS_PROFILE=ci|dev``.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True, deadline=None, print_blob=True)
settings.register_profile("dev", deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE") or ("ci" if os.environ.get("CI") else "dev"))


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
