"""The build cache of the cpu backend's C++ kernels: compiler flags, the cache key, the lock a
build holds, the pruning of unused builds, and `load_extension`.

The extension is compiled on first use with `torch.utils.cpp_extension.load` into a cache
directory keyed on the sources and their location, the flags, torch, Python and (for the
-march=native build on x86-64) the CPU model and feature flags (`$GSCOMPRESS_CACHE_DIR` or
`$XDG_CACHE_HOME/gscompress`, default `~/.cache/gscompress`); later processes import the finished
build directly. A build holds an OS lock on its directory for its whole life: processes that
want the same build wait for it and load it, and each new build removes the builds no process
has used for 30 days, skipping any directory another process holds. Without a C++ compiler, or
when the build fails, `load_extension()` warns once and returns None, and the caller falls back
to the pure-torch backend.

`$GSCOMPRESS_MARCH` picks another target than the build machine's: `generic` for portable
flags, or a compiler target such as `x86-64-v3` (AVX2 with FMA) to build, test or time another
vector width than the CPU's widest (`bench/render.py --march`). A target whose instructions the
CPU lacks builds, but the process dies with an illegal instruction on the first render.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib.util
import logging
import os
import platform
import re
import shutil
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import IO

import torch

from gscompress.errors import InputError

logger = logging.getLogger(__name__)

try:
    import fcntl
except ImportError:  # (Windows)
    fcntl = None  # type: ignore[assignment]


_SOURCES = tuple(Path(__file__).with_name(n) for n in ("composite.cpp", "project.cpp", "ssim.cpp"))
# -ffp-contract=off keeps the forward, the backward and the torch oracle rounding alike.
_CFLAGS = ("-O3", "-fopenmp", "-ffp-contract=off")
_LDFLAGS = ("-fopenmp",)  # tuples: torch's loader appends its libraries to the lists it is given


def _cpu_signature() -> str | None:
    """The CPU's model and feature flags (Linux), or None when they cannot be read."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    lines = [ln for ln in text.splitlines() if ln.startswith(("flags", "model name"))]
    return "\n".join(sorted(set(lines))) or None


MARCH_ENV = "GSCOMPRESS_MARCH"
"""Environment variable naming the `-march` target of the build: `native` (the default),
`generic` (portable flags) or a target of the compiler's, e.g. `x86-64-v3` (AVX2 and FMA)."""


def _build_flags() -> tuple[list[str], str]:
    """Compiler flags and the CPU part of the cache key.

    The kernels are vectorised for the build machine (-march=native, e.g. AVX2 / AVX-512), so
    the cache key includes the CPU's model and feature flags: a home directory shared between
    different machines then holds one build per CPU type instead of a build that crashes.
    Elsewhere (not x86-64, or the CPU cannot be identified) the build uses portable flags.
    `$GSCOMPRESS_MARCH` overrides the target (see `MARCH_ENV`): a named one is keyed by its
    name alone, as it does not depend on the CPU that builds it.

    Raises:
        InputError: a `$GSCOMPRESS_MARCH` that is not a plain target name.
    """
    march = os.environ.get(MARCH_ENV, "").strip() or "native"
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+-]*", march):
        raise InputError(
            f"{MARCH_ENV}={march!r} is not a -march target; use native, generic or a name "
            "such as x86-64-v3"
        )
    if march == "generic":
        return list(_CFLAGS), "generic"
    if march != "native":
        return [*_CFLAGS, f"-march={march}"], f"march={march}"
    cpu = _cpu_signature() if platform.machine() in ("x86_64", "AMD64") else None
    if cpu is None:
        return list(_CFLAGS), "generic"
    return [*_CFLAGS, "-march=native"], cpu


_LOCK = "gsc.lock"


@contextlib.contextmanager
def _build_lock(build_dir: Path) -> Iterator[None]:
    """Make the build directory and hold an OS lock on it, clearing the `lock` a killed build left.

    The lock (flock on `gsc.lock`, which the OS releases when a process dies) is held for the
    build's whole life: other builders of the same directory wait for it, and `_prune_cache`
    leaves a locked directory alone. The pruner may still lock and remove a directory made here
    before this process locked it; the lock then held is on a removed file, so the directory is
    made again and locked once more. torch's build waits forever on a `lock` file, which a build
    killed midway (Ctrl-C on the first run) leaves behind; found while holding ours, it is stale.

    Raises:
        OSError: the directory cannot be made, or was removed under this process twice.
    """
    if fcntl is None:  # not POSIX: torch's own lock only
        build_dir.mkdir(parents=True, exist_ok=True)
        yield
        return
    for _ in range(2):
        build_dir.mkdir(parents=True, exist_ok=True)
        try:
            handle = open(build_dir / _LOCK, "a")
        except FileNotFoundError:  # removed between mkdir and open
            continue
        with handle:
            _wait_for_lock(handle, build_dir)
            if _is_linked(handle, build_dir / _LOCK):
                (build_dir / "lock").unlink(missing_ok=True)
                yield
                return
    raise OSError(f"{build_dir} was removed twice while this process waited to build in it")


def _wait_for_lock(handle: IO[str], build_dir: Path) -> None:
    """Take the exclusive lock of `handle`, saying so when another process's build holds it."""
    assert fcntl is not None
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        logger.info("waiting for another process building the C++ render kernels in %s", build_dir)
        with _heartbeat("still waiting for the C++ render kernels' build in %s", build_dir):
            fcntl.flock(handle, fcntl.LOCK_EX)


def _is_linked(handle: IO[str], path: Path) -> bool:
    """Whether the open file `handle` is still the file at `path`."""
    try:
        here = os.stat(path)
    except FileNotFoundError:
        return False
    held = os.fstat(handle.fileno())
    return (held.st_dev, held.st_ino) == (here.st_dev, here.st_ino)


@contextlib.contextmanager
def _try_lock(build_dir: Path) -> Iterator[bool]:
    """Hold the build lock of `build_dir` if no process holds it (True), else yield False."""
    assert fcntl is not None
    with open(build_dir / _LOCK, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        yield True


_HEARTBEAT_S = 10.0
"""Seconds between the lines that say a build is still running."""


@contextlib.contextmanager
def _heartbeat(message: str, *args: object) -> Iterator[None]:
    """Log `message % args` with the seconds elapsed every `_HEARTBEAT_S` while the body runs.

    A first build takes a minute on an idle machine and several on a loaded one; without these
    lines it looks hung.
    """
    done, start = threading.Event(), time.monotonic()

    def beat() -> None:
        while not done.wait(_HEARTBEAT_S):
            logger.info(message + " (%.0f s)", *args, time.monotonic() - start)

    thread = threading.Thread(target=beat, name="gsc-build-heartbeat", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def _cache_root() -> Path:
    """Where the compiled extensions are kept."""
    if "GSCOMPRESS_CACHE_DIR" in os.environ:
        return Path(os.environ["GSCOMPRESS_CACHE_DIR"])
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "gscompress"


def _cache_key(sources: tuple[Path, ...], cflags: list[str], cpu: str, compiler: str) -> str:
    """16 hex digits naming one build: the sources' bytes and location, flags, toolchain, CPU.

    The location counts because the build directory's ninja file names the sources by path: two
    checkouts of the same sources sharing one cache would otherwise rebuild in turn, a whole
    build each time (seen when alternating runs of two worktrees; docs/setup.md, "The C++ render
    kernels").
    """
    key = hashlib.sha256()
    for source in sources:
        key.update(source.read_bytes())
        key.update(str(source.resolve()).encode())
    key.update(" ".join([*cflags, *_LDFLAGS]).encode())
    key.update(f"{torch.__version__}|{sys.version}|{platform.machine()}|{compiler}".encode())
    key.update(cpu.encode())
    return key.hexdigest()[:16]


# Written once a build has loaded. A link killed midway leaves a truncated library, and loading
# one kills the process (SIGBUS), so only a marked build is imported directly.
_BUILT = "gsc.built"


def _load_built(build_dir: Path, name: str) -> ModuleType | None:
    """The extension of a finished earlier build, imported directly; None if there is none.

    The directory's name already fixes the sources' bytes, flags, toolchain and CPU, so there
    is nothing for torch's loader to check: going through it costs each process the import of
    setuptools and a run of ninja, this next to nothing (measured in docs/design-experiments.md,
    "Start-up").
    """
    path = build_dir / f"{name}.so"
    if not (build_dir / _BUILT).exists() or not path.exists():
        return None
    module = _import_library(path, name)
    if module is None:
        return None
    with contextlib.suppress(OSError):  # the time of last use, for `_prune_cache`
        os.utime(build_dir / _BUILT)
    return module


def _import_library(path: Path, name: str) -> ModuleType | None:
    """The extension module in the library at `path`; None when it cannot be imported."""
    try:
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            return None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except ImportError:  # e.g. a library it links against has moved: torch's loader decides
        return None
    return module


def _last_use(build_dir: Path) -> float:
    """When a build was last used: its marker's time (touched at each direct load), else its
    library's; 0 for a build that has written neither (in progress, or failed)."""
    stamps = [build_dir / _BUILT, *build_dir.glob("*.so")]
    return max((p.stat().st_mtime for p in stamps if p.exists()), default=0.0)


def _prune_cache(root: Path, keep: Path, unused_days: float = 30.0) -> None:
    """Remove the builds in `root` other than `keep` that no process has used for this long.

    Every change of the sources, flags, torch or CPU makes a new build (its size:
    docs/setup.md, "The C++ render kernels"), and a checkout whose sources are edited makes one
    per edit. Runs only when torch's loader was used (a new build, or a build made before the
    marker existed), so rarely. A directory whose build lock another process holds is in use
    (a build in progress, or one waiting for it) and is skipped; the others are locked, checked
    again and removed under the lock, so that a build cannot start in a directory being removed
    (see `_build_lock`). Without flock (not POSIX) a build in progress cannot be told from an
    abandoned one, and nothing is removed.
    """
    if fcntl is None:
        return
    limit = time.time() - unused_days * 86400
    for old in root.glob("ext-*"):
        if old == keep or not re.fullmatch(r"ext-[0-9a-f]{16}", old.name) or not old.is_dir():
            continue
        with contextlib.suppress(OSError):  # e.g. removed meanwhile by another process
            if _last_use(old) >= limit:
                continue
            with _try_lock(old) as locked:
                if locked and _last_use(old) < limit:
                    shutil.rmtree(old, ignore_errors=True)


@functools.cache
def load_extension() -> ModuleType | None:
    """The compiled kernels, building them on first use; None when no compiler is available.

    Processes that ask for the same build at once wait for the one that compiles it, then load
    what it built. A missing compiler or a failed build is reported once with a warning that
    says what falling back to pure torch costs and how to fix it.
    """
    compiler = os.environ.get("CXX", "c++")
    if shutil.which(compiler) is None:
        _warn_fallback(
            f"no C++ compiler ({compiler!r}) found",
            "install g++ (e.g. apt-get install g++) or set CXX to a C++ compiler",
        )
        return None
    cflags, cpu = _build_flags()
    digest = _cache_key(_SOURCES, cflags, cpu, compiler)
    build_dir = _cache_root() / f"ext-{digest}"
    name = f"gsc_composite_{digest}"
    built = _load_built(build_dir, name)
    if built is not None:
        return built
    try:
        module = _build(build_dir, name, cflags)
    except Exception as exc:  # a build failure must not take rendering down
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        target = f" for {MARCH_ENV}={os.environ[MARCH_ENV]}" if os.environ.get(MARCH_ENV) else ""
        _warn_fallback(
            f"building the C++ render kernels{target} failed ({first_line})",
            _build_fix(exc, build_dir),
        )
        return None
    _prune_cache(build_dir.parent, keep=build_dir)
    return module


def _build(build_dir: Path, name: str, cflags: list[str]) -> ModuleType:
    """Compile the extension in `build_dir` under its lock and load it; if another process
    built it while this one waited for the lock, load that build instead."""
    from torch.utils import cpp_extension

    with _build_lock(build_dir):
        built = _load_built(build_dir, name)
        if built is not None:
            return built
        if not (build_dir / f"{name}.so").exists():
            logger.info(
                "building the C++ render kernels in %s (first use: a minute or more)", build_dir
            )
        (build_dir / _BUILT).unlink(missing_ok=True)  # until this build has loaded
        with _heartbeat("still compiling the C++ render kernels in %s", build_dir):
            module = cpp_extension.load(
                name=name,
                sources=[str(source) for source in _SOURCES],
                extra_cflags=list(cflags),
                extra_ldflags=list(_LDFLAGS),
                build_directory=str(build_dir),
                verbose=False,
            )
        (build_dir / _BUILT).write_text(f"{name}.so\n")
    return module


# Forward and backward of one render, C++ against pure torch (docs/performance.md, Renderer).
_PURE_TORCH_SLOWER = "53-60x"


def _build_fix(exc: Exception, build_dir: Path) -> str:
    """What to do about a failed build: a cache that cannot be written wants another place;
    a compiler error, a fresh build (after an update of the compiler or torch)."""
    if isinstance(exc, OSError):
        return (
            f"make {build_dir.parent} writable (with free space), or set GSCOMPRESS_CACHE_DIR "
            "to a folder that is"
        )
    hint = f"unset {MARCH_ENV} or " if os.environ.get(MARCH_ENV) else ""
    return f"{hint}remove {build_dir} to build afresh, or install g++ if the compiler is broken"


def _warn_fallback(what: str, fix: str) -> None:
    """The one warning of a process whose cpu render backend falls back to pure torch."""
    warnings.warn(
        f"{what}: the cpu render backend falls back to pure torch, which renders "
        f"{_PURE_TORCH_SLOWER} slower (docs/performance.md); to fix it, {fix}",
        RuntimeWarning,
        stacklevel=4,
    )
