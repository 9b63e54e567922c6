"""Fixtures shared by several test modules."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner, Result

from gscompress.gaussians import GaussianMap
from gscompress.threads import THREAD_VARIABLES
from gscompress_cli.main import cli


def gsc(*args: object) -> Result:
    """`gsc ARGS...` run in this process through click's CliRunner (each argument as text)."""
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture
def threads_restored() -> Iterator[None]:
    """`gsc --threads N` sets OMP/MKL_NUM_THREADS and torch's thread count for the whole
    process; put them back after the test, so that later tests run as before."""
    import torch

    names = THREAD_VARIABLES
    saved, before = {name: os.environ.get(name) for name in names}, torch.get_num_threads()
    yield
    torch.set_num_threads(before)
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


@pytest.fixture
def terminated(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., tuple[int, str]]:
    """Run a command, send it SIGTERM once `ready(stderr so far)` holds; its exit code and
    stderr."""
    log = tmp_path_factory.mktemp("terminated") / "stderr.txt"

    def run(cmd: list[str], ready: Callable[[str], bool], timeout: float = 300) -> tuple[int, str]:
        with open(log, "w+", encoding="utf-8") as stderr:
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=stderr, text=True)
            try:
                deadline = time.monotonic() + timeout
                while not ready(log.read_text(encoding="utf-8")):
                    assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
                    time.sleep(0.05)
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=timeout)
            finally:
                proc.kill()
        return proc.returncode, log.read_text(encoding="utf-8")

    return run


def rewrite_log(src: Path, dst: Path, profile: str = "", **writer_options: Any) -> None:
    """Copy a log's messages and metadata through a plain `mcap` writer with `writer_options`
    (another tool's file: lz4 chunks, no statistics...)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f)
        writer = Writer(out, **writer_options)
        writer.start(profile, "another tool")
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages():
            if channel.id not in channels:
                assert schema is not None
                schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time
            )
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        writer.finish()


def webp_image(pixels: np.ndarray, width: int) -> bytes:
    """A lossless WebP of [N, 4] uint8 pixels in rows of `width` (zero-padded)."""
    from PIL import Image

    rows = -(-len(pixels) // width)
    full = np.zeros((rows * width, 4), np.uint8)
    full[: len(pixels)] = pixels
    out = io.BytesIO()
    Image.fromarray(full.reshape(rows, width, 4), "RGBA").save(
        out, "WEBP", lossless=True, exact=True
    )
    return out.getvalue()


def _nearest_codes(values: np.ndarray, codebook: np.ndarray) -> np.ndarray:
    """The nearest codebook entry of each value."""
    return np.abs(values[..., None] - codebook).argmin(axis=-1).astype(np.uint8)


def sog_bundle(
    g: GaussianMap, meta_edit: Callable[[dict[str, Any]], object] | None = None
) -> bytes:
    """A SOG bundle of `g` with evenly spaced codebooks (a test encoder written from the
    layout; splat-transform clusters instead). Higher SH is not written."""
    n, width = len(g), 32
    logged = np.sign(g.means) * np.log1p(np.abs(g.means.astype(np.float64)))
    mins, maxs = logged.min(axis=0), logged.max(axis=0)
    t = np.round((logged - mins) / np.where(maxs > mins, maxs - mins, 1) * 65535).astype(np.int64)
    alpha = np.full((n, 1), 255, np.uint8)
    low = np.concatenate([(t & 255).astype(np.uint8), alpha], axis=1)
    high = np.concatenate([(t >> 8).astype(np.uint8), alpha], axis=1)
    q = g.quats / np.linalg.norm(g.quats, axis=1, keepdims=True)
    largest = np.abs(q).argmax(axis=1)
    q *= np.where(q[np.arange(n), largest] < 0, -1, 1)[:, None]
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]
    stored = np.take_along_axis(q, others, axis=1)
    quats = np.concatenate(
        [np.round(255 * (stored * np.sqrt(2) * 0.5 + 0.5)), 252 + largest[:, None]], axis=1
    ).astype(np.uint8)
    log3 = np.broadcast_to(g.log_scales, (n, 3))
    scale_book = np.linspace(log3.min(), log3.max(), 256)
    colour_book = np.linspace(g.sh_dc.min(), g.sh_dc.max(), 256)
    opacity = np.round(255 * g.opacities()).astype(np.uint8)[:, None]
    sh0 = np.concatenate([_nearest_codes(g.sh_dc, colour_book), opacity], axis=1)
    scales = np.concatenate([_nearest_codes(log3, scale_book), alpha], axis=1)
    meta = {
        "version": 2,
        "count": n,
        "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": ["l.webp", "u.webp"]},
        "scales": {"codebook": scale_book.tolist(), "files": ["s.webp"]},
        "quats": {"files": ["q.webp"]},
        "sh0": {"codebook": colour_book.tolist(), "files": ["c.webp"]},
    }
    if meta_edit:
        meta_edit(meta)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as bundle:
        bundle.writestr("meta.json", json.dumps(meta))
        for name, pixels in (("l", low), ("u", high), ("q", quats), ("s", scales), ("c", sh0)):
            bundle.writestr(f"{name}.webp", webp_image(pixels, width))
    return out.getvalue()


@pytest.fixture(scope="session")
def seq_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic room: 6 frames at 64x48 (shared by every test that asks: read it only)."""
    from gscompress.datasets.synthetic import write_synthetic_sequence

    return write_synthetic_sequence(tmp_path_factory.mktemp("seq") / "room", 6, (64, 48))


@pytest.fixture(scope="session")
def seq_dir_8(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic room: 8 frames at 64x48, for two agents or a run stopped and resumed
    (shared by every test that asks: read it only)."""
    from gscompress.datasets.synthetic import write_synthetic_sequence

    return write_synthetic_sequence(tmp_path_factory.mktemp("seq8") / "room", 8, (64, 48))


@pytest.fixture(scope="session")
def run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny SLAM log of the synthetic room (6 frames at 48x36, the tiny preset: a keyframe
    every 2), its sequence, and a folder for outputs (refinement and solver tests). It keeps the
    sums accumulated while its map grew (`pwas.final_scores: false`): the refinement tests
    shape the Gaussians a PWAS prune keeps, and on so small a map the finished-map sums keep
    mostly Gaussians that absorb no others (tests/test_eval.py checks those sums)."""
    from gscompress.datasets.synthetic import write_synthetic_sequence
    from gscompress.pipeline import slam_file
    from gscompress.pipeline.slam_run.options import SlamOptions

    root = tmp_path_factory.mktemp("tiny-run")
    seq = write_synthetic_sequence(root / "room", 6, (48, 36))
    log = root / "run.mcap"
    config = root / "accumulated.yaml"
    config.write_text("preset: tiny\npwas:\n  final_scores: false\n")
    slam_file(seq, log, SlamOptions(preset="tiny", config_path=config))
    return {"seq": seq, "log": log, "root": root}


TINY_STUDY = (
    "--preset",
    "tiny",
    "--seeds",
    "1",
    "--sweep",
    "0.2",
    "--strategies",
    "random,pwas",
    "--merge-iters",
    "5",
    "--refine-poses",
    "2",
    "--no-lpips",
    "--references",
    "none",
    "--json",
)
"""`gsc experiment` options of a study of a few seconds: one seed, two strategies, one budget,
short merges, short pose refinement of the cross-agent scoring, no whole map in the field's
formats (11 runs and 7 scoring steps)."""


@pytest.fixture(scope="session")
def tiny_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic room: 4 frames at 32x24 (for TINY_STUDY; read it only)."""
    from gscompress.datasets.synthetic import write_synthetic_sequence

    return write_synthetic_sequence(tmp_path_factory.mktemp("tiny") / "room", 4, (32, 24))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    """A test skipped without saying why fails instead: every skip in the summary has a reason."""
    outcome = yield
    report = outcome.get_result()  # type: ignore[attr-defined]
    if report.skipped and isinstance(report.longrepr, tuple):
        reason = str(report.longrepr[2]).removeprefix("Skipped:").strip()
        if reason in ("", "Skipped", "unconditional skip", "condition: True"):
            report.outcome = "failed"
            report.longrepr = f"{item.nodeid} was skipped without a reason: say why it skips"
