"""Shared pytest fixtures; helper functions live in ``tests/helpers.py``."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
