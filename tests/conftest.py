"""Shared fixtures. The body model is built once per test session (its first build is slow)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DATAGEN_SHARED", REPO.parent / "shared"))
CMU_DIR = SHARED / "mocap" / "cmu"


@pytest.fixture(scope="session")
def repo_dir() -> Path:
    return REPO


@pytest.fixture(scope="session")
def cmu_dir() -> Path:
    if not CMU_DIR.is_dir():
        pytest.fail(
            f"the shared CMU clips are missing: {CMU_DIR} (CI puts ../shared beside the repo)"
        )
    return CMU_DIR


@pytest.fixture(scope="session")
def body_model():
    from datagen.body.anny_model import default_body_model

    return default_body_model()
