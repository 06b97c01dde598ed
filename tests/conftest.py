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


def in_ieee_process(request: pytest.FixtureRequest) -> bool:
    """Run the calling test again in a pytest process of its own whose kernels compile without
    fast math (DATAGEN_TI_IEEE=1, datagen/sim/backend.py), and return True there once it passed;
    return False inside that process, where the test runs its body. A test that two code paths
    compute the same operations asserts it bit for bit there: with fast math, where LLVM fuses
    a multiply and an add depends on the whole kernel, so the one-launch frame kernel and the
    per-effect kernels part by a few float32 steps (datagen/sim/backend.py)."""
    import subprocess
    import sys

    from datagen.sim import backend

    if backend.ieee():
        return False
    env = dict(os.environ, **{backend.IEEE_ENV: "1"})
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
         request.node.nodeid],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=900,
    )
    assert done.returncode == 0, (done.stdout + done.stderr)[-4000:]
    return True
