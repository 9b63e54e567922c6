"""The one exception family of gscompress.

Anything raised as a `GscError` is an expected failure caused by the input or the environment:
the CLI prints its message on one line and exits non-zero. Any other exception is a bug.
"""

import reprlib


class GscError(Exception):
    """Base class of every expected gscompress failure.

    Attributes:
        options: the parameters the message names, each written as `name` (in backquotes), so
            that the message speaks of the library's parameters and the CLI can show each as
            its flag (`--name`).
    """

    def __init__(self, *args: object, options: tuple[str, ...] = ()) -> None:
        super().__init__(*args)
        self.options = options


class InputError(GscError):
    """A bad argument or option value (a ratio outside (0, 1], an unknown strategy, ...)."""


class OptionError(InputError):
    """Options that do not go together, or an option's value outside what it takes: the CLI
    reports it as a usage error (exit code 2), as click does for the options it checks."""


class OutputError(GscError):
    """An output path that may not be written (exists, equals an input, ...)."""


class MapError(GscError):
    """A Gaussian map that is inconsistent (shapes, non-finite values, duplicate ids)."""


class LogFormatError(GscError):
    """An MCAP file that is not a valid gscompress log."""


class PlyFormatError(GscError):
    """A PLY file that is not a readable 3DGS map."""


class SpzFormatError(GscError):
    """An SPZ file that is not a readable 3DGS map."""


class SogFormatError(GscError):
    """A SOG bundle that is not a readable 3DGS map."""


class DatasetError(GscError):
    """An RGB-D sequence that cannot be opened or read."""


class BudgetError(GscError):
    """A selection budget that cannot be met."""


class DivergenceError(GscError):
    """An optimisation (tracking, mapping, a refinement) whose loss or parameters stopped being
    finite: its learning rates are too high for the data. The message reads "`what` diverged
    (`detail`): `advice`"; `detail` says what was not finite, `options` the parameters `advice`
    names (as `GscError`'s)."""

    def __init__(self, what: str, detail: str, advice: str, options: tuple[str, ...] = ()) -> None:
        super().__init__(f"{what} diverged ({detail}): {advice}", options=options)
        self.detail = detail


class TrackingLostError(GscError):
    """A frame whose track was lost and that no re-localisation guess recovered.

    Attributes:
        frame: the frame's index in the sequence.
        timestamp: its stamp, seconds.
        reason: why the track was judged lost.
    """

    def __init__(self, frame: int, timestamp: float, reason: str, advice: str = "") -> None:
        super().__init__(
            f"tracking lost at frame {frame} (stamp {timestamp:.3f} s): {reason}, and no "
            f"re-localisation guess recovered it{'; ' if advice else ''}{advice}"
        )
        self.frame, self.timestamp, self.reason = frame, timestamp, reason


class MissingDependencyError(GscError):
    """An optional dependency that the requested feature needs is not installed."""


def led_by(source: str, message: str) -> str:
    """`message` beginning with the file it is about, `source` (unless it already does)."""
    return message if message.startswith(source) else f"{source}: {message}"


def clipped(value: object, limit: int = 40) -> str:
    """A short repr of `value` for a message: strings cut to about `limit` characters, nested
    lists and mappings to a few items (a value a user typed can be megabytes long, and a YAML
    alias can stand for a nested list of billions of items)."""
    shorter = reprlib.Repr()
    shorter.maxlevel, shorter.maxlist, shorter.maxdict = 2, 4, 4
    shorter.maxstring = shorter.maxother = limit
    try:
        return shorter.repr(value)
    except ValueError:  # (an int over 4300 digits)
        return "a number too long to show"
