"""Who hears how far a simulation has got. `datagen simulate` shows a bar over the frames of
each run (an escalated sequence starts a new one); a dataset run counts sequences instead, and
a simulation nobody listens to reports to no one."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

# (frames done, frames in the run, the run's settings in words: "xpbd default 20x4, sor 1.6")
FrameListener = Callable[[int, int, str], None]

_listener: ContextVar[FrameListener | None] = ContextVar("frame_listener", default=None)


@contextmanager
def frame_progress(listener: FrameListener) -> Iterator[None]:
    """Tell `listener` after every frame of every simulation run within the block (the settle
    frames on the rest pose count too)."""
    token = _listener.set(listener)
    try:
        yield
    finally:
        _listener.reset(token)


def report_frame(done: int, total: int, settings: str) -> None:
    listener = _listener.get()
    if listener is not None:
        listener(done, total, settings)
