"""Errors that the CLI turns into one line and a non-zero exit.

Every user-facing failure says which file, which field, and what was expected, so a user can fix
their input without reading a traceback.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path


class DatagenError(Exception):
    """Base class of the errors the CLI reports without a traceback."""


class InputError(DatagenError):
    """Bad user input: a file, the field in it that is wrong, and what was expected."""

    def __init__(
        self,
        source: str | Path | None,
        field: str | None,
        expected: str,
        got: object = None,
    ) -> None:
        self.source = str(source) if source is not None else None
        self.field = field
        self.expected = expected
        self.got = got
        parts = []
        if self.source:
            parts.append(self.source)
        if field:
            parts.append(f"field '{field}'")
        where = ": ".join(parts)
        message = f"expected {expected}"
        if got is not None:
            shown = repr(got)
            if len(shown) > 80:
                shown = shown[:77] + "..."
            message += f", got {shown}"
        super().__init__(f"{where}: {message}" if where else message)

    def __reduce__(self):
        # Raised in a worker process, it must cross back to the parent whole (pickle calls the
        # constructor with self.args, which holds only the message).
        return (InputError, (self.source, self.field, self.expected, self.got))


class RejectedSequence(DatagenError):
    """A sequence that cannot be made valid (an arm through the torso): recorded, not written."""

    def __init__(self, stage: str, reason: str, frames: tuple[int, int] | None = None,
                 runs: int = 1) -> None:
        self.stage = stage
        self.reason = reason
        self.frames = frames
        self.runs = runs  # simulations tried before giving up (the escalation ladder's rungs)
        where = f" (frames {frames[0]}-{frames[1]})" if frames else ""
        super().__init__(f"rejected at {stage}: {reason}{where}")

    def __reduce__(self):
        return (RejectedSequence, (self.stage, self.reason, self.frames, self.runs))


class StoppedRun(RejectedSequence):
    """A run the simulator stopped at the first output frame that the dataset's gate rejects
    (its guards, SimOptions.neckline_guard and bound_guard): stage "qa". Each guard raises a
    type of its own, which the escalation ladder treats in its own way (pipeline.stages)."""

    def __init__(self, reason: str, frames: tuple[int, int] | None = None,
                 runs: int = 1) -> None:
        super().__init__("qa", reason, frames, runs)

    def __reduce__(self):
        return (type(self), (self.reason, self.frames, self.runs))


class SlidOffShoulders(StoppedRun):
    """A run stopped where a garment's neckline had slid off the shoulders (the neckline
    guard). The ladder treats it apart from the bounds that the next rung past the top preset
    can still resolve."""


class BoundBroken(StoppedRun):
    """A run stopped at the first output frame whose QA broke a bound (qa.breaches; the bound
    guard). The ladder simulates it again at finer steps, as it does a finished run over a
    bound."""


def user_errors(func):
    """A CLI command that prints a DatagenError as one line and exits 2, without a traceback."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except DatagenError as exc:
            import click

            click.echo(f"error: {exc}", err=True)
            sys.exit(2)

    return wrapper
