"""The library's errors as the command line says them: each parameter a message names as the
flag that sets it."""

from __future__ import annotations

from gscompress.errors import GscError


def with_flags(exc: GscError) -> str:
    """The message of `exc` with each parameter it names (`exc.options`, written `name`) as
    the flag that sets it (--name)."""
    message = str(exc)
    for name in exc.options:
        message = message.replace(f"`{name}`", "--" + name.replace("_", "-"))
    return message
