"""A disk cache of study trajectories.

Converged references (float64 implicit runs at small steps) and Blender's converged runs take
minutes each; the study and the simulator benchmark both need them, and rerunning either should
not pay for them again. An entry is keyed by what it was run with and by a digest of the source
files that decide its result (the simulator, the study scenes, the Blender script), so any
change to those makes the old entries unreachable instead of wrong.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

PACKAGE = Path(__file__).resolve().parents[1]
SOURCES = ("sim", "study/scenes.py", "study/blender.py", "study/blender_scene.py", "types.py")


def cache_dir() -> Path:
    root = os.environ.get("DATAGEN_CACHE_DIR") or Path.home() / ".cache" / "datagen"
    return Path(root) / "study"


def source_digest() -> str:
    h = hashlib.sha256()
    for name in SOURCES:
        path = PACKAGE / name
        files = sorted(path.rglob("*.py")) if path.is_dir() else [path]
        for f in files:
            h.update(str(f.relative_to(PACKAGE)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def cached(key: dict, compute: Callable[[], dict[str, np.ndarray]],
           use_cache: bool = True, by_source: bool = True) -> dict[str, np.ndarray]:
    """The arrays `compute()` returns for `key`, from the cache when an entry exists.
    `by_source=False` leaves the source digest out of the key: the caller's key then names
    what the result depends on (a behavioural digest, study.fingerprint)."""
    text = json.dumps({**key, "source": source_digest()} if by_source else key, sort_keys=True)
    name = hashlib.sha256(text.encode()).hexdigest()[:24]
    path = cache_dir() / f"{name}.npz"
    if use_cache and path.exists():
        with np.load(path) as d:
            return {k: d[k] for k in d.files}
    arrays = compute()
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
        path.with_suffix(".json").write_text(text)
    return arrays
