"""`SlamOptions`: a fresh SLAM run's settings, their checks, `gsc slam`'s defaults, and the run
`slam_file` makes of them."""

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import gsc

from gscompress.datasets.recording import RecordingOptions
from gscompress.errors import InputError, OptionError
from gscompress.io.mcap_log import LogReader
from gscompress.pipeline.slam_run import RESUME_KEEPS, refuse_own_settings, slam_file
from gscompress.pipeline.slam_run.options import SlamOptions
from gscompress.slam.config import resolve_config
from gscompress_cli.flags import with_flags

TINY = SlamOptions(preset="tiny", frames="0:3", size=(32, 24))


@pytest.mark.parametrize(
    ("options", "error", "message"),
    [
        (SlamOptions(keep=0.0), InputError, r"`keep` must be in \(0, 1\], got 0.0"),
        (SlamOptions(keep=1.5), InputError, r"`keep` must be in \(0, 1\], got 1.5"),
        (
            SlamOptions(keep=0.5, no_prune=True),
            OptionError,
            "`keep` does not go with `no_prune`: there is no pruning stage",
        ),
        (SlamOptions(share_transform="t.txt"), OptionError, "a share transform needs `inject`"),
    ],
)
def test_check_refuses_what_slam_file_refused(
    options: SlamOptions, error: type[Exception], message: str, seq_dir: Path, tmp_path: Path
) -> None:
    with pytest.raises(error, match=message):
        options.check()
    out = tmp_path / "run.mcap"
    with pytest.raises(error, match=message):  # before anything is read or written
        slam_file(seq_dir, out, options)
    assert not out.exists()


def test_check_passes_the_defaults_and_settings_in_range() -> None:
    SlamOptions().check()
    SlamOptions(keep=1.0).check()
    SlamOptions(no_prune=True).check()
    SlamOptions(inject="share.mcap", share_transform="t.txt").check()


def test_options_are_frozen_values() -> None:
    a = SlamOptions(preset="tiny", size=(32, 24), recording=RecordingOptions(rgb="/c"))
    assert a == SlamOptions(preset="tiny", size=(32, 24), recording=RecordingOptions(rgb="/c"))
    assert a != dataclasses.replace(a, keep=0.5)
    assert hash(a) == hash(dataclasses.replace(a))
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.keep = 0.5  # type: ignore[misc]


def _captured(monkeypatch: pytest.MonkeyPatch, *args: Any) -> tuple[SlamOptions, dict[str, Any]]:
    """The options and keywords `gsc slam *args` calls `slam_file` with."""
    from gscompress import pipeline

    calls: list[tuple[SlamOptions, dict[str, Any]]] = []

    def fake_slam_file(seq, dst, options, **kwargs):  # type: ignore[no-untyped-def]
        calls.append((options, kwargs))
        return {"frames": 1, "gaussians": 1, "seconds_per_frame": 1.0}

    monkeypatch.setattr(pipeline, "slam_file", fake_slam_file)
    r = gsc("slam", *args)
    assert r.exit_code == 0, r.output
    (call,) = calls
    return call


def test_the_defaults_are_gsc_slams(monkeypatch, seq_dir: Path, tmp_path: Path) -> None:
    options, kwargs = _captured(monkeypatch, seq_dir, "-o", tmp_path / "run.mcap")
    assert options == SlamOptions(recording=RecordingOptions())  # (every option not given)
    assert kwargs["device"] == "auto" and kwargs["force"] is False


def test_gsc_slam_passes_each_setting(monkeypatch, seq_dir: Path, tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text("preset: tiny\n")
    share, transform = tmp_path / "share.mcap", tmp_path / "t.txt"
    share.write_bytes(b"")
    transform.write_text("0 0 0 0 0 0 1\n")
    options, _ = _captured(
        monkeypatch,
        *(seq_dir, "-o", tmp_path / "run.mcap", "--preset", "tiny", "--config", config),
        *("--frames", "0:3", "--size", "32x24", "--keep", "0.5", "--backend", "torch"),
        *("--inject", share, "--share-transform", transform, "--max-dt", "0.01"),
    )
    assert options == SlamOptions(
        preset="tiny",
        config_path=config,
        frames="0:3",
        size=(32, 24),
        keep=0.5,
        backend="torch",
        inject=share,
        share_transform=transform,
        recording=RecordingOptions(max_dt=0.01),
    )


@pytest.mark.parametrize("name", [*RESUME_KEEPS, "no_prune", "recording"])
def test_resume_refuses_each_of_a_fresh_runs_settings(name: str) -> None:
    values: dict[str, Any] = {
        "preset": {"preset": "tiny"},
        "config": {"config_path": "c.yaml"},
        "frames": {"frames": "0:3"},
        "size": {"size": (32, 24)},
        "backend": {"backend": "torch"},
        "keep": {"keep": 0.5},
        "inject": {"inject": "s.mcap"},
        "share_transform": {"share_transform": "t.txt"},
        "no_prune": {"no_prune": True},
        "recording": {"recording": RecordingOptions(rgb="/c")},
    }
    options = SlamOptions(**values[name])
    recording = "`rgb`/`depth`/`camera_info`/`max_dt`/`gt`"
    named = recording if name == "recording" else f"`{name}`"
    with pytest.raises(OptionError) as refused:
        refuse_own_settings(options.kept, options.no_prune, options.recording)
    said = "continues with the log's own settings; drop"
    assert str(refused.value) == f"`resume` {said} {named}"
    flag = "--rgb/--depth/--camera-info/--max-dt/--gt" if name == "recording" else f"--{name}"
    assert with_flags(refused.value) == f"--resume {said} {flag.replace('_', '-')}"
    default = SlamOptions(recording=RecordingOptions())
    refuse_own_settings(default.kept, default.no_prune, default.recording)  # nothing given


def _log(path: Path) -> tuple[Any, np.ndarray, Any]:
    """A log's map, estimated camera-to-world poses and metadata."""
    with LogReader(path) as reader:
        return reader.read_map(), reader.read_poses()[1], reader.metadata


def test_a_run_from_options_is_the_run_of_its_resolved_config(seq_dir: Path, tmp_path: Path):
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    result = slam_file(seq_dir, a, TINY)
    config = resolve_config("tiny", size=(32, 24))
    slam_file(seq_dir, b, SlamOptions(frames="0:3"), config=config)
    (map_a, poses_a, meta_a), (map_b, poses_b, meta_b) = _log(a), _log(b)
    assert result["frames"] == 3 and len(poses_a) == 3
    assert meta_a.frames == "0:3" and meta_a.config["size"] == [32, 24]
    assert meta_a.config["preset"] == "tiny" and meta_a.config == meta_b.config
    assert np.array_equal(poses_a, poses_b)
    assert len(map_a) == len(map_b) > 0
    for field in dataclasses.fields(map_a):
        value = getattr(map_a, field.name)
        if isinstance(value, np.ndarray):
            assert np.array_equal(value, getattr(map_b, field.name)), field.name
    with pytest.raises(OptionError, match="a ready config takes no preset"):
        slam_file(seq_dir, tmp_path / "c.mcap", TINY, config=config)
