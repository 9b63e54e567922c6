"""`gsc slam` end to end on a tiny synthetic sequence, and the log it writes."""

import contextlib
import json
import logging
import os
import shutil
import subprocess
import sys

import jsonschema
import numpy as np
import pytest
import torch
from conftest import gsc

from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.errors import DatasetError
from gscompress.io.mcap_log import TOPIC_POSE, TOPIC_POSE_GT, TOPIC_STATS, LogReader, read_map
from gscompress.metrics import ate_rmse_cm
from gscompress.pipeline import slam_file
from gscompress.pipeline.slam_run import FRAMES
from gscompress.pipeline.slam_run.options import SlamOptions
from gscompress.render import resolve_backend
from gscompress.selection import keep_count
from gscompress.slam.config import load_config, preset
from gscompress_schemas import load_schema

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow


def poses(log, topic):
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    from gscompress.camera import make_transform, quat_to_rotmat

    out = []
    for _, _, message in log.iter_messages([topic]):
        p = PoseInFrame.FromString(message.data).pose
        q = [p.orientation.w, p.orientation.x, p.orientation.y, p.orientation.z]
        out.append(
            make_transform(quat_to_rotmat(np.array(q)), [p.position.x, p.position.y, p.position.z])
        )
    return np.array(out)


@pytest.fixture(scope="module")
def slam_log(seq_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "run.mcap"
    r = gsc("slam", seq_dir, "--preset", "tiny", "-o", out)
    assert r.exit_code == 0, r.output
    assert "mapped 6 frames" in r.output and "ATE RMSE" in r.output
    return out


def test_log_has_poses_stats_snapshots_and_metadata(slam_log):
    schema = load_schema("slam_stats.v1.schema.json")
    with LogReader(slam_log) as log:
        counts = {c.topic: c.messages for c in log.channels}
        assert counts["/camera/pose"] == counts["/camera/pose_gt"] == counts["/tf"] == 6
        assert counts["/slam/stats"] == 6 and counts["/camera/calibration"] == 1
        assert counts["/gaussians"] == 3  # two pruning stages and the end
        stats = [json.loads(m.data) for _, _, m in log.iter_messages([TOPIC_STATS])]
        est, gt = poses(log, TOPIC_POSE), poses(log, TOPIC_POSE_GT)
        meta = log.metadata
        final = log.read_map()
    for record in stats:
        jsonschema.validate(record, schema)
    assert [s["frame"] for s in stats] == list(range(6))
    assert [s.get("event") for s in stats] == [
        None,
        "prune-stage-1",
        None,
        "prune-stage-2",
        None,
        None,
    ]
    assert stats[-1]["gaussians"] == len(final) and final.has_importance
    assert set(stats[1]["ms"]) >= {"tracking", "densification", "mapping", "pwas", "pruning"}
    ate = ate_rmse_cm(gt, est)
    assert np.isfinite(ate) and ate < 10.0
    assert meta.results["ate_rmse_cm"] == pytest.approx(ate)
    assert meta.results["frames"] == 6 and not meta.results["interrupted"]
    device = torch.device(meta.results["device"])  # auto: what this machine has
    assert meta.results["render_backend"] == resolve_backend("auto", device)
    assert meta.config["preset"] == "tiny" and meta.sequence == "room" and meta.frames == "all"
    assert meta.command.startswith("gsc")


def test_offline_commands_accept_the_log(slam_log, tmp_path):
    r = gsc("info", slam_log, "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["map"]["has_importance"]
    assert json.loads(r.output)["world_frame"] == "ground-truth:room"
    assert "world     ground-truth:room" in gsc("info", slam_log).output
    r = gsc("prune", slam_log, "--keep", "0.5", "-o", tmp_path / "p.mcap")
    assert r.exit_code == 0, r.output
    r = gsc("share", "--budget", "0.2", slam_log, tmp_path / "s.mcap")
    assert r.exit_code == 0, r.output
    r = gsc("export-ply", slam_log, "-o", tmp_path / "m.ply")
    assert r.exit_code == 0, r.output
    assert len(read_map(tmp_path / "p.mcap")) == keep_count(len(read_map(slam_log)), 0.5)


def test_config_save_load_and_no_prune(seq_dir, tmp_path):
    cfg = tmp_path / "c.yaml"
    r = gsc(
        "slam", seq_dir, "--preset", "tiny", "--no-prune", "--keep", "0.4", "--save-config", cfg
    )
    assert r.exit_code == 2 and "--keep does not go with --no-prune" in r.output
    assert not cfg.exists()
    r = gsc("slam", seq_dir, "--preset", "tiny", "--no-prune", "--save-config", cfg)
    assert r.exit_code == 0, r.output
    config = load_config(cfg)
    assert config.prune.stages == ()
    assert config.mapping == preset("tiny").mapping
    out = tmp_path / "n.mcap"
    r = gsc("slam", seq_dir, "--config", cfg, "--frames", "0:4", "--size", "48x36", "-o", out)
    assert r.exit_code == 0, r.output
    with LogReader(out) as log:
        counts = {c.topic: c.messages for c in log.channels}
        assert counts["/gaussians"] == 1 and counts["/camera/pose"] == 4
        assert log.metadata.config["size"] == [48, 36] and log.metadata.frames == "0:4"
    r = gsc("slam", seq_dir, "--preset", "tiny", "-o", out)
    assert r.exit_code != 0 and "exists" in r.output


def test_bad_config_and_missing_output_are_one_line_errors(seq_dir, tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("mapping:\n  iterz: 3\n")
    r = gsc("slam", seq_dir, "--config", cfg, "-o", tmp_path / "x.mcap")
    assert r.exit_code == 1 and "unknown key 'mapping.iterz'" in r.output
    assert not (tmp_path / "x.mcap").exists()
    r = gsc("slam", seq_dir)
    assert r.exit_code == 2 and "-o OUT.mcap" in r.output
    r = gsc("slam", seq_dir, "-o", tmp_path / "none.mcap", "--resume")
    assert r.exit_code == 2 and "no log" in r.output
    cfg.write_text("preset: tiny\nseed: -1\n")
    r = gsc("slam", seq_dir, "--config", cfg, "-o", tmp_path / "x.mcap")
    assert r.exit_code == 1 and "seed must be >= 0" in r.output
    r = gsc("slam", seq_dir, "-o", tmp_path / "x.mcap", "--share-transform", cfg)
    assert r.exit_code == 2 and "needs --inject (see 'cli slam --help')" in r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml"]


def test_no_output_lands_in_the_sequence_and_save_config_waits_for_the_run(
    seq_dir, slam_log, tmp_path
):
    seq = tmp_path / "room"
    shutil.copytree(seq_dir, seq)
    before = {p: p.read_bytes() for p in seq.rglob("*") if p.is_file()}
    for args in (
        ("slam", seq, "--preset", "tiny", "-o", seq / "depth.txt"),
        ("slam", seq, "--save-config", seq / "rgb.txt"),
        ("score", slam_log, "--seq", seq, "-o", seq / "groundtruth.txt"),
        ("merge", slam_log, slam_log, "--seq", seq, "-o", seq / "rgb" / "x.mcap"),
    ):
        r = gsc(*args, "--force")
        assert r.exit_code == 1 and "inside the input folder" in r.output, (args, r.output)
    assert {p: p.read_bytes() for p in seq.rglob("*") if p.is_file()} == before
    # a config asked for beside a run is written only once the run has passed its checks
    out, cfg = tmp_path / "o.mcap", tmp_path / "c.yaml"
    r = gsc("slam", seq, "--preset", "tiny", "--frames", "20:30", "-o", out, "--save-config", cfg)
    assert r.exit_code == 1 and "selects none" in r.output
    r = gsc("slam", seq, "--preset", "tiny", "-o", out, "--save-config", out)
    assert r.exit_code == 1 and "also an input" in r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["room"]
    r = gsc("slam", seq, "--preset", "tiny", "--frames", "0:2", "-o", out, "--save-config", cfg)
    assert r.exit_code == 0, r.output
    assert load_config(cfg) == preset("tiny")


def test_keyboard_interrupt_leaves_a_readable_log_of_the_frames_done(tmp_path):
    sequence = synthetic_sequence(6, (48, 36))
    out = tmp_path / "cut.mcap"

    def stop_after_three(done, total, stats):
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        slam_file(
            None,
            out,
            SlamOptions(preset="tiny", no_prune=True),
            progress=stop_after_three,
            sequence=sequence,
        )
    with LogReader(out) as log:
        counts = {c.topic: c.messages for c in log.channels}
        assert counts["/camera/pose"] == 3 and counts["/slam/stats"] == 3
        assert counts["/gaussians"] == 1
        assert log.metadata.results["interrupted"] and log.metadata.results["frames"] == 3
        final = log.read_map()
    assert len(final) > 0 and final.has_importance


def test_render_kernels_are_ready_before_the_first_timed_frame(monkeypatch, tmp_path):
    """A first-use build of the render kernels (C++: under a minute; gsplat's CUDA ones: minutes)
    must not count as frame 0's time, on whichever backend the run picks."""
    from gscompress.render import cpu as cpu_backend
    from gscompress.render import gsplat_backend
    from gscompress.render.core import gsplat_available

    if torch.cuda.is_available() and not gsplat_available():
        pytest.skip("pure torch on CUDA has no kernels to build")
    from gscompress.slam.system import SlamSystem

    events: list[str] = []
    process = SlamSystem.process

    def recorded(load):  # type: ignore[no-untyped-def]
        def loading():  # type: ignore[no-untyped-def]
            events.append("kernels")
            return load()

        return loading

    def processing(self, frame):  # type: ignore[no-untyped-def]
        events.append("frame")
        return process(self, frame)

    monkeypatch.setattr(cpu_backend, "load_extension", recorded(cpu_backend.load_extension))
    monkeypatch.setattr(gsplat_backend, "gsplat_kernels", recorded(gsplat_backend.gsplat_kernels))
    monkeypatch.setattr(SlamSystem, "process", processing)
    seconds: list[float] = []

    def progress(done, total, stats):  # type: ignore[no-untyped-def]
        seconds.append(stats["seconds"])

    sequence = synthetic_sequence(2, (32, 24))
    result = slam_file(
        None,
        tmp_path / "run.mcap",
        SlamOptions(preset="tiny"),
        sequence=sequence,
        progress=progress,
    )
    assert events[0] == "kernels" and events.count("frame") == 2
    # the bar's s/frame and the summary's come from one clock, started after the build
    assert len(seconds) == 2 and 0 < seconds[0] < seconds[1] <= result["seconds"] + 1e-3


def test_progress_bar_counts_only_the_frames_this_run_does(monkeypatch, caplog, seq_dir, tmp_path):
    """The bar's rate and ETA start with the frame loop: a slow set-up (a first-use kernel build,
    here a sleep) is not the first frame's time, and the frames of a resumed log are not done by
    this run."""
    import logging
    import time

    import gscompress.render as render
    import gscompress_cli.slam as slam_command

    resolve, make_bar = render.resolve_backend, slam_command.progress_bar
    ready: list[float] = []

    def slow_resolve(*args, **kwargs):  # type: ignore[no-untyped-def]
        time.sleep(0.5)
        ready.append(time.time())
        return resolve(*args, **kwargs)

    bars = []

    @contextlib.contextmanager
    def kept_bar(*args, **kwargs):  # type: ignore[no-untyped-def]
        with make_bar(*args, **kwargs) as bar:
            bars.append(bar)
            yield bar

    def stop_after_two(done, total, stats):  # type: ignore[no-untyped-def]
        if done == 2:
            raise KeyboardInterrupt

    out = tmp_path / "run.mcap"
    with pytest.raises(KeyboardInterrupt):
        slam_file(seq_dir, out, SlamOptions(preset="tiny"), progress=stop_after_two)
    monkeypatch.setattr(render, "resolve_backend", slow_resolve)
    monkeypatch.setattr(slam_command, "progress_bar", kept_bar)
    caplog.set_level(logging.INFO)  # the bar shows at gsc's default level, not under -q
    frames_end: list[tuple[int, int, float]] = []  # the bar as the frames end
    phases = slam_command._phases

    def watched(bar):  # type: ignore[no-untyped-def]
        phase = phases(bar)

        def watch(name, done, total):  # type: ignore[no-untyped-def]
            if name != FRAMES and not frames_end:
                frames_end.append((bar.initial, bar.n, bar.start_t))
            phase(name, done, total)

        return watch

    monkeypatch.setattr(slam_command, "_phases", watched)
    r = gsc("slam", seq_dir, "-o", out, "--resume")
    assert r.exit_code == 0, r.output
    assert len(bars) == 1
    ((initial, n, start_t),) = frames_end
    assert initial == 2 and n == 6  # 4 frames done by this run, counted from 2
    assert start_t >= ready[-1] - 0.05  # the clock started after the set-up


def test_every_phase_of_a_run_reports_its_progress(tmp_path):
    """The frames' phase starts before the first frame (whose mapping may take a while), and
    the final refinement and the final scoring report each step, not only when they end."""
    from gscompress.pipeline.slam_run import FINAL_REFINEMENT, FINAL_SCORING

    events: list[tuple[str, int, int | None]] = []
    frames_done: list[int] = []

    def phases(name, done, total):  # type: ignore[no-untyped-def]
        events.append((name, done, total))

    def progress(done, total, stats):  # type: ignore[no-untyped-def]
        frames_done.append(len(events))

    config = preset("tiny").with_overrides(**{"mapping.final_iters": 7})
    slam_file(
        None,
        tmp_path / "run.mcap",
        config=config,
        sequence=synthetic_sequence(3, (32, 24)),
        progress=progress,
        phases=phases,
    )
    assert events[0] == (FRAMES, 0, 3) and frames_done[0] == 1  # before the first frame
    refining = [e for e in events if e[0] == FINAL_REFINEMENT]
    assert refining == [(FINAL_REFINEMENT, k, 7) for k in range(8)]
    scoring = [e for e in events if e[0] == FINAL_SCORING]
    assert scoring == [(FINAL_SCORING, k, 3) for k in range(4)]
    assert events.index(refining[-1]) < events.index(scoring[0])


def test_cli_preset_names_are_the_presets() -> None:
    from gscompress.slam.config import PRESETS
    from gscompress_cli.options import PRESET_NAMES

    assert set(PRESET_NAMES) == set(PRESETS)


def test_threads_option_sets_torch_and_openmp_threads(
    seq_dir, tmp_path, monkeypatch, threads_restored
):
    import torch

    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    r = gsc(
        "--threads",
        "1",
        "slam",
        seq_dir,
        "-o",
        tmp_path / "t.mcap",
        "--preset",
        "tiny",
        "--size",
        "32x24",
        "--frames",
        "0:2",
    )
    assert r.exit_code == 0, r.output
    assert torch.get_num_threads() == 1 and os.environ["OMP_NUM_THREADS"] == "1"
    assert gsc("--threads", "0", "info", tmp_path / "t.mcap").exit_code == 2


def test_slam_and_merge_do_not_import_torch_dynamo(seq_dir, tmp_path):
    """torch.optim's first use imports torch._dynamo, seconds of start-up on a 2-core machine
    (as long as importing torch itself); the map's own Adam keeps `gsc slam` and `gsc merge`
    from paying it. A fresh interpreter, since other tests may have imported it."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from gscompress_cli.main import cli\n"
        f"a, s, b = [{str(tmp_path)!r} + n for n in ('/a.mcap', '/s.mcap', '/m.mcap')]\n"
        f"args = [['slam', {str(seq_dir)!r}, '--preset', 'tiny', '-o', a],\n"
        "        ['share', a, s, '--budget', '0.5'],\n"
        f"        ['merge', a, s, '--seq', {str(seq_dir)!r}, '--iters', '2', '-o', b]]\n"
        "for argv in args:\n"
        "    try:\n"
        "        cli(argv)\n"
        "    except SystemExit as e:\n"
        "        assert not e.code, e.code\n"
        "print('dynamo' if 'torch._dynamo' in sys.modules else 'no dynamo')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().endswith("no dynamo"), done.stdout[-2000:]


def test_force_never_writes_over_a_file_the_command_reads(seq_dir, slam_log, tmp_path):
    config = tmp_path / "my.yaml"
    config.write_text("tracking:\n  iters: 2\n")
    transform = tmp_path / "T.txt"
    transform.write_text("0 0 0 0 0 0 1\n")
    share = tmp_path / "share.mcap"
    r = gsc("share", slam_log, share, "--budget", "0.5")
    assert r.exit_code == 0, r.output
    kept = {p: p.read_bytes() for p in (config, transform, share, slam_log)}
    inject = ("--inject", share, "--share-transform", transform)
    for args in (
        ("slam", seq_dir, "--preset", "tiny", "--config", config, "-o", config),
        ("slam", seq_dir, "--preset", "tiny", *inject, "-o", transform),
        (
            "slam",
            seq_dir,
            "--preset",
            "tiny",
            *inject,
            "-o",
            tmp_path / "b.mcap",
            "--save-config",
            share,
        ),
        ("merge", slam_log, share, "--iters", "0", "--share-transform", transform, "-o", transform),
    ):
        r = gsc(*args, "--force")
        assert r.exit_code == 1 and "also an input" in r.output, (args, r.output)
    r = gsc("slam", seq_dir, "--save-config", slam_log, "--force")  # a config over a log
    assert r.exit_code == 1 and "writes a YAML config, not an MCAP log" in r.output
    assert {p: p.read_bytes() for p in kept} == kept


def test_a_file_system_refusal_is_a_one_line_error(seq_dir, slam_log, tmp_path):
    long_name = tmp_path / ("a" * 300 + ".mcap")  # longer than any file system allows
    for args in (
        ("prune", slam_log, "--keep", "0.5", "-o", long_name),
        ("slam", seq_dir, "--preset", "tiny", "-o", long_name),
    ):
        r = gsc(*args)
        assert r.exit_code == 1 and isinstance(r.exception, SystemExit), r.exception
        assert r.output.count("\n") == 1 and "File name too long" in r.output, r.output
    if os.geteuid() != 0:  # the superuser writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        r = gsc("prune", slam_log, "--keep", "0.5", "-o", locked / "p.mcap")
        assert r.exit_code == 1 and "cannot write in" in r.output, r.output
        assert not list(locked.iterdir())


def test_progress_bar_shows_counts_as_numbers(monkeypatch, seq_dir, tmp_path):
    """tqdm shortens a round count to scientific notation ("gaussians=1e+4"); the bar must show
    the count as it is."""
    import gscompress.pipeline as pipeline
    import gscompress_cli.slam as slam_command

    make_bar = slam_command.progress_bar
    bars = []

    @contextlib.contextmanager
    def kept_bar(*args, **kwargs):  # type: ignore[no-untyped-def]
        with make_bar(*args, **kwargs) as bar:
            bars.append(bar)
            yield bar

    def fake_slam_file(*args, progress, **kwargs):  # type: ignore[no-untyped-def]
        progress(1, 1, {"frame": 10000, "gaussians": 20000, "seconds": 1.0})
        return {"frames": 1, "gaussians": 20000, "seconds_per_frame": 1.0}

    monkeypatch.setattr(slam_command, "progress_bar", kept_bar)
    monkeypatch.setattr(pipeline, "slam_file", fake_slam_file)
    r = gsc("slam", seq_dir, "-o", tmp_path / "run.mcap")
    assert r.exit_code == 0, r.output
    (bar,) = bars
    assert "frame=10000" in bar.postfix and "gaussians=20000" in bar.postfix, bar.postfix


def test_a_size_too_small_to_map_is_refused_and_an_enlarging_one_is_warned(
    seq_dir, tmp_path, caplog
):
    out = tmp_path / "small.mcap"
    r = gsc("slam", seq_dir, "--preset", "tiny", "--size", "15x12", "-o", out)
    assert r.exit_code == 2 and "working size 15x12 is too small to map" in r.output
    assert not out.exists()
    with caplog.at_level(logging.WARNING, logger="gscompress.pipeline.slam_run"):
        slam_file(
            seq_dir, tmp_path / "own.mcap", SlamOptions(preset="tiny", frames="0:2", no_prune=True)
        )
        assert "enlarges" not in caplog.text
        slam_file(
            seq_dir,
            tmp_path / "big.mcap",
            SlamOptions(preset="tiny", frames="0:2", size=(96, 72), no_prune=True),
        )
    assert "working size 96x72 enlarges room's 64x48 frames" in caplog.text


def test_a_settings_error_partway_says_to_run_afresh_not_to_resume(seq_dir, tmp_path, caplog):
    out = tmp_path / "k.mcap"
    with caplog.at_level(logging.WARNING, logger="gscompress.pipeline.slam_run"):
        r = gsc("slam", seq_dir, "--preset", "tiny", "--keep", "0.00001", "-o", out)
    assert r.exit_code == 1 and "rounds to none" in r.output, r.output
    assert "run afresh with the settings changed (--force replaces the log)" in caplog.text
    assert "--resume" not in r.output and "resume starts again" not in caplog.text
    with LogReader(out) as log:  # the frames before the first stage are kept all the same
        assert 0 < log.metadata.results["frames"] < 6


def test_a_passing_error_partway_is_not_called_a_settings_one(
    seq_dir, tmp_path, caplog, monkeypatch
):
    from gscompress.slam.system import SlamSystem

    process = SlamSystem.process

    def short_of_memory(self, frame):  # type: ignore[no-untyped-def]
        if len(self.poses) == 3:
            raise MemoryError
        return process(self, frame)

    monkeypatch.setattr(SlamSystem, "process", short_of_memory)
    with (
        caplog.at_level(logging.WARNING, logger="gscompress.pipeline.slam_run"),
        pytest.raises(MemoryError),
    ):
        slam_file(seq_dir, tmp_path / "m.mcap", SlamOptions(preset="tiny", no_prune=True))
    assert "holds the 3 frame(s) done before the error" in caplog.text
    assert "run afresh" not in caplog.text


def test_an_error_partway_keeps_the_frames_done_and_says_so(seq_dir, tmp_path, caplog):
    broken = shutil.copytree(seq_dir, tmp_path / "room")
    sorted((broken / "depth").glob("*.png"))[3].write_bytes(b"not a png")  # the 4th frame's
    out = tmp_path / "b.mcap"
    with (
        caplog.at_level(logging.WARNING, logger="gscompress.pipeline.slam_run"),
        pytest.raises(DatasetError, match="cannot read depth image"),
    ):
        slam_file(broken, out, SlamOptions(preset="tiny", no_prune=True))
    assert f"{out} holds the 3 frame(s) done before the error" in caplog.text
    with LogReader(out) as log:
        assert log.metadata.results["frames"] == 3 and log.metadata.results["interrupted"]
        assert "cannot read depth image" in log.metadata.results["error"]
        assert len(log.read_map()) > 0
    # the command says how to go on (the library does not: an experiment reruns instead)
    assert "--resume" not in caplog.text
    out.unlink()
    r = gsc("slam", broken, "--preset", "tiny", "--no-prune", "-o", out)
    assert r.exit_code == 1 and "cannot read depth image" in r.output
    assert (
        f"Once the error below is fixed, `gsc slam {broken} -o {out} --resume` continues the run"
    ) in " ".join(r.output.split())
    r = gsc("slam", broken, "--preset", "tiny", "-o", out)  # refused: this run wrote nothing
    assert r.exit_code == 1 and "exists" in r.output and "--resume" not in r.output
    # an error of the settings: --resume (which takes none) would only repeat it
    r = gsc("slam", seq_dir, "--preset", "tiny", "--keep", "0.0001", "-o", tmp_path / "k.mcap")
    assert r.exit_code == 1 and "raise the keep ratio (--keep, prune.keep)" in r.output
    assert "--resume" not in r.output


def test_an_interrupt_before_the_first_frame_says_nothing_was_written(seq_dir, slam_log, tmp_path):
    from gscompress_cli.slam import _interrupted_text

    assert "nothing was written" in _interrupted_text(seq_dir, tmp_path / "none.mcap")
    # with --force over a finished log, cut before the loop: the old log is still there
    assert f"{slam_log} was left as it was" in _interrupted_text(seq_dir, slam_log)


def test_backend_option_overrides_the_config_and_is_refused_on_resume(seq_dir, tmp_path):
    out = tmp_path / "torch.mcap"
    r = gsc("slam", seq_dir, "--preset", "tiny", "--frames", "0:2", "--backend", "torch", "-o", out)
    assert r.exit_code == 0, r.output
    with LogReader(out) as log:
        assert log.metadata.config["backend"] == "torch"
        assert log.metadata.results["render_backend"] == "torch"
    r = gsc("slam", seq_dir, "-o", out, "--resume", "--backend", "cpu")
    assert r.exit_code == 2 and "drop --backend" in r.output
    r = gsc("slam", seq_dir, "--preset", "tiny", "--backend", "cuda", "-o", tmp_path / "x.mcap")
    assert r.exit_code == 2 and "'cuda' is not one of" in r.output


def test_verbose_adds_each_frames_stats_and_quiet_keeps_to_warnings(seq_dir, tmp_path):
    def stderr(*flags: str) -> str:
        out = tmp_path / f"v{len(flags)}{'q' if '-q' in flags else ''}.mcap"
        args = ["slam", str(seq_dir), "--preset", "tiny", "--frames", "0:2", "-o", str(out)]
        proc = subprocess.run(
            [sys.executable, "-m", "gscompress_cli", *flags, *args],
            capture_output=True,
            text=True,
            timeout=300,
            check=True,
        )
        return proc.stderr

    assert "DEBUG gscompress.pipeline.slam_run: frame 2 of 2: {'frame': 1," in stderr("-v")
    assert "DEBUG" not in stderr() and "DEBUG" not in stderr("-q")
