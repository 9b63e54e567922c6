"""`gsc export-traj`: write a log's trajectory as TUM text for evo and other tools."""

from __future__ import annotations

from pathlib import Path

import click

from gscompress.pipeline import export_trajectory

from .options import INPUT_FILE, emit, force_option, json_option, output_option


@click.command("export-traj", short_help="Write a log's trajectory as TUM text (for evo).")
@click.argument("src", type=INPUT_FILE)
@output_option("Output TUM trajectory (.txt): `timestamp tx ty tz qx qy qz qw` per pose.")
@click.option(
    "--ground-truth",
    is_flag=True,
    help="Write the log's ground-truth poses (/camera/pose_gt) instead of the estimate.",
)
@force_option()
@json_option
def export_traj(src: Path, dst: Path, ground_truth: bool, force: bool, as_json: bool) -> None:
    """Write the camera-to-world poses of the SLAM log SRC as a TUM trajectory.

    Each line is a frame's timestamp and pose (`/camera/pose`, or `/camera/pose_gt` with
    --ground-truth), in the log's world frame: what evo, and `gsc score --poses`, read.

    \b
    Examples:
      gsc export-traj run.mcap -o est.txt
      gsc export-traj run.mcap -o gt.txt --ground-truth
      evo_ape tum gt.txt est.txt -a             # the ATE gsc eval reports as ate_rmse_cm
    """
    result = export_trajectory(src, dst, ground_truth=ground_truth, force=force)
    emit(result, as_json, f"wrote {dst}: {result['poses']} poses from {result['topic']}")
