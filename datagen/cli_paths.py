"""The CLI's output file names, checked as click callbacks while the command line is parsed:
a name that would fail at the end (a preview format nothing writes) or be written where no
reader looks (a shard a dataset folder's reader skips) is refused before a body or a
simulation has been computed."""

from __future__ import annotations

from pathlib import Path

import click


def shard_path(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    from datagen.io.shard import SHARD_SUFFIX

    if value is not None and Path(value).suffix != SHARD_SUFFIX:
        raise click.BadParameter(
            f"expected a shard file name ending in {SHARD_SUFFIX} (the reader and `datagen "
            f"validate` take a folder's *{SHARD_SUFFIX} files), got {value!r}")
    return value


def preview_path(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    from datagen.render import PREVIEW_SUFFIXES

    if value is not None and Path(value).suffix.lower() not in PREVIEW_SUFFIXES:
        raise click.BadParameter(
            f"expected a .gif (animated) or .png (four frames) file name, got {value!r}")
    return value
