"""`gsc share`: cut a budgeted top-K share of a map for another agent."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from gscompress.io.codec import DEFAULT_SHARE_CODEC, PRECISIONS
from gscompress.io.keyframes import MAX_CARRIED
from gscompress.ops.budget import Budget
from gscompress.pipeline import share_log
from gscompress.pipeline.share.options import SOLVED, ShareOptions
from gscompress.selection import STRATEGIES

from .options import (
    INPUT_FILE,
    OUTPUT_FILE,
    BudgetParam,
    check_recording_seq,
    codec_option,
    command_line,
    emit,
    fold_option,
    force_option,
    ids_option,
    json_option,
    log_refiner,
    output_path,
    refine_options,
    refined_text,
    seed_option,
    sums_option,
)
from .progress import Phases, progress_bar


@click.command("share", short_help="Cut a budgeted top share of a map for another agent.")
@click.argument("src", type=INPUT_FILE)
@click.argument("dst", type=OUTPUT_FILE, required=False)
@click.option(
    "-o",
    "--output",
    type=OUTPUT_FILE,
    default=None,
    help="The share log (.mcap), as the other commands take it; or give it as DST.",
)
@click.option(
    "--budget",
    type=BudgetParam(),
    default="0.2",
    show_default=True,
    help="A fraction of the map's Gaussians in (0, 1] (0.2 or 20%), or the most bytes the share "
    "file may take, with a unit: B, kB, MB, GB (powers of 1000) or KiB, MiB, GiB (e.g. 50kB, "
    "1.5MiB; the prefix in either case, so 50KB is 50 kB; a lowercase b, bits, is refused), or "
    "a percentage of the map's bytes at fp32 (5%bytes).",
)
@click.option(
    "--strategy",
    "--by",
    type=click.Choice(STRATEGIES),
    default="pwas",
    show_default=True,
    help="What to rank Gaussians by (--by, as in `gsc prune`, is the same option).",
)
@codec_option(DEFAULT_SHARE_CODEC)
@click.option(
    "--precision",
    type=click.Choice(PRECISIONS),
    default=None,
    hidden=True,
    help="Deprecated: --codec fp32|fp16 says the same.",
)
@sums_option
@ids_option
@fold_option
@click.option(
    "--spread/--no-spread",
    default=False,
    show_default=True,
    help="Spread the strategy's order over space: the best Gaussian of each of K distinct "
    "places before any place gets a second one (space cut by ever finer grids). Off: the K "
    "highest scores, wherever they cluster.",
)
@click.option(
    "--ply",
    type=OUTPUT_FILE,
    default=None,
    help="Also write the share as a float32 3DGS PLY file (the values the receiver decodes).",
)
@click.option(
    "--solve",
    is_flag=True,
    help="Choose the codec (and whether to send the PWAS sums) that give the best picture for "
    "a byte budget: each candidate is cut to the most Gaussians that fit, rendered at a few "
    "of the log's keyframes and scored against the frames of --seq (else against the whole "
    "map's renders); each with and without --fold. An explicit --codec, --no-sums or "
    "--fold/--no-fold constrains the search. Needs torch.",
)
@click.option(
    "--align-to",
    type=INPUT_FILE,
    default=None,
    help="The receiver's log, when its world frame is not SRC's: the share is cut already "
    "expressed in that frame, the transform found as `gsc align SRC ALIGN_TO` finds it (and "
    "refused as it refuses); the receiver merges it without --share-transform.",
)
@click.option(
    "--for",
    "receiver",
    type=INPUT_FILE,
    default=None,
    help="The receiver's log: send first the Gaussians its camera has not seen. Only its "
    "estimated poses (up to 64, spread over its run) and calibration are read, what the "
    "receiver would send (28 bytes a pose, counted in a byte budget); the map is rendered "
    "from them and a Gaussian drawing under one pixel there counts as unseen. In the "
    "receiver's world frame: with another frame, add --align-to. Needs torch.",
)
@click.option(
    "--keyframes",
    "keyframes",
    type=click.IntRange(min=0, max=MAX_CARRIED),
    default=0,
    show_default=True,
    help="Also send this many of the sender's keyframes, spread over its run (colour as JPEG, "
    "depth as 16-bit PNG, the estimated pose; needs --seq), so that `gsc merge` refines the "
    "merged map on the sender's views as well as the receiver's. A byte budget counts their "
    "bytes too (14-19 kB each at 160x120), leaving fewer Gaussians.",
)
@refine_options
@seed_option("Seed of the random strategy and of the refinement's view order.")
@force_option()
@json_option
def share(
    src: Path,
    dst: Path | None,
    output: Path | None,
    budget: Budget,
    strategy: str,
    codec: str,
    precision: str | None,
    sums: bool,
    ids: bool,
    fold: bool,
    spread: bool,
    ply: Path | None,
    solve: bool,
    align_to: Path | None,
    receiver: Path | None,
    keyframes: int,
    refine_iters: int,
    anisotropic: bool,
    seq: Path | None,
    recording: Any,
    device: str,
    seed: int,
    force: bool,
    as_json: bool,
) -> None:
    """Write the top BUDGET share of the map in SRC to DST or -o (a small gscompress log).

    The share holds the selected Gaussians with their PWAS score and sums (or, with --no-sums,
    the score alone) and, with --ids, their ids, and records its source, strategy, budget,
    codec, bytes and the selected / total counts. Each Gaussian left out is folded into the
    nearest one sent (--no-fold: left out). It is stored compact by default (quantised,
    compressed columns: about 10 bytes per Gaussian with the PWAS score and sums, 8-9 with
    --no-sums, about 2 more with --ids, against 76 at fp32); --codec fp32 or fp16 sends a
    foxglove.PointCloud that Foxglove draws.

    A fraction budget sends round(fraction x N) Gaussians. A byte budget sends the most
    Gaussians whose share file fits in it (the whole file as written: framing, schema,
    metadata and map, the bytes that cross the link); it is never exceeded. The command line
    and file names it records count as 256 bytes whatever their length, so the same budget
    gives the same share from any folder and under any name. `gsc info` shows a share's codec
    and bytes.

    With --refine N the selected Gaussians are refined on the sender's own frames before they
    are sent (--seq: the sequence SRC was made from); a byte budget still bounds the file of
    the refined values (which may compress a little less well, leaving out the last few). The
    refinement gives each Gaussian three scales and a rotation (--isotropic: one scale): fewer
    Gaussians fit, and they draw more; not when the byte budget holds the whole map as it is.

    With --for B.mcap the share is cut for that receiver: the Gaussians its views do not draw
    (where it has not been) are sent first, each group in the strategy's order; the receiver's
    request (its poses and calibration) counts in a byte budget.

    \b
    Examples:
      gsc share --budget 0.2 agent_a.mcap -o share.mcap --ply share.ply
      gsc share --budget 50kB agent_a.mcap -o share.mcap
      gsc share --budget 5%bytes --no-sums agent_a.mcap -o share.mcap
      gsc share --budget 72kB --ids agent_a.mcap -o share.mcap
      gsc share --budget 2MB --codec fp16 agent_a.mcap -o share.mcap
      gsc share --budget 50kB --refine 500 --seq data/room agent_a.mcap -o share.mcap
      gsc share agent_a.mcap -o share.mcap --align-to agent_b.mcap
      gsc share --budget 1 --keyframes 3 --seq data/room agent_a.mcap -o share.mcap
      gsc share --budget 5%bytes agent_a.mcap -o share.mcap --for agent_b.mcap
    """
    options = _share_options(strategy, codec, precision, sums, ids, seed, fold, spread)
    dst = output_path(dst, output, "share", "DST")
    check_recording_seq(recording, seq)
    context = click.get_current_context()
    fixed = [
        name for name in SOLVED if context.get_parameter_source(name) != ParameterSource.DEFAULT
    ]
    with progress_bar("share", "cut", hidden=as_json) as bar:
        fitting = f"fitting {budget}"  # (a byte budget's search: each cut a fold and an encoding)
        phases = Phases(bar, {"refine": "iter", fitting: "cut"})
        # (--seq also serves --solve and --keyframes)
        refine_seq = seq if refine_iters or not (solve or keyframes) else None
        refine = log_refiner(
            src,
            refine_iters,
            refine_seq,
            device,
            seed,
            phases,
            "share without --refine",
            anisotropic,
            recording,
        )
        common: dict[str, Any] = dict(
            ply=ply,
            refine=refine,
            align_to=align_to,
            carry=_carried(src, keyframes, seq, recording),
            receiver=receiver,
            device=device,
            command=command_line(),
            force=force,
        )
        if solve:
            from gscompress.pipeline.share.solve import share_solved

            result = share_solved(
                src, dst, budget, options, fixed=fixed, seq=seq, recording=recording, **common
            )
            click.echo(_solver_text(result), err=True)
        else:
            result = share_log(
                src,
                dst,
                budget,
                options,
                progress=lambda tried: phases(fitting, tried, None),
                **common,
            )
    emit(result, as_json, _share_text(result, options, dst, ply, receiver))


def _carried(src: Path, keyframes: int, seq: Path | None, recording: Any) -> Any:
    """The `keyframes` keyframes the share carries, read from `seq` (None: none)."""
    if not keyframes:
        return None
    if seq is None:
        raise click.UsageError("--keyframes takes the frames from --seq: pass it")
    from gscompress.pipeline.logs import carried_keyframes

    return carried_keyframes(src, keyframes, seq, recording)


def _share_options(
    strategy: str,
    codec: str,
    precision: str | None,
    sums: bool,
    ids: bool,
    seed: int,
    fold: bool,
    spread: bool,
) -> ShareOptions:
    """The share's settings from the command's options (`--precision`: the old name of
    `--codec`)."""
    if precision is not None:
        if codec != DEFAULT_SHARE_CODEC and codec != precision:
            raise click.UsageError("--precision is an old name of --codec: give one of them")
        codec = precision
    return ShareOptions(
        strategy=strategy, codec=codec, sums=sums, ids=ids, seed=seed, fold=fold, spread=spread
    )


def _solver_text(result: dict[str, Any]) -> str:
    """What the solver chose, and the picture it predicts."""
    return (
        f"solver: {result['codec']}{'' if result['sums'] else ' without sums'}"
        f"{', folded,' if result['fold'] else ', not folded,'} predicted "
        f"{result['predicted_psnr']:.2f} dB against the {result['solved_against']}"
    )


def _share_text(
    result: dict[str, Any],
    options: ShareOptions,
    dst: Path,
    ply: Path | None,
    receiver: Path | None,
) -> str:
    """The line `gsc share` prints of what it wrote."""
    extra = f" and {ply}" if ply else ""
    folded = result["fold"] and result["selected"] < result["total"]
    carried = (
        f" with {result['keyframes']} keyframes ({result['keyframe_bytes']} B)"
        if result.get("keyframes")
        else ""
    )
    if receiver is not None:
        carried += (
            f", unseen by {receiver.name} first ({result['unseen']} of them; its request "
            f"{result['request_bytes']} B)"
        )
    return (
        f"shared {result['selected']} of {result['total']} Gaussians ({options.strategy}"
        f"{', spread' if options.spread else ''}{', the rest folded in' if folded else ''}, "
        f"{result['codec']}, {result['file_bytes']} B)"
        f"{carried}{refined_text(result)} -> {dst}{extra}"
    )
