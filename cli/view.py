"""`gsc view`: see a map, its importance and a share in the browser."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import click

from .options import INPUT_FILE, check_recording_seq, recording_options, seed_option, seq_option


@click.command("view", short_help="See a map, its importance, a prune or a share in the browser.")
@click.argument("src", type=INPUT_FILE)
@click.option(
    "--port",
    type=click.IntRange(0, 65535),
    default=8080,
    show_default=True,
    help="Port to serve the page on (taken: the next free one; 0: any free one).",
)
@click.option(
    "--host",
    default="127.0.0.1",
    show_default=True,
    help="Address to listen on (0.0.0.0: every machine that can reach this one).",
)
@seq_option(
    required=False,
    help="The sequence SRC was made from: the solver button scores its candidates against "
    "these frames (else against the whole map's renders).",
)
@recording_options
@click.option(
    "--compare",
    type=INPUT_FILE,
    default=None,
    help="A second log or map file (agent B): shown alone, beside SRC, or with the "
    "share of SRC the page previews.",
)
@click.option(
    "--out-dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("."),
    show_default=True,
    help="Folder the write button puts prunes and shares in (never over an existing file).",
)
@click.option(
    "--render",
    type=click.Choice(["browser", "server"]),
    default="browser",
    show_default=True,
    help="Where the splats are drawn. browser: WebGL in the page (fluid with a GPU in the "
    "browser's machine). server: gsc's own rasterizer on this machine (CUDA when torch has "
    "it), each frame sent to the page as an image, smaller while the camera moves; for a "
    "browser without a GPU, where WebGL draws splats in software.",
)
@seed_option("Seed of the random strategy.")
def view(
    src: Path,
    port: int,
    host: str,
    seq: Path | None,
    recording: Any,
    compare: Path | None,
    out_dir: Path,
    render: str,
    seed: int,
) -> None:
    """Serve the map of SRC (a gscompress log, or a PLY or SPZ map file) as a web page.

    The page draws every Gaussian as a splat, coloured by RGB, PWAS importance (log scale,
    with a legend), opacity or kept / dropped. Its keep-ratio slider shows what `gsc prune
    --keep R --by S` keeps and its budget slider what `gsc share --budget B` sends, with that
    share's bytes in each codec; both run the commands' own code, and a button writes the
    file. A log also shows its estimated and ground-truth trajectories, its keyframe
    cameras and its map snapshots over time. Needs the [view] extra (viser).

    \b
    Examples:
      gsc view run.mcap
      gsc view run.mcap --compare agent_b.mcap --port 8081
      gsc view map.ply
      gsc view run.mcap --render server     # a browser without a GPU
    """
    from gscompress.view import MapViewer, ViewOptions

    check_recording_seq(recording, seq)
    options = ViewOptions(
        host=host,
        port=port,
        seq=seq,
        compare=compare,
        out_dir=out_dir,
        seed=seed,
        render=render,
        recording=recording,
    )
    viewer = MapViewer(src, options)
    try:  # (announced inside: a stop right after the address shows is a clean stop too)
        click.echo(f"gsc view: http://{host}:{viewer.port} (Ctrl-C to stop)", err=True)
        threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
