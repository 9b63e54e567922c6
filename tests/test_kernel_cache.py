"""The cache of compiled C++ render kernels shared by processes: builds in progress are never
removed, one build serves every process that waits for it, a slow build says so, and a fallback
to pure torch says how much it costs. The compiler is replaced by a slow fake that writes a fake
library, so no test here compiles anything."""

from __future__ import annotations

import fcntl
import json
import logging
import os
import shutil
import subprocess
import sys
import threading
import time
import types
import warnings
from collections.abc import Callable
from pathlib import Path

import pytest

from gscompress.render.cpu import build as cpu_build

_FAKE = b"not a library"


def _fake_compiler(journal: Path, seconds: float) -> Callable[..., types.ModuleType]:
    """A stand-in for `torch.utils.cpp_extension.load`: notes each build in `journal`, takes
    `seconds`, then writes a fake library where the real one would go."""

    def load(*, name: str, build_directory: str, **_: object) -> types.ModuleType:
        with open(journal, "a") as f:
            f.write(f"{name}\n")
        time.sleep(seconds)
        (Path(build_directory) / f"{name}.so").write_bytes(_FAKE)
        return types.ModuleType(name)

    return load


def _fake_import(path: Path, name: str) -> types.ModuleType | None:
    """Imports what `_fake_compiler` wrote (the real import would reject it)."""
    return types.ModuleType(name) if path.read_bytes() == _FAKE else None


def worker() -> None:
    """One process's first use of the kernels: `python -c` entry of `_first_uses`.

    argv: journal, start signal, seconds of the fake build. Waits for the start signal so that
    every worker asks at once, then prints what `load_extension` gave and warned as JSON.
    """
    import torch.utils.cpp_extension

    journal, start, seconds = Path(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3])
    torch.utils.cpp_extension.load = _fake_compiler(journal, seconds)
    cpu_build._import_library = _fake_import
    (start.parent / f"ready-{os.getpid()}").touch()
    while not start.exists():
        time.sleep(0.01)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ext = cpu_build.load_extension()
    messages = [str(w.message) for w in caught]
    print(json.dumps({"name": getattr(ext, "__name__", None), "warnings": messages}))


def _first_uses(tmp_path: Path, marches: list[str], seconds: list[float]) -> tuple[list, Path]:
    """Start one process per `marches` entry (each its own `$GSCOMPRESS_MARCH`, so equal entries
    share a build and different ones do not) on one cache, let them ask for the kernels at the
    same moment, and return their answers and the journal of the builds they ran."""
    root, journal, start = tmp_path / "cache", tmp_path / "builds.txt", tmp_path / "start"
    journal.touch()
    env = dict(os.environ, GSCOMPRESS_CACHE_DIR=str(root), CXX=sys.executable)  # never run
    procs = []
    for march, s in zip(marches, seconds, strict=True):
        cmd = [sys.executable, "-c", "import test_kernel_cache as t; t.worker()"]
        procs.append(
            subprocess.Popen(
                [*cmd, str(journal), str(start), str(s)],
                cwd=Path(__file__).parent,
                env={**env, cpu_build.MARCH_ENV: march},
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        )
    deadline = time.monotonic() + 120
    while len(list(tmp_path.glob("ready-*"))) < len(procs):
        assert all(p.poll() is None for p in procs), [p.communicate() for p in procs]
        assert time.monotonic() < deadline
        time.sleep(0.02)
    start.touch()
    answers = []
    for proc in procs:
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
        answers.append(json.loads(out.splitlines()[-1]))
    return answers, journal


@pytest.mark.slow
def test_builds_of_different_digests_at_once_all_finish(tmp_path):
    """Three first uses with three build digests on one cache (three venvs or checkouts sharing
    ~/.cache): the first to finish prunes the cache while the others still compile. Each keeps
    its folder and loads its own build; none falls back to pure torch."""
    answers, journal = _first_uses(tmp_path, ["fake-a", "fake-b", "fake-c"], [0.5, 1.0, 1.5])
    assert [a["warnings"] for a in answers] == [[], [], []]
    names = [a["name"] for a in answers]
    assert None not in names and len(set(names)) == 3
    assert sorted(journal.read_text().split()) == sorted(names)  # one build each
    for name in names:
        folder = tmp_path / "cache" / f"ext-{name.rsplit('_', 1)[1]}"
        assert (folder / f"{name}.so").read_bytes() == _FAKE
        assert (folder / cpu_build._BUILT).exists()


@pytest.mark.slow
def test_first_uses_of_one_digest_share_one_build(tmp_path):
    """Three processes asking for the same build at once: one compiles, the others wait for
    it and load what it built."""
    answers, journal = _first_uses(tmp_path, ["fake-a"] * 3, [1.0] * 3)
    assert [a["warnings"] for a in answers] == [[], [], []]
    names = {a["name"] for a in answers}
    assert len(names) == 1 and None not in names
    assert journal.read_text().split() == list(names)  # built once


@pytest.fixture
def fake_build(monkeypatch, tmp_path):
    """`load_extension` on a fresh cache with a fake compiler of `seconds` (default 0.4), its
    heartbeat every 0.05 s; returns a function that runs it and the journal of its builds."""
    import torch.utils.cpp_extension

    journal = tmp_path / "builds.txt"
    journal.touch()
    monkeypatch.setenv("GSCOMPRESS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("CXX", sys.executable)
    monkeypatch.setenv(cpu_build.MARCH_ENV, "fake-a")
    monkeypatch.setattr(cpu_build, "_import_library", _fake_import)
    monkeypatch.setattr(cpu_build, "_HEARTBEAT_S", 0.05)

    def run(seconds: float = 0.4, fails: bool = False) -> types.ModuleType | None:
        load = _fake_compiler(journal, seconds)

        def failing(**kwargs: object) -> types.ModuleType:
            load(**kwargs)  # type: ignore[arg-type]
            raise RuntimeError("Error building extension 'gsc_composite': g++ said no")

        monkeypatch.setattr(torch.utils.cpp_extension, "load", failing if fails else load)
        cpu_build.load_extension.cache_clear()
        try:
            return cpu_build.load_extension()
        finally:
            cpu_build.load_extension.cache_clear()

    return run, journal


def _beats(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if "still compiling" in r.getMessage()]


def test_a_slow_build_says_it_is_still_compiling(fake_build, caplog):
    """A line every heartbeat while the compiler runs, with the time so far; none once it has
    finished, and none when the build is already there."""
    run, journal = fake_build
    caplog.set_level(logging.INFO, logger="gscompress")
    assert run(0.4) is not None
    beats = _beats(caplog)
    assert len(beats) >= 3 and all(b.endswith(" s)") for b in beats), beats
    time.sleep(0.2)
    assert len(_beats(caplog)) == len(beats)  # stopped with the build
    caplog.clear()
    assert run(0.4) is not None
    assert len(journal.read_text().split()) == 1  # loaded, not built again
    assert not caplog.records


def test_a_failed_build_stops_its_heartbeat_and_says_how_to_fix(fake_build, caplog, tmp_path):
    """A compiler error: one warning with the error, the cost of pure torch and the folder to
    remove; the heartbeat stops with the build."""
    run, _ = fake_build
    caplog.set_level(logging.INFO, logger="gscompress")
    with pytest.warns(RuntimeWarning) as caught:
        assert run(0.2, fails=True) is None
    assert len(caught) == 1
    message = str(caught[0].message)
    assert "g++ said no" in message and "pure torch" in message
    assert "53-60x slower" in message  # docs/performance.md, the renderer's table
    [folder] = (tmp_path / "cache").glob("ext-*")
    assert f"remove {folder}" in message
    count = len(_beats(caplog))
    time.sleep(0.2)
    assert count >= 1 and len(_beats(caplog)) == count


def test_a_cache_that_cannot_be_written_names_the_variable_to_set(
    fake_build, monkeypatch, tmp_path
):
    run, journal = fake_build
    (tmp_path / "a-file").touch()
    monkeypatch.setenv("GSCOMPRESS_CACHE_DIR", str(tmp_path / "a-file" / "cache"))
    with pytest.warns(RuntimeWarning) as caught:
        assert run() is None
    assert len(caught) == 1 and not journal.read_text()
    message = str(caught[0].message)
    assert "53-60x slower" in message and "set GSCOMPRESS_CACHE_DIR" in message


def test_a_missing_compiler_warns_once_with_the_cost_and_the_fix(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler-gsc")
    cpu_build.load_extension.cache_clear()
    try:
        with pytest.warns(RuntimeWarning) as caught:
            assert cpu_build.load_extension() is None
            assert cpu_build.load_extension() is None  # asked again: no second warning
    finally:
        cpu_build.load_extension.cache_clear()
    assert len(caught) == 1
    message = str(caught[0].message)
    assert "no C++ compiler" in message and "53-60x slower" in message and "g++" in message


def _folder(root: Path, name: str, days_unused: float, built: bool = True) -> Path:
    """An `ext-*` folder last used `days_unused` ago: a finished build, or one whose compiler
    has written nothing yet."""
    folder = root / name
    folder.mkdir()
    stamp = time.time() - days_unused * 86400
    if built:
        for f in (folder / "x.so", folder / cpu_build._BUILT):
            f.write_text("")
            os.utime(f, (stamp, stamp))
    os.utime(folder, (stamp, stamp))
    return folder


def test_the_pruner_skips_a_folder_whose_build_holds_its_lock(tmp_path):
    """A build in progress holds an OS lock on its folder: the pruner leaves a locked folder
    alone however old it looks, and removes an old one nobody holds."""
    busy = _folder(tmp_path, "ext-00000000000000aa", 40, built=False)
    old = _folder(tmp_path, "ext-00000000000000bb", 40)
    current = _folder(tmp_path, "ext-00000000000000cc", 0)
    with open(busy / "gsc.lock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        cpu_build._prune_cache(tmp_path, keep=current)
        assert busy.exists() and not old.exists() and current.exists()
    cpu_build._prune_cache(tmp_path, keep=current)  # released: an abandoned build
    assert not busy.exists()


def test_a_build_whose_folder_was_removed_before_it_locked_it_starts_again(tmp_path):
    """A pruner may lock and remove a folder just made by a build that has not locked it yet:
    the build, once it holds the lock, sees its lock file is no longer the folder's, makes the
    folder again and locks that."""
    folder = tmp_path / "ext-00000000000000aa"
    folder.mkdir()
    entered = threading.Event()
    with open(folder / "gsc.lock", "a") as pruner:
        fcntl.flock(pruner, fcntl.LOCK_EX)

        def build() -> None:
            with cpu_build._build_lock(folder):
                assert (folder / "gsc.lock").exists()
                (folder / "built-here").touch()
                entered.set()

        builder = threading.Thread(target=build)
        builder.start()
        time.sleep(0.3)  # the builder waits on the pruner's lock
        assert not entered.is_set()
        shutil.rmtree(folder)
    builder.join(timeout=10)
    assert entered.is_set() and (folder / "built-here").exists()


def test_a_build_waiting_for_another_says_so(monkeypatch, tmp_path, caplog):
    """A process that finds the build locked by another says it waits, and keeps saying so
    with the time so far until it holds the lock."""
    monkeypatch.setattr(cpu_build, "_HEARTBEAT_S", 0.05)
    caplog.set_level(logging.INFO, logger="gscompress")
    folder = tmp_path / "ext-00000000000000aa"
    folder.mkdir()
    entered = threading.Event()

    def build() -> None:
        with cpu_build._build_lock(folder):
            entered.set()

    with open(folder / "gsc.lock", "a") as other:
        fcntl.flock(other, fcntl.LOCK_EX)
        waiter = threading.Thread(target=build)
        waiter.start()
        time.sleep(0.4)
        assert not entered.is_set()
    waiter.join(timeout=10)
    messages = [r.getMessage() for r in caplog.records]
    assert entered.is_set() and messages[0].startswith("waiting for another process")
    assert len([m for m in messages if m.startswith("still waiting")]) >= 3
