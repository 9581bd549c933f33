"""Shared fixtures. Tests run float32 by default (the library default); tests that need float64 use
the ``x64`` fixture, which switches it on for that test only."""

from __future__ import annotations

import os
import pathlib

import jax
import numpy as np
import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
SHARED_DATA = pathlib.Path(os.environ.get("MBAVO_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def shared_dataset(name: str) -> pathlib.Path:
    """Path of a real clip in ../shared/data. Fails loudly (never skips) when it is missing."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.fail(f"shared test data missing: {path} (set MBAVO_SHARED_DATA or provide ../shared/data)")
    return path
