"""The `gsc` click group.

Commands are loaded lazily from their own modules, so that `gsc info` never pays for importing
torch or the SLAM code. Options that do not go together (`OptionError`) are a usage error,
exit code 2; any other `GscError`, an error of the file system (`OSError`: no space, no
permission) or running out of memory is a one-line message and exit code 1; anything else is a
bug and keeps its traceback.
"""

from __future__ import annotations

import importlib
import logging
import os
import re
import sys
from pathlib import Path
from typing import Any

import click

from gscompress import __version__
from gscompress.errors import GscError, OptionError
from gscompress.interrupts import interrupted, sigterm_interrupts
from gscompress.io.files import safe_text
from gscompress.threads import use_threads

from .flags import with_flags

# command name -> "module:function" inside this package
COMMANDS: dict[str, str] = {
    "import-ply": "import_ply:import_ply",
    "info": "info:info",
    "prune": "prune:prune",
    "share": "share:share",
    "export-ply": "export_ply:export_ply",
    "export-traj": "export_traj:export_traj",
    "score": "score:score",
    "synth": "synth:synth",
    "convert": "convert:convert",
    "slam": "slam:slam",
    "eval": "eval:eval_command",
    "render": "render:render",
    "merge": "merge:merge",
    "align": "align:align",
    "experiment": "experiment:experiment",
    "view": "view:view",
}


class OneLineUsageError(click.UsageError):
    """A usage error shown as one line (exit code 2), naming where to find help: the help of
    `command_path`, by default that of the context's command."""

    def __init__(
        self, message: str, ctx: click.Context | None = None, command_path: str | None = None
    ):
        super().__init__(message, ctx)
        self.command_path = command_path or (ctx.command_path if ctx is not None else None)

    def show(self, file: Any = None) -> None:
        hint = f" (see '{self.command_path} --help')" if self.command_path else ""
        click.echo(f"Error: {self.format_message()}{hint}", file=file, err=True)


def one_line(exc: click.UsageError) -> click.UsageError:
    """`exc` as a one-line usage error; a bare `gsc` still prints its help. A group option
    given after the command says where it goes."""
    shown_as_is = (OneLineUsageError, getattr(click.exceptions, "NoArgsIsHelpError", ()))
    if isinstance(exc, shown_as_is):  # (NoArgsIsHelpError: click >= 8.2)
        return exc
    message = re.sub(  # (click echoes a value as typed, and a number can be 5000 digits long)
        r"[0-9]{41,}",
        lambda m: f"{m[0][:18]}...{m[0][-18:]} ({len(m[0])} digits)",
        exc.format_message(),
    )
    if isinstance(exc, click.NoSuchOption) and exc.ctx is not None and exc.ctx.parent is not None:
        group = exc.ctx.parent
        for option in group.command.params:
            if isinstance(option, click.Option) and exc.option_name in option.opts:
                metavar = option.metavar or str(option.name).upper()
                value = "" if option.is_flag or option.count else f" {metavar}"
                message = message.rstrip(".") + (
                    f": {exc.option_name} is an option of {group.command_path} itself, given "
                    f"before the command: {group.command_path} {exc.option_name}{value} "
                    f"{exc.ctx.info_name} ..."
                )
    return OneLineUsageError(message, exc.ctx)


class GscGroup(click.Group):
    """A group that imports each command on first use, reports GscError and usage errors on one
    line, and ends on Ctrl-C or SIGTERM with exit code 130 (temporary outputs removed)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = COMMANDS.get(cmd_name)
        if target is None:
            return None
        module_name, attr = target.split(":")
        module = importlib.import_module(f"{__package__}.{module_name}")
        command: click.Command = getattr(module, attr)
        return command

    def make_context(self, *args: Any, **kwargs: Any) -> click.Context:
        try:
            return super().make_context(*args, **kwargs)
        except click.UsageError as exc:
            raise one_line(exc) from None

    def invoke(self, ctx: click.Context) -> Any:
        try:
            with sigterm_interrupts():
                return self._invoke_reporting(ctx)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM; slam and experiment say more themselves
            pass
        except Exception:  # the SIGTERM's interrupt surfacing from inside a library
            if not interrupted():
                raise
        click.echo("Interrupted: outputs are only written once complete", err=True)
        raise SystemExit(130) from None

    def _invoke_reporting(self, ctx: click.Context) -> Any:
        """The command, its errors reported on one line."""
        try:
            return super().invoke(ctx)
        except OptionError as exc:  # options that do not go together: a usage error, as click's
            command = f"{ctx.command_path} {ctx.invoked_subcommand}"
            raise OneLineUsageError(" ".join(with_flags(exc).split()), ctx, command) from None
        except GscError as exc:
            message = safe_text(" ".join(with_flags(exc).split()))
            raise click.ClickException(message) from None
        except click.UsageError as exc:
            raise one_line(exc) from None
        except OSError as exc:  # the file system said no: a full disk, a read-only folder...
            if exc.errno is None:  # (io.UnsupportedOperation and the like: a bug)
                raise
            raise click.ClickException(os_error_message(exc)) from None
        except MemoryError:
            raise click.ClickException(OUT_OF_MEMORY) from None
        except RuntimeError as exc:  # torch's CPU and CUDA allocators say it so
            if "can't allocate memory" not in str(exc) and "out of memory" not in str(exc):
                raise
            raise click.ClickException(OUT_OF_MEMORY) from None


OUT_OF_MEMORY = "out of memory (smaller images, fewer frames or a smaller map need less)"


def os_error_message(exc: OSError) -> str:
    """One line for an error of the file system, naming the file the user asked for rather
    than the temporary one it was being written under (`.NAME.PID.tmp`, `.NAME.PID.XXXXXXXX.tmp`,
    `.NAME.XXXX.tmp`)."""
    reason = " ".join((exc.strerror or str(exc)).split())
    if exc.filename is None:
        return reason
    path = Path(os.fsdecode(exc.filename))
    temporary = re.fullmatch(r"\.(.+?)\.(?:\d+(?:\.[0-9a-f]{8})?|\w+)\.tmp", path.name)
    return f"{path.with_name(temporary[1]) if temporary else path}: {reason}"


@click.group(cls=GscGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="gsc")
@click.option(
    "-v",
    "--verbose",
    count=True,
    help="More log output: -v adds each SLAM frame's stats, -vv the libraries' debug output.",
)
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")
@click.option(
    "--threads",
    type=click.IntRange(min=1),
    default=None,
    metavar="N",
    help="CPU threads for torch and for synth's frame writers (default: one per core). Give "
    "each job 1 when several run at "
    "once: threads that outnumber the cores wait on each other, and each job runs several "
    "times slower.",
)
def cli(verbose: int, quiet: bool, threads: int | None) -> None:
    """gsc: compact 3D Gaussian Splatting maps and bandwidth-aware map sharing.

    \b
    Typical flow:
      gsc synth -o SEQ --frames 60        a synthetic RGB-D sequence to try it on
      gsc info REC                        a robot's recording (ROS 1/2 bag, MCAP): its topics
      gsc slam SEQ -o a.mcap              map a sequence, score every Gaussian (PWAS)
      gsc eval a.mcap --seq SEQ           ATE, PSNR, SSIM, LPIPS of the map
      gsc prune a.mcap --keep 0.3 -o p.mcap   keep the most important 30%
      gsc share a.mcap -o s.mcap --budget 0.2   the top-20% share for another agent
      gsc merge b.mcap s.mcap --seq SEQ -o m.mcap   give that share to agent B's map
      gsc export-ply a.mcap -o a.ply      open the map in any 3DGS viewer
      gsc export-traj a.mcap -o a.txt     the trajectory for evo (TUM text)
      gsc info a.mcap                     what a log holds
      gsc view a.mcap                     see the map, a prune or a share in the browser
    """
    if threads is not None:
        use_threads(threads)
    if getattr(sys.stdout, "errors", None) == "strict" and hasattr(sys.stdout, "reconfigure"):
        sys.stdout.reconfigure(errors="backslashreplace")  # (a file name that is not UTF-8)
    # gscompress says what it is doing at INFO (-q: only warnings; -v: each frame's stats too);
    # the libraries it uses speak from -vv on
    logging.basicConfig(level=logging.DEBUG if verbose > 1 else logging.WARNING)
    for handler in logging.getLogger().handlers:
        if type(handler) is logging.StreamHandler:  # (the console's, not a test's capture)
            handler.setFormatter(ConsoleFormatter(named=verbose > 0))
    own = logging.WARNING if quiet else (logging.DEBUG if verbose else logging.INFO)
    logging.getLogger("gscompress").setLevel(own)


class ConsoleFormatter(logging.Formatter):
    """gsc's log lines on the console: what gscompress says at INFO (progress, a build under way)
    as it is, a warning or an error after its level; with `named` (gsc -v), every line with its
    level and logger, as a developer reads them."""

    def __init__(self, named: bool) -> None:
        super().__init__("%(levelname)s %(name)s: %(message)s" if named else "%(message)s")
        self.named = named

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        if self.named or record.levelno == logging.INFO:
            return text
        return f"{record.levelname.lower()}: {text}"
