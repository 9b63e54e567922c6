"""The views and pictures `gsc eval` and `gsc render` share (`ImageOptions`): their checks."""

from __future__ import annotations

from pathlib import Path

import pytest

from gscompress.errors import InputError, OptionError
from gscompress.pipeline.evaluate import evaluate_log
from gscompress.pipeline.images import ImageOptions


@pytest.mark.parametrize(
    "options, error, message",
    [
        (ImageOptions(every=0), InputError, "`every` must be a positive integer, got 0"),
        (ImageOptions(poses="t.txt", poses_from="a.mcap"), OptionError, "do not go together"),
    ],
)
def test_bad_views_are_refused_before_the_log_is_read(
    options: ImageOptions, error: type[Exception], message: str, tmp_path: Path
) -> None:
    with pytest.raises(error, match=message):
        options.check()
    with pytest.raises(error, match=message):  # (the log is not there: refused before it)
        evaluate_log(tmp_path / "missing.mcap", tmp_path / "seq", options)
    ImageOptions().check()


def test_refine_poses_stays_evaluate_logs_own_check(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="`refine_poses` must be 0 or more"):
        evaluate_log(tmp_path / "missing.mcap", tmp_path / "seq", refine_poses=-1)


def test_the_defaults_are_gsc_evals() -> None:
    options = ImageOptions()
    assert (options.frames, options.every, options.size) == (None, 1, None)
    assert (options.backend, options.device, options.lpips) == ("auto", "auto", True)
    assert options.save_images is None and options.colorings == ("rgb",)
    assert options.side_by_side
