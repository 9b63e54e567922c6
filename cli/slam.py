"""`gsc slam`: map an RGB-D sequence with 3DGS SLAM and PWAS importance into a log."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from click.core import ParameterSource

from gscompress.io.codec import DEFAULT_CODEC

from .options import (
    INPUT_FILE,
    INPUT_SEQUENCE,
    OUTPUT_FILE,
    Ratio,
    backend_option,
    codec_option,
    command_line,
    device_option,
    emit,
    force_option,
    frames_option,
    json_option,
    recording_options,
    share_transform_option,
    size_option,
    slam_config_options,
)
from .progress import Phases, advance, progress_bar

if TYPE_CHECKING:
    from gscompress.pipeline.slam_run.options import SlamOptions


def _phases(bar: Any) -> Callable[[str, int, int | None], None]:
    """The run's phases on `bar`: the frames from before the first one, then the final
    refinement's iterations and the final scoring's views."""
    from gscompress.pipeline.slam_run import FINAL_REFINEMENT, FINAL_SCORING, FRAMES

    phases = Phases(bar, {FRAMES: "frame", FINAL_REFINEMENT: "iter", FINAL_SCORING: "view"})

    def phase(name: str, done: int, total: int | None) -> None:
        if name == FRAMES and phases.name != FRAMES:
            _start_at_loop(bar, done, total)
            phases.name = name
        phases(name, done, total)

    return phase


def _start_at_loop(bar: Any, frames_before: int, total: int | None) -> None:
    """Start the tqdm bar's count and clock where the SLAM loop starts, now.

    The bar was made before the set-up (sequence, a resumed log's replay, a first-use build of
    the render kernels); left alone, its rate and ETA would count that as the first frame's time
    and the frames a resumed log already holds as done in this run.
    """
    bar.total = total
    bar.n = bar.last_print_n = bar.initial = frames_before
    bar.start_t = bar.last_print_t = time.time()


def _interrupted_text(seq: Path, dst: Path) -> str:
    """What an interrupted run left in `dst`, and how to go on."""
    from gscompress.errors import GscError
    from gscompress.io.mcap_log import LogReader
    from gscompress.io.recover import resume_sources
    from gscompress.pipeline.slam_run import map_note

    resume = f"`gsc slam {seq} -o {dst} --resume`"
    if not resume_sources(dst):
        return "Interrupted before the first frame: nothing was written"
    try:
        with LogReader(dst) as log:
            results = log.metadata.results
        done, total = int(results["frames"]), int(results["frames_total"])
        map_frames = int(results.get("map_frames", done))
    except (GscError, OSError, KeyError, TypeError, ValueError):  # (not closed: a kill)
        return f"Interrupted: the frames done so far can be continued with {resume}"
    if not results.get("interrupted"):  # an earlier, finished log (--force) stayed
        return f"Interrupted before the first frame: {dst} was left as it was"
    note = map_note(done, map_frames)
    if done == total and not note:
        return (
            f"Interrupted at the end: {dst} holds all {total} frames and the map, its final "
            f"refinement cut short ({resume} only closes it)"
        )
    return f"Interrupted: {dst} holds {done} of {total} frames{note}; continue with {resume}"


def _modified_ns(path: Path) -> int | None:
    return path.stat().st_mtime_ns if path.exists() else None


@click.command("slam", short_help="Map a sequence with 3DGS SLAM into an MCAP log.")
@click.argument("seq", type=INPUT_SEQUENCE)
@click.option(
    "-o",
    "--output",
    "dst",
    type=OUTPUT_FILE,
    default=None,
    help="Output log (.mcap). Required unless only --save-config is asked for.",
)
@slam_config_options
@click.option(
    "--save-config",
    type=OUTPUT_FILE,
    default=None,
    help="Write the resolved config (preset + --config + options) as YAML; with -o, once the "
    "run has passed its checks and mapped its first frame.",
)
@frames_option
@recording_options
@size_option(help="Working image size WxH (default: the config's; the cpu preset uses 160x120).")
@device_option
@backend_option("the config's `backend:`, auto")
@click.option(
    "--keep",
    type=Ratio(),
    default=None,
    help="Fraction kept at each PWAS pruning stage (default: the config's, 0.3).",
)
@click.option(
    "--no-prune",
    is_flag=True,
    help="Skip the PWAS pruning stages (transparent and huge Gaussians are still removed).",
)
@click.option(
    "--inject",
    type=INPUT_FILE,
    default=None,
    help="Start the map with another agent's share (a `gsc share` log in the same world "
    "frame): its Gaussians, ids and PWAS sums, so tracking uses them from the first frame; "
    "the sender's keyframes it carries (`gsc share --keyframes`) join the run's keyframes "
    "(such a run cannot be resumed: its log does not hold them).",
)
@share_transform_option
@click.option(
    "--resume",
    is_flag=True,
    help="Continue the interrupted run whose log (or unfinished file, after a kill) is at -o, "
    "with the settings recorded in it (so no --preset, --config, --frames, --size, --backend, "
    "--keep, --no-prune or --inject).",
)
@codec_option(DEFAULT_CODEC, " The log's map snapshots; fp32 keeps the map visible in Foxglove.")
@force_option(more="; with a fresh run, also the unfinished file a killed run of -o left")
@json_option
def slam(
    seq: Path,
    dst: Path | None,
    preset: str | None,
    config_path: Path | None,
    save_config: Path | None,
    frames: object,
    recording: Any,
    size: tuple[int, int] | None,
    device: str,
    backend: str | None,
    keep: float | None,
    no_prune: bool,
    inject: Path | None,
    share_transform: Path | None,
    resume: bool,
    codec: str,
    force: bool,
    as_json: bool,
) -> None:
    """Run 3DGS RGB-D SLAM over the sequence SEQ and write an MCAP log.

    SEQ is a dataset folder (TUM, Replica) or a robot's recording: a ROS 2 bag (folder, .mcap
    or .db3), a ROS 1 .bag or a Foxglove MCAP, its topics chosen when unambiguous (else
    --rgb/--depth/--camera-info; `gsc info REC` shows the candidates).

    Per frame: track the camera, add Gaussians where the map misses the frame, optimise the
    map over a window of keyframes, and accumulate each Gaussian's PWAS importance; at 1/3 and
    2/3 of the sequence keep the top --keep fraction by importance (with the cpu preset each
    Gaussian kept then takes its own three scales and rotation). The log has the poses
    (estimated and ground truth), per-frame stats, and the map after each pruning stage and
    at the end, ready for `gsc prune`, `gsc share`, `gsc export-ply` and Foxglove.

    \b
    Examples:
      gsc synth -o demo_seq --frames 60 --size 320x240
      gsc slam demo_seq -o demo.mcap                  # cpu preset, 160x120
      gsc slam data/office --preset paper --device cuda -o office.mcap
      gsc slam demo_seq --save-config my.yaml         # edit, then --config my.yaml
      gsc slam demo_seq -o demo.mcap --resume         # after Ctrl-C or a kill
      gsc slam demo_seq --frames even --inject a_share.mcap -o b.mcap
      gsc slam robot_bag -o robot.mcap --gt-frames map camera_color_optical_frame

    Ctrl-C (or SIGTERM) stops after closing a valid log of the frames done so far; a
    checkpoint of the map is logged every `checkpoint_every` frames (config, default 20), so
    even a killed run resumes with --resume, redoing at most that many frames.
    """
    from gscompress.pipeline.slam_run.options import SlamOptions

    # what was not given stays None, so that --resume can refuse settings it would not use
    frames_given = (
        click.get_current_context().get_parameter_source("frames") != ParameterSource.DEFAULT
    )
    fresh = SlamOptions(
        preset=preset,
        config_path=config_path,
        frames=str(frames) if frames_given else None,
        size=size,
        keep=keep,
        no_prune=no_prune,
        backend=backend,
        inject=inject,
        share_transform=share_transform,
        recording=recording,
    )
    inputs = [p for p in (config_path, seq, dst, inject, share_transform) if p is not None]
    config = _config_to_save(save_config, resume, fresh, inputs, force)
    if dst is None and save_config is not None:
        from gscompress.slam.config import save_config as write_config

        write_config(config, save_config)
        click.echo(f"wrote {save_config}")
        return
    dst = _run_output(dst, resume)
    loop: dict[str, Any] = dict(device=device, codec=codec, force=force, command=command_line())
    saving = (save_config, config) if save_config is not None else None
    result = _run_with_progress(seq, dst, resume, fresh, loop, saving, as_json)
    emit(result, as_json, _mapped_text(result, dst))


def _config_to_save(
    save_config: Path | None, resume: bool, fresh: SlamOptions, inputs: list[Path], force: bool
) -> Any:
    """With --save-config, the run's resolved config once its file is checked (None without)."""
    if save_config is None:
        return None
    from gscompress.io.files import check_output
    from gscompress.slam.config import resolve_config

    if resume:
        raise click.UsageError("--save-config does not go with --resume (the log holds its config)")
    config = resolve_config(fresh.preset, fresh.config_path, **fresh.settings)
    check_output(save_config, inputs, force, ".yaml")
    return config


def _run_output(dst: Path | None, resume: bool) -> Path:
    """-o, checked: given, and with --resume naming a log or an unfinished run."""
    from gscompress.io.recover import resume_sources

    if dst is None:
        raise click.UsageError("give an output log with -o OUT.mcap (or only --save-config)")
    if resume and not resume_sources(dst):
        raise click.UsageError(f"--resume: there is no log {dst} nor an unfinished run of it")
    return dst


def _run_with_progress(
    seq: Path,
    dst: Path,
    resume: bool,
    fresh: SlamOptions,
    loop: dict[str, Any],
    saving: tuple[Path, Any] | None,
    as_json: bool,
) -> dict[str, Any]:
    """The run under a progress bar; `saving`: (--save-config's path, the config), written once
    the run has mapped its first frame. Ctrl-C exits 130 with how to resume; an error --resume
    can get past says so."""
    from gscompress.pipeline.slam_run import RESUMABLE
    from gscompress.slam.config import save_config as write_config

    before = _modified_ns(dst)
    with progress_bar("slam", "frame", hidden=as_json) as bar:
        processed = 0

        def progress(done: int, total: int, stats: dict[str, Any]) -> None:
            nonlocal processed
            processed += 1
            if processed == 1 and saving is not None:  # once the run passed its checks
                write_config(saving[1], saving[0])
            bar.set_postfix(  # counts as text: tqdm would show 10000 as "1e+4"
                frame=str(stats["frame"]),
                gaussians=str(stats["gaussians"]),
                track=f"{stats.get('loss_tracking', 0.0):.4f}",
                map=f"{stats.get('loss_mapping', 0.0):.4f}",
                s_per_frame=f"{stats['seconds'] / processed:.2f}",
                refresh=False,
            )
            advance(bar, done, total)

        try:
            return _slam_or_resume(
                seq, dst, resume, fresh, {**loop, "progress": progress, "phases": _phases(bar)}
            )
        except KeyboardInterrupt:
            bar.close()
            click.echo(_interrupted_text(seq, dst), err=True)
            raise SystemExit(130) from None
        except RESUMABLE:  # a frame or the disk: --resume goes on once it is fixed
            bar.close()
            if _modified_ns(dst) != before:  # (a log this run wrote, the error said above)
                click.echo(
                    f"Once the error below is fixed, `gsc slam {seq} -o {dst} --resume` "
                    "continues the run",
                    err=True,
                )
            raise


def _mapped_text(result: dict[str, Any], dst: Path) -> str:
    """The line a finished run prints."""
    ate = result.get("ate_rmse_cm")
    return (
        f"mapped {result['frames']} frame{'s' if result['frames'] != 1 else ''} -> "
        f"{result['gaussians']} Gaussians in {dst} "
        + (f"(started with {result['injected']} received) " if result.get("injected") else "")
        + f"({_speed(result)}"
        + (f", ATE RMSE {ate:.2f} cm" if ate is not None else "")
        + ")"
    )


def _slam_or_resume(
    seq: Path, dst: Path, resume: bool, fresh: SlamOptions, loop: dict[str, Any]
) -> dict[str, Any]:
    """The run: `slam_file` with the settings of a fresh run (`fresh`, its `SlamOptions`), or
    with --resume `resume_slam_file`, which refuses them (they are the log's); `loop`: what
    both take (--force only a fresh run's)."""
    from gscompress.pipeline import resume_slam_file, slam_file
    from gscompress.pipeline.slam_run import refuse_own_settings

    force = loop.pop("force")
    if not resume:
        return slam_file(seq, dst, fresh, force=force, **loop)
    refuse_own_settings(fresh.kept, fresh.no_prune, fresh.recording)
    return resume_slam_file(seq, dst, **loop)


def _speed(result: dict[str, Any]) -> str:
    """Seconds per frame of the frames this run processed (a resume's own)."""
    start = result.get("resumed_at")
    if start is None:
        return f"{result['seconds_per_frame']:.2f} s/frame"
    ran = result["frames"] - start
    if ran == 0:
        return f"resumed after {start} frames: none left to run"
    return f"resumed after {start} frames, {result['seconds_per_frame']:.2f} s/frame over {ran}"
