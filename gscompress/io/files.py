"""Safe files: small text inputs read with limits; outputs that refuse to overwrite inputs,
written under a temporary name and renamed.

A crash or an error never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import re
import secrets
import stat
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

from gscompress.errors import GscError, InputError, OutputError

try:
    import fcntl
except ImportError:  # (Windows)
    fcntl = None  # type: ignore[assignment]


def safe_text(text: str) -> str:
    """`text` as Unicode that any UTF-8 writer takes: the bytes of a file name that are not UTF-8
    (which Python holds as surrogate escapes, as `os.fsdecode` makes them) written as `\\xNN`,
    any other lone surrogate as `\\uXXXX`; so that recording or printing a path never raises."""
    if text.isascii():
        return text
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:  # a surrogate that is not an escaped byte
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def safe_value(value: Any) -> Any:
    """`value` with every string in it (keys too, and paths, made strings) `safe_text`."""
    if isinstance(value, str):
        return safe_text(value)
    if isinstance(value, os.PathLike):
        return safe_text(os.fsdecode(value))
    if isinstance(value, dict):
        return {safe_value(k): safe_value(x) for k, x in value.items()}
    if isinstance(value, list | tuple):
        return [safe_value(x) for x in value]
    return value


def json_text(value: Any, **options: Any) -> str:
    """Standard JSON of `value`: non-finite floats (a PSNR of identical images) become null, and
    text that is not UTF-8 (a file's name) is escaped (`safe_text`).

    `json.dumps` would write them as `Infinity`/`NaN`, which strict readers (jq, browsers,
    pandas' default engine) reject. `options` go to `json.dumps` (`default=str` is set).
    """

    def clean(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [clean(x) for x in v]
        return v

    return json.dumps(
        clean(safe_value(value)), allow_nan=False, default=lambda v: safe_text(str(v)), **options
    )


def sha256(path: str | Path) -> str:
    """Hex sha256 of a file, read in 8 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(8 << 20):
            digest.update(block)
    return digest.hexdigest()


SUFFIXES = {
    ".mcap": "an MCAP log",
    ".ply": "a PLY file",
    ".spz": "an SPZ file",
    ".yaml": "a YAML config",
    ".txt": "a text file",
}
"""The output kinds the tool writes, by file-name suffix."""


def is_within(path: str | Path, folder: str | Path) -> bool:
    """Whether `path` is `folder` or lies inside it (links resolved).

    Raises:
        OutputError: a link on either path that leads back to itself.
    """
    path, folder = resolved(path), resolved(folder)
    return path == folder or folder in path.parents


def resolved(path: str | Path) -> Path:
    """`path` absolute with its links resolved, as far as it exists.

    Raises:
        OutputError: a link loop on the path (which `Path.resolve` reports as a RuntimeError
            up to Python 3.12, an OSError since).
    """
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError) as exc:
        raise OutputError(f"{path}: cannot follow its links ({exc})") from None


MAX_TEXT_BYTES = 64 << 20
"""Largest text input read (configs, trajectories, transforms, a sequence's lists)."""


def read_text(
    path: str | Path, what: str, error: type[GscError] = InputError, limit: int = MAX_TEXT_BYTES
) -> str:
    """The UTF-8 text of the file `path` (a `what`: "config", "trajectory"...).

    At most `limit` bytes are read: /dev/zero is refused as too large rather than read
    until memory runs out (a pipe, `/dev/stdin` or `<(...)`, is read like a file).

    Raises:
        error: missing, a directory, too large, unreadable or not UTF-8.
    """
    path = Path(path)
    try:
        if not path.exists():
            raise error(f"{what} file not found: {path}")
        if path.is_dir():
            raise error(f"{what} file {path} is a directory")
        with open(path, "rb") as f:
            data = f.read(limit + 1)
        if len(data) > limit:
            size = f"{limit >> 20} MiB" if limit >= 1 << 20 else f"{limit >> 10} KiB"
            raise error(f"{what} file {path} is over {size}: too large for a {what} file")
        return data.decode("utf-8-sig")  # (a byte-order mark some editors write is not text)
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"cannot read {what} file {path}: {exc}") from None


def read_json(path: str | Path, what: str, error: type[GscError] = InputError) -> Any:
    """The JSON value of the file `path` (`read_text`'s limits).

    Raises:
        error: as `read_text`, or not JSON (also: nested too deep, an int of over 4300 digits).
    """
    try:
        return json.loads(read_text(path, what, error))
    except (ValueError, RecursionError) as exc:  # (JSONDecodeError is a ValueError)
        raise error(f"cannot read {what} file {path}: {' '.join(str(exc).split())}") from None


def check_input(path: str | Path, error: type[GscError] = InputError) -> Path:
    """`path` as a Path when it names a regular file (links followed).

    Raises:
        error: it does not exist, is a directory, or is something else (a device such as
            /dev/zero, a FIFO, a socket), each said as such.
    """
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except OSError as exc:  # a link loop, a name too long, a folder without permission
        raise error(f"{path}: cannot open ({exc.strerror or exc})") from None
    if stat.S_ISDIR(mode):
        raise error(f"{path} is a directory, not a file")
    if not stat.S_ISREG(mode):
        raise error(f"{path} is not a regular file (a device, a FIFO or a socket); name a file")
    return path


def check_output(
    output: str | Path, inputs: Sequence[str | Path] = (), force: bool = False, suffix: str = ""
) -> Path:
    """Refuse to write over an input (also through a link) or into an input folder (a
    sequence), onto a directory, a symbolic link, a device or a FIFO (the rename into place
    would replace them), or over an existing file without `force`; the output's
    directory must exist and be writable. With `suffix` (a key of `SUFFIXES`, what is written),
    the name must end in it: `-o map.ply` on a command that writes a log is a slip that would
    leave an MCAP file named .ply, and `-o map` one that leaves a file no tool recognises.
    """
    output = Path(output)
    for source in map(Path, inputs):
        same = output.exists() and source.exists() and output.samefile(source)
        if same or resolved(output) == resolved(source):
            raise OutputError(f"output {output} is also an input; choose another path")
        if source.is_dir() and is_within(output, source):
            raise OutputError(f"output {output} is inside the input folder {source}")
    named = output.suffix.lower()
    if suffix and named != suffix:
        what = f", not {SUFFIXES[named]}" if named in SUFFIXES else ""
        raise OutputError(
            f"{output}: this writes {SUFFIXES[suffix]}{what}; name it "
            f"{output.name + suffix if not named else output.with_suffix(suffix).name}"
            + (f" (gsc export-ply writes {named[1:].upper()})" if named in (".ply", ".spz") else "")
        )
    if output.is_dir():
        raise OutputError(f"{output} is a directory")
    if output.is_symlink():  # (/dev/stdout: the rename replaces the link, not what it names)
        raise OutputError(f"{output} is a symbolic link; name the file itself")
    if output.exists() and not output.is_file():  # the rename would replace /dev/null
        raise OutputError(f"{output} is not a regular file (a device or a FIFO?); choose a file")
    if output.exists() and not force:
        raise OutputError(f"{output} exists; pass `force` to overwrite it", options=("force",))
    if not output.parent.exists():
        raise OutputError(f"directory {output.parent} does not exist")
    if not os.access(output.parent, os.W_OK | os.X_OK):  # before any work is done
        raise OutputError(f"cannot write in {output.parent} (permission denied or read-only)")
    return output


class AtomicFile:
    """A binary file written under a temporary name and renamed into place on `commit`.

    The temporary file is created exclusively beside the output (`create_temporary`): never
    through a link or over a file already there. The writer holds an exclusive lock on it
    (where the system has `flock`), so that `is_being_written` tells a live writer's file from
    one a killed writer left.
    """

    def __init__(self, path: Path):
        self.path = path
        self.tmp_path, self.file = create_temporary(path)
        if fcntl is not None:
            with contextlib.suppress(OSError):  # a file system without locks: write unlocked
                fcntl.flock(self.file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)

    def commit(self) -> None:
        """Flush, fsync and rename over the final path."""
        self.file.flush()
        os.fsync(self.file.fileno())
        self.file.close()
        os.replace(self.tmp_path, self.path)

    def discard(self) -> None:
        """Close and remove the temporary file (also when closing fails: on a full disk the
        flush of what is being dropped fails too)."""
        with contextlib.suppress(OSError):
            self.file.close()
        self.tmp_path.unlink(missing_ok=True)


_EXCLUSIVE = (
    os.O_WRONLY
    | os.O_CREAT
    | os.O_EXCL
    | getattr(os, "O_NOFOLLOW", 0)
    | getattr(os, "O_CLOEXEC", 0)
    | getattr(os, "O_BINARY", 0)
)
"""How a temporary output is opened: created here and now, never an existing file or a link."""


def create_temporary(path: Path) -> tuple[Path, IO[bytes]]:
    """A new, empty file beside `path` to write it under, and its name: `.NAME.PID.tmp`, or when
    something is in the way there (a killed writer's leftover, or a planted file or link),
    `.NAME.PID.XXXXXXXX.tmp` with random hex digits.

    Raises:
        OutputError: no such name could be created (after 100 tries).
    """
    pid = os.getpid()
    for attempt in range(100):
        tmp_path = temporary_path(path, pid, secrets.token_hex(4) if attempt else "")
        try:
            fd = os.open(tmp_path, _EXCLUSIVE, 0o666)
        except FileExistsError:
            continue
        return tmp_path, os.fdopen(fd, "wb")
    raise OutputError(f"{path}: cannot create a temporary file beside it (every name is taken)")


class MemoryFile:
    """An `AtomicFile` stand-in that keeps the bytes in memory (a file sized before it is written,
    such as a share that must fit a byte budget)."""

    def __init__(self) -> None:
        self.file = io.BytesIO()
        self.data = b""

    def commit(self) -> None:
        """Keep the bytes written."""
        self.data = self.file.getvalue()

    def discard(self) -> None:
        """Drop the bytes written."""
        self.file = io.BytesIO()


def write_atomic(path: str | Path, write: Callable[[IO[bytes]], object]) -> Path:
    """Write a binary file by `write(file)` under a temporary name (`AtomicFile`), renamed
    into place only when `write` returns; on an error nothing appears under `path`."""
    out = AtomicFile(Path(path))
    try:
        write(out.file)
        out.commit()
    except BaseException:
        out.discard()
        raise
    return out.path


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write a binary file under a temporary name and rename it into place."""
    return write_atomic(path, lambda file: file.write(data))


def temporary_path(path: Path, pid: int, tag: str = "") -> Path:
    """Where process `pid` writes `path` until it is complete: `.NAME.PID.tmp` beside it (with
    a `tag`, `.NAME.PID.TAG.tmp`)."""
    return path.with_name(f".{path.name}.{pid}{'.' + tag if tag else ''}.tmp")


def abandoned_files(folder: Path, name: str | None = None) -> list[Path]:
    """Temporary files (`temporary_path`'s) that writers killed before they committed left in
    `folder`, of output `name` (None: of any output), newest first; none a live writer holds,
    and none that is not a regular file (a link or a folder of that name is not a writer's)."""
    stem = re.escape(name) if name is not None else ".+"
    pattern = re.compile(rf"\.{stem}\.\d+(\.[0-9a-f]{{8}})?\.tmp")
    found = []
    for entry in folder.iterdir() if folder.is_dir() else ():
        if not pattern.fullmatch(entry.name):
            continue
        try:
            info = entry.lstat()
        except FileNotFoundError:  # removed meanwhile
            continue
        if stat.S_ISREG(info.st_mode) and not is_being_written(entry):
            found.append((info.st_mtime, entry))
    return [entry for _, entry in sorted(found, reverse=True)]


def is_being_written(path: Path) -> bool:
    """Whether a live `AtomicFile` holds `path` (without `flock`: never)."""
    if fcntl is None:
        return False
    try:
        with open(path, "rb") as f:
            fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:  # held
        return True
    except FileNotFoundError:  # renamed into place meanwhile: its writer finished
        return True
    except OSError:  # no locks here: cannot tell
        return False
    return False


def check_only_entries(
    folder: Path, allowed: frozenset[str], what: str, action: str, options: tuple[str, ...] = ()
) -> None:
    """Refuse a folder holding anything besides `allowed` entries (what gsc itself wrote there).

    Raises:
        OutputError: naming up to three foreign entries, "not {what}", then `action` (which
            names the parameters `options`, as `GscError`'s).
    """
    foreign = [p.name for p in folder.iterdir() if p.name not in allowed]
    if foreign:
        raise OutputError(
            f"{folder} holds files that are not {what} ({some_names(foreign)}); {action}",
            options=options,
        )


def some_names(names: Sequence[str], shown: int = 3) -> str:
    """The first `shown` of `names` in sorted order, comma-separated, "..." when there are more."""
    ordered = sorted(names)
    return ", ".join(ordered[:shown]) + (", ..." if len(ordered) > shown else "")


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write a UTF-8 text file under a temporary name and rename it into place (what is not
    UTF-8 in `text`, such as a file's name, escaped: `safe_text`)."""
    return write_bytes_atomic(path, safe_text(text).encode("utf-8"))
