"""`gsc slam --resume` after Ctrl-C, SIGTERM and SIGKILL, and `gsc slam --inject`."""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.errors import DatasetError, DivergenceError, InputError, MapError
from gscompress.io.mcap_log import TOPIC_GAUSSIANS, TOPIC_POSE, TOPIC_STATS, LogReader
from gscompress.io.recover import read_messages, unfinished_files
from gscompress.pipeline import resume_slam_file, share_log, slam_file
from gscompress.pipeline.slam_run import refuse_own_settings
from gscompress.pipeline.slam_run.options import SlamOptions
from gscompress.slam.system import SlamSystem
from gscompress_cli.main import cli

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

FRAMES = 8


@pytest.fixture(scope="module")
def config_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "tiny.yaml"
    path.write_text("preset: tiny\ncheckpoint_every: 2\n")
    return path


def frames_in(path: Path) -> list[int]:
    with LogReader(path) as log:
        return [json.loads(m.data)["frame"] for _, _, m in log.iter_messages([TOPIC_STATS])]


def interrupted(seq_dir_8: Path, out: Path, frames: int = 3, **options: object) -> Path:
    """`out`: a run of `seq_dir_8` stopped by Ctrl-C after `frames` frames."""
    with pytest.raises(KeyboardInterrupt):
        slam_file(seq_dir_8, out, SlamOptions(**options), progress=stop_after(frames))
    return out


def stop_after(count: int):  # type: ignore[no-untyped-def]
    def progress(done: int, total: int, stats: dict) -> None:
        if done == count:
            raise KeyboardInterrupt

    return progress


def test_interrupted_run_is_a_valid_log_and_resumes_to_every_frame(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    out = interrupted(seq_dir_8, tmp_path / "run.mcap", config_path=config_file)
    with LogReader(out) as log:
        assert log.metadata.results["interrupted"] is True
        assert log.metadata.results["frames"] == 3
        interrupted_map = log.read_map()
    assert frames_in(out) == [0, 1, 2]

    result = resume_slam_file(seq_dir_8, out)
    assert result["frames"] == FRAMES and result["resumed_at"] == 3
    assert result["interrupted"] is False
    assert frames_in(out) == list(range(FRAMES))
    with LogReader(out) as log:
        assert {c.topic: c.messages for c in log.channels}[TOPIC_POSE] == FRAMES
        stats = [json.loads(m.data) for _, _, m in log.iter_messages([TOPIC_STATS])]
        assert log.metadata.config["checkpoint_every"] == 2  # the log's own config
    # the map went on from the interrupted one: its Gaussians that survived keep their ids,
    # and new Gaussians were numbered after every id the interrupted run had used
    fresh = [s for s in stats[3:] if s["added"] > 0]
    assert fresh and min(s["next_id"] for s in fresh) > int(interrupted_map.ids.max())

    with pytest.raises(InputError, match="finished run"):
        resume_slam_file(seq_dir_8, out)
    # (the settings resume_slam_file takes from the log: gsc slam refuses them beside --resume)
    resume = ["slam", str(seq_dir_8), "-o", str(out), "--resume"]
    r = CliRunner().invoke(cli, [*resume, "--keep", "0.5"])
    assert r.exit_code != 0 and "drop --keep" in r.output
    r = CliRunner().invoke(cli, [*resume, "--preset", "tiny", "--frames", "0:4"])
    assert r.exit_code != 0 and "drop --preset, --frames" in r.output
    with pytest.raises(InputError, match="drop `keep`"):
        refuse_own_settings((None, None, None, None, None, 0.5, None, None), False, None)
    with pytest.raises(InputError, match="drop `preset`, `frames`"):
        refuse_own_settings(("tiny", None, "0:4", None, None, None, None, None), False, None)


def test_a_resumes_summary_gives_the_speed_of_the_frames_it_ran(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    out = interrupted(seq_dir_8, tmp_path / "run.mcap", config_path=config_file)
    r = CliRunner().invoke(cli, ["slam", str(seq_dir_8), "-o", str(out), "--resume"])
    assert r.exit_code == 0, r.output
    assert f"mapped {FRAMES} frames" in r.output
    assert "(resumed after 3 frames, " in r.output and f" s/frame over {FRAMES - 3}" in r.output


def test_a_resumed_run_keeps_the_view_of_every_frame_it_restored(
    seq_dir_8: Path, tmp_path: Path
) -> None:
    from gscompress.pipeline.slam_run.start import resume_run

    config = tmp_path / "frames.yaml"
    config.write_text(
        "preset: tiny\ncheckpoint_every: 2\nmapping:\n  final_iters: 3\n  final_views: frames\n"
    )
    out = interrupted(seq_dir_8, tmp_path / "run.mcap", config_path=config)
    run = resume_run(seq_dir_8, out, "cpu", None)
    assert run.start == 3 and [v.index for v in run.system.views] == [0, 1, 2]
    assert [v.index for v in run.system.keyframes] == [0, 2]
    fresh = SlamSystem(run.config, run.system.intrinsics, total_frames=FRAMES)
    with pytest.raises(MapError, match="every restored frame"):  # the keyframes alone
        fresh.restore(
            run.system.gaussian_map(),
            [(i, float(i), np.eye(4)) for i in range(3)],
            run.system.keyframes,
            mapping_iterations=0,
            next_id=0,
            first_depth=run.system.keyframes[0].depth.numpy(),
        )
    assert len(fresh) == 0 and fresh.poses == []  # refused before any of it was taken


def test_nothing_to_resume_is_a_clear_error(seq_dir_8: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no log"):
        resume_slam_file(seq_dir_8, tmp_path / "none.mcap")


@pytest.mark.parametrize("cut", [False, True])
def test_a_share_or_pruned_log_is_not_resumed_even_cut_short(
    seq_dir_8: Path, tmp_path: Path, cut: bool
) -> None:
    from gscompress.pipeline import prune_log

    slam_file(seq_dir_8, tmp_path / "a.mcap", SlamOptions(preset="tiny", frames="0:4"))
    share_log(tmp_path / "a.mcap", tmp_path / "s.mcap", 0.2)
    prune_log(tmp_path / "a.mcap", tmp_path / "p.mcap", 0.3)
    for derived in (tmp_path / "s.mcap", tmp_path / "p.mcap"):
        if cut:  # as a full disk or a copy cut short leaves it: no summary
            derived.write_bytes(derived.read_bytes()[: derived.stat().st_size * 2 // 3])
        before = derived.read_bytes()
        with pytest.raises(InputError, match="not the log of a `gsc slam` run"):
            resume_slam_file(seq_dir_8, derived)
        assert derived.read_bytes() == before


SIGNAL_AFTER = """
import os, sys
from gscompress.slam.system import SlamSystem
from gscompress_cli.main import cli

signum, after = int(sys.argv[1]), int(sys.argv[2])
process, done = SlamSystem.process, []

def process_then_signal(self, frame):
    result = process(self, frame)
    done.append(frame)
    if len(done) == after:  # inside the frame, before it is logged
        os.kill(os.getpid(), signum)
    return result

SlamSystem.process = process_then_signal
cli(sys.argv[3:], prog_name="gsc")
"""


def _gsc_signalled(signum: int, after: int, *args: object) -> list[str]:
    """`gsc ARGS` in a process that sends itself `signum` while mapping frame `after` - 1:
    the same moment on a slow CPU and a fast GPU, where polling the log from outside raced
    a run that finished first."""
    return [sys.executable, "-c", SIGNAL_AFTER, str(int(signum)), str(after), *map(str, args)]


def _checkpoints(path: Path) -> int:
    return sum(
        1 for _, channel, _ in read_messages(path).messages if channel.topic == TOPIC_GAUSSIANS
    )


def test_killed_run_resumes_to_the_same_number_of_frames(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "killed.mcap"
    cmd = _gsc_signalled(signal.SIGKILL, 4, "slam", seq_dir_8, "-o", out, "--config", config_file)
    proc = subprocess.run(cmd, capture_output=True, timeout=300, check=False)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert not out.exists()  # nothing half-written under the final name
    (leftover,) = unfinished_files(out)
    assert _checkpoints(leftover) >= 1  # frames 0-2 were flushed, checkpoint_every 2
    done_before = len(read_messages(leftover).messages)
    assert done_before > 0
    # what tells this scene from another of its name is in the metadata written at the start
    assert len(read_messages(leftover).metadata.results["first_frame"]) == 4

    fresh = ["slam", str(seq_dir_8), "-o", str(out), "--config", str(config_file)]
    r = CliRunner().invoke(cli, fresh)  # a fresh run would leave the killed one to rot
    assert r.exit_code == 1 and f"an unfinished run of {out} is there" in r.output, r.output
    assert unfinished_files(out) == [leftover] and not out.exists()
    resume = ["slam", str(seq_dir_8), "-o", str(out), "--resume", "--json"]
    r = CliRunner().invoke(cli, [*resume, "--frames", "0:4"])  # settings come from the log
    assert r.exit_code == 2 and "drop --frames" in r.output, r.output
    r = CliRunner().invoke(cli, resume)
    assert r.exit_code == 0, r.output
    result = json.loads(r.output)
    assert result["frames"] == FRAMES and result["resumed_at"] >= 2
    assert frames_in(out) == list(range(FRAMES))
    assert unfinished_files(out) == []


def test_a_resume_killed_in_its_turn_is_resumed_from_where_it_got(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    out = interrupted(seq_dir_8, tmp_path / "twice.mcap", config_path=config_file)
    cmd = _gsc_signalled(signal.SIGKILL, 4, "slam", seq_dir_8, "-o", out, "--resume")
    proc = subprocess.run(cmd, capture_output=True, timeout=300, check=False)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert len(unfinished_files(out)) == 1  # frames 3-5 done beyond the log's 3, then killed
    assert frames_in(out) == [0, 1, 2]
    result = resume_slam_file(seq_dir_8, out)
    assert result["resumed_at"] > 3  # from the killed resume's file, not the older log
    assert frames_in(out) == list(range(FRAMES)) and unfinished_files(out) == []


def test_a_resume_takes_up_the_newest_run_not_an_older_one_further_along(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "two.mcap"
    first = _gsc_signalled(signal.SIGKILL, 6, "slam", seq_dir_8, "-o", out, "--config", config_file)
    assert subprocess.run(first, capture_output=True, timeout=300, check=False).returncode < 0
    again = _gsc_signalled(
        signal.SIGKILL,
        2,
        "slam",
        seq_dir_8,
        "-o",
        out,
        "--config",
        config_file,
        "--size",
        "48x36",
        "--force",
    )
    assert subprocess.run(again, capture_output=True, timeout=300, check=False).returncode < 0
    assert len(unfinished_files(out)) == 2
    result = resume_slam_file(seq_dir_8, out)
    assert result.get("resumed_at", 0) < 4  # the 48x36 run's start, not the older run's 4
    with LogReader(out) as log:
        assert log.metadata.config["size"] == [48, 36]
    assert frames_in(out) == list(range(FRAMES)) and unfinished_files(out) == []


def test_a_resume_takes_up_the_newest_run_of_another_scene_of_the_same_name(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    other = write_synthetic_sequence(tmp_path / "other" / seq_dir_8.name, FRAMES, (64, 48), seed=7)
    out = tmp_path / "r.mcap"
    older = _gsc_signalled(signal.SIGKILL, 6, "slam", seq_dir_8, "-o", out, "--config", config_file)
    newer = _gsc_signalled(
        signal.SIGKILL, 4, "slam", other, "-o", out, "--config", config_file, "--force"
    )
    for cmd in (older, newer):
        assert subprocess.run(cmd, capture_output=True, timeout=300, check=False).returncode < 0
    result = resume_slam_file(other, out)  # not "not recorded on this room" from the older
    assert result["frames"] == FRAMES and unfinished_files(out) == []


def test_a_log_from_before_the_fingerprint_and_its_resumes_file_are_one_run(
    tmp_path: Path,
) -> None:
    import os

    from gscompress.gaussians import random_map
    from gscompress.io.mcap_log import LogMetadata, LogWriter
    from gscompress.pipeline.slam_run.start import _furthest

    def log(path: Path, map_at: int, **results: object) -> Path:
        meta = LogMetadata(sequence="room", frames="all", config={"seed": 0}, results=results)
        written = path.with_name("written.mcap")  # (then named as a killed writer leaves it)
        with LogWriter(written, meta) as out:
            for t in range(1, 4):
                out.write_pose(np.eye(4), t)
            out.write_gaussians(random_map(5), map_at)
        return written.rename(path)

    old = log(tmp_path / "old.mcap", 3)  # written before logs recorded their first frame
    newer = log(tmp_path / ".old.mcap.1.tmp", 1, first_frame=[3.6, 0.5, 0.4, 0.3])
    os.utime(old, ns=(1, 1))  # the resume's file is the newer
    assert _furthest([old, newer])[0] == old  # one run: the one further along wins
    other = log(tmp_path / ".old.mcap.2.tmp", 0, first_frame=[1.0, 0.5, 0.4, 0.3])
    os.utime(newer, ns=(2, 2))
    assert _furthest([newer, other])[0] == other  # another scene's run, the newest, not newer


def test_a_fresh_run_with_force_replaces_an_unfinished_one(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "again.mcap"
    stale = tmp_path / ".again.mcap.99999.tmp"  # as a killed writer leaves it
    stale.write_bytes(b"\x89MCAP0\r\n")
    r = CliRunner().invoke(
        cli,
        [
            "slam",
            str(seq_dir_8),
            "-o",
            str(out),
            "--config",
            str(config_file),
            "--frames",
            "0:2",
            "--force",
        ],
    )
    assert r.exit_code == 0, r.output
    assert frames_in(out) == [0, 1] and not stale.exists()


def test_sigterm_closes_a_valid_log(seq_dir_8: Path, config_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "term.mcap"
    cmd = _gsc_signalled(signal.SIGTERM, 4, "slam", seq_dir_8, "-o", out, "--config", config_file)
    proc = subprocess.run(cmd, capture_output=True, timeout=300, check=False)
    assert proc.returncode == 130, proc.stderr
    assert f"holds 4 of {FRAMES} frames; continue with".encode() in proc.stderr
    assert b"--resume" in proc.stderr
    with LogReader(out) as log:
        assert log.metadata.results["interrupted"] is True
        done = log.metadata.results["frames"]
    # the signal came while frame 3 was being mapped: the run stopped after that frame
    assert done == 4 and frames_in(out) == [0, 1, 2, 3]


def test_a_signal_in_the_middle_of_a_frame_stops_after_that_frame(
    seq_dir_8: Path,
    config_file: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    from gscompress.slam.system import SlamSystem

    process, seen = SlamSystem.process, []

    def interrupted_process(self, frame):
        if len(self.poses) == 2:
            os.kill(os.getpid(), signal.SIGINT)  # lands while this frame is being processed
        result = process(self, frame)
        seen.append(result.gaussians)
        return result

    monkeypatch.setattr(SlamSystem, "process", interrupted_process)
    out = tmp_path / "stopped.mcap"
    with caplog.at_level(logging.WARNING), pytest.raises(KeyboardInterrupt):
        slam_file(seq_dir_8, out, SlamOptions(config_path=config_file))
    assert frames_in(out) == [0, 1, 2]  # the frame finished, and no later one started
    assert "stopping after this frame (again to stop at once)" in caplog.text
    with LogReader(out) as log:
        assert log.metadata.results["interrupted"] is True
        assert log.metadata.results["gaussians"] == len(log.read_map()) == seen[-1]


def test_a_signal_during_the_final_refinement_ends_it_and_keeps_the_map(
    tmp_path: Path,
    seq_dir_8: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    from gscompress.slam.mapper import Mapper

    config = tmp_path / "final.yaml"
    config.write_text("preset: tiny\nmapping: {final_iters: 400}\nprune: {stages: []}\n")
    refine, done = Mapper.refine, []

    def refine_then_signal(self, views, iters, rng, on_step=None, **kwargs):  # type: ignore[no-untyped-def]
        def step(loss: float) -> None:  # (and the SLAM's own, its progress, if it has one)
            if on_step is not None:
                on_step(loss)
            done.append(loss)
            if len(done) == 5:
                os.kill(os.getpid(), signal.SIGINT)  # lands during the final refinement

        return refine(self, views, iters, rng, on_step=step, **kwargs)

    monkeypatch.setattr(Mapper, "refine", refine_then_signal)
    out = tmp_path / "stopped.mcap"
    with caplog.at_level(logging.WARNING), pytest.raises(KeyboardInterrupt):
        slam_file(seq_dir_8, out, SlamOptions(config_path=config))
    assert len(done) == 5  # 5 of the 400 iterations, then the refinement ended
    assert "ending the final refinement at the next iteration" in caplog.text
    assert "stopping after this frame" not in caplog.text
    assert frames_in(out) == list(range(FRAMES))
    with LogReader(out) as log:
        results = log.metadata.results
        last = [json.loads(m.data) for _, _, m in log.iter_messages([TOPIC_STATS])][-1]
        assert results["interrupted"] is True and results["frames"] == FRAMES
        assert results["gaussians"] == len(log.read_map())  # the map refined so far
    assert last["refine_iters"] == 5
    from gscompress_cli.slam import _interrupted_text  # what `gsc slam` then says

    said = _interrupted_text(seq_dir_8, out)
    assert f"Interrupted at the end: {out} holds all {FRAMES} frames and the map" in said


def test_inject_starts_the_map_with_the_share(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    a = tmp_path / "a.mcap"
    slam_file(seq_dir_8, a, SlamOptions(config_path=config_file, frames="odd"))
    share = tmp_path / "share.mcap"
    share_log(a, share, 0.5)
    with LogReader(share) as log:
        shared = log.read_map()
        assert log.metadata.world_frame == "ground-truth:room"

    b = tmp_path / "b.mcap"
    result = slam_file(
        seq_dir_8, b, SlamOptions(config_path=config_file, frames="even", inject=share)
    )
    assert result["injected"] == len(shared)
    with LogReader(b) as log:
        first = log.read_map(0)
        step = log.metadata.provenance[-1]
    assert step["operation"]["name"] == "inject" and step["parent"] == "share.mcap"
    assert step["operation"]["own_ids_from"] == int(shared.ids.max()) + 1
    # the first snapshot (a checkpoint after two frames) still holds share Gaussians, with
    # their PWAS sums carried on (never smaller than what the share brought)
    common, in_first, in_share = np.intersect1d(first.ids, shared.ids, return_indices=True)
    assert len(common) > 0
    assert np.all(first.importance_weight[in_first] >= shared.importance_weight[in_share])


def test_inject_refuses_a_share_from_another_world_frame(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    other = write_synthetic_sequence(tmp_path / "other", 3, (64, 48), seed=1)
    a = tmp_path / "a.mcap"
    slam_file(other, a, SlamOptions(config_path=config_file))
    share = tmp_path / "share.mcap"
    share_log(a, share, 0.5)
    with pytest.raises(MapError, match="world frame"):
        slam_file(
            seq_dir_8, tmp_path / "b.mcap", SlamOptions(config_path=config_file, inject=share)
        )
    assert not (tmp_path / "b.mcap").exists()


def test_unfinished_reader_stops_at_a_truncated_tail(
    seq_dir_8: Path, config_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "full.mcap"
    slam_file(seq_dir_8, out, SlamOptions(config_path=config_file))
    data = out.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    contents = read_messages(cut)
    assert not contents.finished
    assert 0 < len(contents.messages) < len(read_messages(out).messages)
    assert contents.metadata.config["checkpoint_every"] == 2
    os.unlink(cut)


def test_unfinished_files_are_this_outputs_and_not_a_live_writers(tmp_path: Path) -> None:
    from gscompress.io.files import AtomicFile

    out = tmp_path / "run[1].mcap"  # glob characters in the name are plain characters
    killed = tmp_path / ".run[1].mcap.123.tmp"
    killed.write_bytes(b"x")
    for other in (".run1.mcap.4242.tmp", ".run[1].mcap.x.mcap.77.tmp", ".run[1].mcap.ab.tmp"):
        (tmp_path / other).write_bytes(b"x")  # another output's, or not a writer's name
    assert unfinished_files(out) == [killed]
    live = AtomicFile(out)  # a writer still at work on the same output
    try:
        assert live.tmp_path.exists() and unfinished_files(out) == [killed]
    finally:
        live.discard()


def _tiny_config(tmp_path: Path, settings: str) -> Path:
    path = tmp_path / "c.yaml"
    path.write_text("preset: tiny\n" + settings)
    return path


def _signalled_twice_in(position: int):  # type: ignore[no-untyped-def]
    """SlamSystem.process that stops at once inside the frame at `position`."""
    process = SlamSystem.process

    def signalled_twice(self, frame):  # type: ignore[no-untyped-def]
        if len(self.poses) == position:
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
        return process(self, frame)

    return signalled_twice


def test_a_second_signal_inside_a_frame_keeps_the_last_map_and_says_what_a_resume_redoes(
    seq_dir_8: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from gscompress_cli.slam import _interrupted_text

    config = _tiny_config(tmp_path, "checkpoint_every: 3\nprune: {stages: []}\n")
    out = tmp_path / "twice.mcap"
    with pytest.raises(KeyboardInterrupt):
        slam_file(
            seq_dir_8, out, SlamOptions(config_path=config), progress=stop_after(4)
        )  # a map after 4
    monkeypatch.setattr(SlamSystem, "process", _signalled_twice_in(5))  # the resumed 2nd frame
    with pytest.raises(KeyboardInterrupt):
        resume_slam_file(seq_dir_8, out)
    monkeypatch.undo()
    assert frames_in(out) == [0, 1, 2, 3, 4]  # frame 5 was cut, and no map after frame 4
    with LogReader(out) as log:
        assert log.metadata.results["map_frames"] == 4  # the map the resumed run started from
    said = _interrupted_text(seq_dir_8, out)
    assert f"holds 5 of {FRAMES} frames (its last map covers the first 4: a resume" in said
    # that map was put back (else the checkpoint after 3 frames would be the last)
    resumed = resume_slam_file(seq_dir_8, out)
    assert resumed["resumed_at"] == 4 and frames_in(out) == list(range(FRAMES))


def test_a_resume_keeps_a_stage_snapshot_that_was_a_stopped_runs_last(
    seq_dir_8: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run stopped inside a frame ends on a frame's snapshot (here the first pruning stage's),
    not an end map; the resumed run keeps it, so every stage still has its snapshot."""
    config = _tiny_config(tmp_path, "checkpoint_every: 0\n")
    out = tmp_path / "staged.mcap"
    monkeypatch.setattr(SlamSystem, "process", _signalled_twice_in(4))
    with pytest.raises(KeyboardInterrupt):
        slam_file(seq_dir_8, out, SlamOptions(config_path=config))
    monkeypatch.undo()
    resume_slam_file(seq_dir_8, out)
    with LogReader(out) as log:
        events = {
            m.log_time: json.loads(m.data).get("event")
            for _, _, m in log.iter_messages([TOPIC_STATS])
        }
        snapshot_times = [m.log_time for _, _, m in log.iter_messages([TOPIC_GAUSSIANS])]
        results = log.metadata.results
    stages = sorted(t for t, event in events.items() if event)
    assert len(stages) == 2  # both pruning stages ran, the first before the stop
    assert snapshot_times == [*stages, max(events)]  # each stage's snapshot, then the map
    assert "error" not in results and results["map_frames"] == results["frames"] == FRAMES


def test_resuming_an_injected_run_that_holds_no_map_yet_is_refused(
    seq_dir_8: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = _tiny_config(tmp_path, "checkpoint_every: 0\nprune: {stages: []}\n")
    a = tmp_path / "a.mcap"
    slam_file(seq_dir_8, a, SlamOptions(config_path=config, frames="odd"))
    share = tmp_path / "share.mcap"
    share_log(a, share, 0.5)
    b = tmp_path / "b.mcap"
    monkeypatch.setattr(SlamSystem, "process", _signalled_twice_in(2))
    with pytest.raises(KeyboardInterrupt):
        slam_file(seq_dir_8, b, SlamOptions(config_path=config, frames="even", inject=share))
    monkeypatch.undo()
    with pytest.raises(InputError, match=r"holds no map yet, so not the share .*\(`inject`"):
        resume_slam_file(seq_dir_8, b)


def test_a_resume_past_an_error_clears_it(seq_dir_8: Path, tmp_path: Path) -> None:
    broken = shutil.copytree(seq_dir_8, tmp_path / "room")
    depth = sorted((broken / "depth").glob("*.png"))[3]
    good = depth.read_bytes()
    depth.write_bytes(b"not a png")
    out = tmp_path / "e.mcap"
    with pytest.raises(DatasetError):
        slam_file(broken, out, SlamOptions(preset="tiny"))
    with LogReader(out) as log:
        assert "cannot read depth image" in log.metadata.results["error"]
    depth.write_bytes(good)
    resume_slam_file(broken, out)
    with LogReader(out) as log:
        assert "error" not in log.metadata.results and not log.metadata.results["interrupted"]


def test_a_run_whose_map_diverges_keeps_the_frames_before_with_a_finite_map(
    seq_dir_8: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = _tiny_config(tmp_path, "checkpoint_every: 2\nprune: {stages: []}\n")
    process = SlamSystem.process

    def diverging(self, frame):  # type: ignore[no-untyped-def]
        if len(self.poses) == 3:
            with torch.no_grad():
                self.mapper.params.means[0] = float("nan")
        return process(self, frame)

    monkeypatch.setattr(SlamSystem, "process", diverging)
    out = tmp_path / "diverged.mcap"
    with pytest.raises(DivergenceError, match="diverged"):
        slam_file(seq_dir_8, out, SlamOptions(config_path=config))
    assert frames_in(out) == [0, 1, 2]
    with LogReader(out) as log:
        results = log.metadata.results
        gaussians = log.read_map(-1)  # validated: the checkpoint after frame 2, not the NaN map
    assert results["map_frames"] == 2 and "DivergenceError" in results["error"]
    assert len(gaussians) > 0


def test_a_resume_on_another_scene_of_the_same_name_is_refused(
    seq_dir_8: Path, tmp_path: Path
) -> None:
    out = interrupted(seq_dir_8, tmp_path / "run.mcap", preset="tiny")
    with LogReader(out) as log:
        assert len(log.metadata.results["first_frame"]) == 4
    other = write_synthetic_sequence(tmp_path / "other" / seq_dir_8.name, FRAMES, (64, 48), seed=5)
    with pytest.raises(InputError, match=r"not recorded on this room: its first frame differs"):
        resume_slam_file(other, out)
    assert resume_slam_file(seq_dir_8, out)["frames"] == FRAMES  # the same scene goes on
