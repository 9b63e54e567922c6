"""`gsc render` and `gsc eval --save-images`: pictures of a map at known views."""

import json
from dataclasses import replace

import numpy as np
import pytest
from conftest import gsc
from PIL import Image

from gscompress.datasets import open_sequence
from gscompress.errors import MapError
from gscompress.io.mcap_log import LogReader, LogWriter
from gscompress.ops.evaluate import render_view
from gscompress.ops.score import activated_tensors
from gscompress.pipeline.images import IMPORTANCE_CMAP, colormap, importance_colors, to_uint8
from gscompress.selection import strategy_scores

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow


def test_rgb_pictures_are_the_renders_at_the_logs_poses(run, tmp_path):
    out = tmp_path / "pics"
    r = gsc("render", run["log"], "--seq", run["seq"], "-o", out, "--json")
    assert r.exit_code == 0, r.output
    result = json.loads(r.output)
    with LogReader(run["log"]) as log:
        gaussians = log.read_map()
        _, poses = log.read_poses()
    files = sorted((out / "rgb").iterdir())
    assert [f.name for f in files] == [f"{i:06d}.png" for i in range(len(poses))]
    assert sorted(result["images"]) == sorted(str(f) for f in files)
    sequence = open_sequence(run["seq"], size=(48, 36))
    color, _ = render_view(activated_tensors(gaussians), poses[3], sequence.intrinsics)
    written = np.asarray(Image.open(files[3]))
    assert written.shape == (36, 48, 3)
    assert np.abs(written.astype(int) - to_uint8(color).astype(int)).max() <= 1


def test_importance_colours_span_the_colour_map_from_least_to_most_important(run):
    with LogReader(run["log"]) as log:
        gaussians = log.read_map()
    colors, scale = importance_colors(gaussians)
    low, high = scale.low, scale.high
    scores = strategy_scores(gaussians, "pwas")
    top, bottom = np.argmax(scores), np.argmin(np.where(scores > 0, scores, np.inf))
    assert low < high
    np.testing.assert_allclose(colors[top], colormap(np.array(high), low, high, IMPORTANCE_CMAP))
    np.testing.assert_allclose(colors[bottom], colormap(np.array(low), low, high, IMPORTANCE_CMAP))
    # brighter means more important on viridis: the top Gaussian's colour is the lighter one
    assert colors[top].sum() > colors[bottom].sum()


def test_side_by_side_figure_and_every_colouring_are_written(run, tmp_path):
    out = tmp_path / "pics"
    colors = ("--color", "rgb", "--color", "importance", "--color", "depth")
    r = gsc(
        "render",
        run["log"],
        "--seq",
        run["seq"],
        "-o",
        out,
        "--frames",
        "2:4",
        *colors,
        "--side-by-side",
    )
    assert r.exit_code == 0, r.output
    for folder in ("rgb", "importance", "depth", "side_by_side"):
        assert sorted(p.name for p in (out / folder).iterdir()) == ["000002.png", "000003.png"]
    rgb = np.asarray(Image.open(out / "rgb" / "000002.png"))
    importance = np.asarray(Image.open(out / "importance" / "000002.png"))
    assert not np.array_equal(rgb, importance)
    figure = np.asarray(Image.open(out / "side_by_side" / "000002.png").convert("RGB"))
    assert figure.shape[1] > 4 * figure.shape[0]  # five panels in a row
    assert figure.std() > 10  # not a blank page


def test_importance_of_a_map_without_sums_is_refused_before_anything_is_written(run, tmp_path):
    with LogReader(run["log"]) as log:
        gaussians = log.read_map()
        meta = log.metadata
        stamps, poses = log.read_poses()
    bare = replace(gaussians, importance_sum=np.zeros_like(gaussians.importance_sum))
    src = tmp_path / "bare.mcap"
    with LogWriter(src, meta) as writer:
        for ns, T in zip(stamps, poses, strict=True):
            writer.write_pose(T, int(ns))
        writer.write_gaussians(bare, int(stamps[-1]))
    out = tmp_path / "pics"
    r = gsc("render", src, "--seq", run["seq"], "-o", out, "--color", "importance")
    assert r.exit_code != 0
    assert "no PWAS importance" in r.output and len(r.output.strip().splitlines()) == 1
    assert not out.exists()
    with pytest.raises(MapError):
        importance_colors(bare)


def test_eval_saves_pictures_at_given_and_refined_poses(run, tmp_path):
    out = tmp_path / "pics"
    r = gsc(
        "eval",
        run["log"],
        "--seq",
        run["seq"],
        "--frames",
        "0:2",
        "--no-lpips",
        "--refine-poses",
        "2",
        "--save-images",
        out,
        "--json",
    )
    assert r.exit_code == 0, r.output
    result = json.loads(r.output)
    for folder in ("rgb", "side_by_side", "refined/rgb", "refined/side_by_side"):
        assert sorted(p.name for p in (out / folder).iterdir()) == ["000000.png", "000001.png"]
    assert len(result["images"]) == 8


def test_a_file_in_place_of_the_folder_is_one_line(run, tmp_path):
    blocker = tmp_path / "pics"
    blocker.write_text("not a folder")
    r = gsc("render", run["log"], "--seq", run["seq"], "-o", blocker / "sub")
    assert r.exit_code != 0 and len(r.output.strip().splitlines()) == 1
    assert blocker.read_text() == "not a folder"
