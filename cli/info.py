"""`gsc info`: what a gscompress log holds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from gscompress.pipeline import log_info

from .options import INPUT_FILE, emit, json_option


@click.command("info", short_help="Show what a log holds: map, scores, bytes, provenance.")
@click.argument("src", type=INPUT_FILE)
@json_option
def info(src: Path, as_json: bool) -> None:
    """Show the channels, snapshots, map, importance scores, bytes and provenance of SRC.

    \b
    Examples:
      gsc info run.mcap
      gsc info run.mcap --json | jq .map.gaussians
    """
    result = log_info(src)
    emit(result, as_json, format_info(result))


def format_info(info: dict[str, Any]) -> str:
    """Human-readable text of a `log_info` result."""
    lines = [
        f"{info['path']}  ({_size(info['file_bytes'])}, profile {info['profile_version'] or '?'}, "
        f"written by gscompress {info['tool_version'] or '?'})",
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
