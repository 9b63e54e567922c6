"""`gsc info`: what a gscompress log or a recording holds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from gscompress.pipeline import log_info

from .flags import with_flags
from .options import INPUT_SEQUENCE, emit, json_option, recording_options


@click.command("info", short_help="Show what a log or a recording holds.")
@click.argument("src", type=INPUT_SEQUENCE)
@recording_options
@json_option
def info(src: Path, recording: Any, as_json: bool) -> None:
    """Show what SRC holds, and say what it is: a gscompress log, a ROS 2 bag, a ROS 1 bag or
    a Foxglove recording.

    A log: its channels, snapshots, map, importance scores, bytes and provenance. A recording
    (a ROS 2 bag folder, .mcap or .db3, a ROS 1 .bag, a Foxglove MCAP): its topics with message
    counts, image sizes, encodings and rates, and the colour, depth and camera-info topics that
    `gsc slam` would read (or why it would read none; the recording options choose them as
    they do for `gsc slam`). A recording's image topics are read once.

    \b
    Examples:
      gsc info run.mcap
      gsc info run.mcap --json | jq .map.gaussians
      gsc info robot_bag
      gsc info robot.bag --rgb /camera/rgb/image_color --depth /camera/depth/image
    """
    from gscompress.pipeline.recordings import GSC_LOG, is_log, recording_info

    if is_log(src):
        result = log_info(src)
        result["kind"] = GSC_LOG
        emit(result, as_json, format_info(result))
        return
    result = recording_info(src, recording, with_flags)
    emit(result, as_json, format_recording(result))


def format_recording(info: dict[str, Any]) -> str:
    """Human-readable text of a `recording_info` result."""
    lines = [f"{info['path']}  ({info['kind']})", "topics"]
    for t in info["topics"]:
        size = t.get("size")
        detail = " ".join(
            part
            for part in (
                t.get("encoding") or "",
                f"{size[0]}x{size[1]}" if size else "",
                f"{t['rate_hz']:.1f} Hz" if t.get("rate_hz") else "",
                f"frame {t['frame_id']}" if t.get("frame_id") else "",
            )
            if part
        )
        lines.append(f"  {t['topic']:<44} {t['messages']:>7}  {t['type']}  {detail}".rstrip())
    chosen = info["slam_would_read"]
    if chosen is None:
        lines.append(f"slam      reads nothing: {info['why_not']}")
    else:
        skipped = chosen["skipped"]
        lines.append(
            f"slam      colour {chosen['rgb']}, depth {chosen['depth']}, camera info "
            f"{chosen['camera_info']} ({chosen['chosen_by']}): {chosen['frames']} frames of "
            f"{chosen['size'][0]}x{chosen['size'][1]} paired within {chosen['max_dt']:g} s, "
            f"{skipped['rgb']} colour and {skipped['depth']} depth messages without a partner"
        )
    return "\n".join(lines)


def format_info(info: dict[str, Any]) -> str:
    """Human-readable text of a `log_info` result."""
    lines = [
        f"{info['path']}  ({info.get('kind', 'gscompress log')}, {_size(info['file_bytes'])}, "
        f"profile {info['profile_version'] or '?'}, written by gscompress "
        f"{info['tool_version'] or '?'})",
    ]
    if info["sequence"]:
        lines.append(f"sequence  {info['sequence']}  frames {info['frames'] or 'all'}")
    if info["world_frame"]:
        lines.append(f"world     {info['world_frame']}")
    lines.append("channels")
    for c in info["channels"]:
        lines.append(f"  {c['topic']:<22} {c['messages']:>7}  {c['schema']} ({c['encoding']})")
    snaps = info["snapshots"]
    lines.append(
        f"snapshots {len(snaps)}: " + ", ".join(f"{s['gaussians']} ({s['codec']})" for s in snaps)
    )
    m = info.get("map")
    if not m:
        lines.append("map       none: no /gaussians channel (not a map log)")
    else:
        kind = "isotropic" if m["isotropic"] else "anisotropic"
        lines.append(
            f"map       {m['gaussians']} Gaussians, {kind}, SH degree {m['sh_degree']}, "
            f"codec {m['codec']}"
        )
        per = m["bytes_per_gaussian"]
        lines.append(
            f"bytes     {m['bytes']} B ({_size(m['bytes'])}) as a /gaussians message"
            + (f": {per:.2f} B per Gaussian" if per is not None else "")
        )
        if m["has_importance"]:
            q = m["importance_quantiles"]
            lines.append(
                f"importance scored {m['scored']}/{m['gaussians']}; min {q['q00']:.4g}  "
                f"q25 {q['q25']:.4g}  median {q['q50']:.4g}  q75 {q['q75']:.4g}  "
                f"q95 {q['q95']:.4g}  max {q['q100']:.4g}"
            )
            log = m["importance_histogram_log"]
            peak = max(log["counts"])
            if peak == 0:
                lines.append("histogram every score is 0")
            else:
                bars = "".join(" ▁▂▃▄▅▆▇█"[round(8 * c / peak)] for c in log["counts"])
                low, high = log["edges"][0], log["edges"][-1]
                zeros = f"; {log['zeros']} at 0" if log["zeros"] else ""
                lines.append(f"histogram |{bars}| log scale, {low:.4g} to {high:.4g}{zeros}")
        else:
            lines.append("importance none (run `gsc score` or `gsc slam` to get PWAS scores)")
    for step in info["provenance"]:
        op = step["operation"]
        params = " ".join(
            f"{k}={_value(v)}" for k, v in op.items() if k != "name" and v is not None
        )
        lines.append(
            f"from      {op.get('name', '?')} {params} <- {step['parent']} "
            f"(sha256 {step['parent_sha256'][:12]})"
        )
    if info["results"]:
        results = info["results"].items()
        lines.append("results   " + " ".join(f"{k}={_value(v)}" for k, v in results))
    return "\n".join(lines)


def _value(v: Any) -> str:
    """A value for reading: floats to 6 significant digits, also within lists (`--json` gives
    them whole)."""
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return str(v)


def _size(n: int) -> str:
    value = float(n)
    for unit in ("B", "KiB", "MiB"):
        if value < 1024:
            return f"{n} B" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    return f"{value:.1f} GiB"
