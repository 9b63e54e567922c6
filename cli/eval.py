"""`gsc eval`: ATE, PSNR, SSIM, MS-SSIM, LPIPS, depth L1, Gaussians and bytes of a SLAM log."""

from __future__ import annotations

import logging
from functools import partial
from pathlib import Path
from typing import Any

import click

from gscompress.pipeline import evaluate_log
from gscompress.pipeline.images import ImageOptions

from .options import (
    INPUT_FILE,
    backend_option,
    device_option,
    emit,
    force_option,
    json_option,
    recording_options,
    seq_option,
    view_options,
)
from .progress import advance, progress_bar


@click.command("eval", short_help="Score a log's map and poses: ATE, PSNR, SSIM, LPIPS.")
@click.argument("src", metavar="LOG.mcap", type=INPUT_FILE)
@seq_option(help="The RGB-D sequence the log was made from (a folder or a recording).")
@recording_options
@view_options
@click.option(
    "--refine-poses",
    type=click.IntRange(min=1),
    default=None,
    metavar="N",
    help="Also refine each frame's pose against the fixed map (N tracking iterations from the "
    "given pose) and score again there; 100 separates map from pose across agents.",
)
@backend_option()
@device_option
@click.option("--no-lpips", is_flag=True, help="Skip LPIPS (reported as not asked for).")
@click.option(
    "--save-images",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    metavar="DIR",
    help="Also write a picture of every frame scored: the render (DIR/rgb/) and observed | "
    "render | error side by side (DIR/side_by_side/); at refined poses in DIR/refined/.",
)
@click.option(
    "--leave-out",
    type=INPUT_FILE,
    multiple=True,
    metavar="FILE",
    help="Also leave out the frames that FILE (a share, or a map merged from one) carries "
    "as keyframes, to score maps on the same frames as one refined on them (repeatable). A "
    "map's own carried frames are always left out.",
)
@force_option(more=" (the pictures in the folder)")
@json_option
def eval_command(
    src: Path,
    seq: Path,
    recording: Any,
    view: dict[str, Any],
    refine_poses: int | None,
    backend: str,
    device: str,
    no_lpips: bool,
    save_images: Path | None,
    leave_out: tuple[Path, ...],
    force: bool,
    as_json: bool,
) -> None:
    """Score the map and trajectory of a SLAM log against its sequence.

    The log's final map is rendered at its estimated poses (/camera/pose, matched to the frames
    by timestamp), or at those of --poses or --poses-from, and compared with the observed frames
    on pixels with valid depth: PSNR, SSIM, MS-SSIM, LPIPS and depth L1. ATE (of the poses
    rendered at) is reported in two conventions: `ate_rmse_cm` (evo's `evo_ape -a` RMSE on
    camera centres) and `ate_splatam_cm` (the mean SplaTAM prints). A metric that cannot be
    computed is reported unavailable with the reason.

    Two agents' maps sit a few centimetres apart, each consistent with its own trajectory; at
    the other agent's poses that offset, not the map, decides the figures. --refine-poses N
    moves each frame's pose to where the fixed map explains it best (N iterations of the SLAM
    tracker, the map unchanged) and reports the metrics there too, with the median pose change.

    \b
    Examples:
      gsc eval run.mcap --seq data/room
      gsc eval run.mcap --seq data/room --every 5 --json | jq .psnr
      gsc eval B.mcap --seq data/room --frames odd --poses-from A.mcap --refine-poses 100
      gsc eval run.mcap --seq data/room --every 10 --save-images pictures/
    """
    with progress_bar("eval", "view", hidden=as_json) as bar:
        result = evaluate_log(
            src,
            seq,
            ImageOptions(
                **view,
                backend=backend,
                device=device,
                lpips=not no_lpips,
                save_images=save_images,
                force=force,
            ),
            refine_poses=refine_poses or 0,
            leave_out=leave_out,
            progress=partial(advance, bar),
            recording=recording,
        )
    emit(result, as_json, format_eval(result))


IMAGE_ROWS = (
    ("PSNR", "psnr", "{:.2f} dB"),
    ("SSIM", "ssim", "{:.4f}"),
    ("MS-SSIM", "ms_ssim", "{:.4f}"),
    ("LPIPS", "lpips", "{:.4f}"),
    ("depth L1", "depth_l1_cm", "{:.3f} cm"),
)
"""(label, result key, format) of the image metrics in the text table."""


def format_eval(r: dict[str, Any]) -> str:
    """Human-readable table of an `evaluate_log` result."""
    w, h = r["size"]
    lines = [
        f"{r['log']}  vs  {r['sequence']} (frames {r['frames']}, {w}x{h}, every {r['every']}, "
        + ("at the log's poses)" if r["own_poses"] else f"at the poses of {r['poses']})"),
        f"  {'frames':<13}{r['frames_evaluated']} rendered of {r['frames_with_pose']} with an "
        f"estimated pose ({r['frames_without_pose']} of {r['frames_selected']} without)",
    ]
    if r["frames_carried_left_out"]:
        lines.append(
            f"  {'':<13}{r['frames_carried_left_out']} left out: carried by a share and refined on"
        )
    if r["frames_without_depth"]:
        lines.append(f"  {'':<13}{r['frames_without_depth']} left out: no valid depth")
    if r["ate_rmse_cm"] is None:
        lines.append(f"  {'ATE':<13}unavailable: {r['ate_reason']}")
    else:
        lines.append(
            f"  {'ATE RMSE':<13}{r['ate_rmse_cm']:.3f} cm  (SE(3)-aligned camera centres, as "
            f"evo_ape -a; {r['ate_frames']} frames, ground truth from the {r['ground_truth']})"
        )
        lines.append(
            f"  {'ATE SplaTAM':<13}{r['ate_splatam_cm']:.3f} cm  (mean error of world-to-camera "
            "translations, as SplaTAM prints it)"
        )
    refined = r.get("refined")
    if refined is not None:
        moved = (
            f"median pose change {refined['pose_change_cm']:.2f} cm, "
            f"{refined['pose_change_deg']:.2f} deg"
            if refined["pose_change_cm"] is not None
            else "no frame refined"
        )
        lines.append(
            f"  {'':<13}{'at given poses':<16}at refined poses ({refined['iters']} iterations; "
            f"{moved})"
        )
    verbose = logging.getLogger("gscompress").isEnabledFor(logging.DEBUG)
    for label, key, fmt in IMAGE_ROWS:
        cells = [r] if refined is None else [r, refined]
        if not verbose and all(c[key] is None and _expected(c[key + "_reason"]) for c in cells):
            continue  # (a metric left out by choice or by the image size: gsc -v says why)
        texts = [
            fmt.format(c[key]) if c[key] is not None else f"unavailable: {c[key + '_reason']}"
            for c in cells
        ]
        if all(c[key] is None for c in cells):
            texts = texts[:1]  # (the same reason twice)
        lines.append(f"  {label:<13}{'  '.join(t.ljust(14) for t in texts).rstrip()}")
    lines.append(
        f"  {'map':<13}{r['gaussians']} Gaussians, {r['bytes']} bytes as a message, "
        f"{r['file_bytes']} bytes of log file"
    )
    lines.append(f"  {'time':<13}{r['seconds']:.1f} s")
    if "images" in r:
        lines.append(f"  {'pictures':<13}{images_text(r['images'])}")
    return "\n".join(lines)


def _expected(reason: str) -> bool:
    """Whether a metric is unavailable as asked (--no-lpips) or as the image size implies (MS-SSIM
    below 161 pixels a side): a note for `gsc -v eval`, not for every table."""
    return reason.startswith("not asked for") or " needs images of at least " in reason


def images_text(paths: list[str]) -> str:
    """How many pictures were written, and where."""
    if not paths:
        return "none written (no frame was rendered)"
    folders = sorted({str(Path(p).parent) for p in paths})
    return f"{len(paths)} written to {', '.join(folders)}"
