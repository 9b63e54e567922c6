"""Reusable click options and parameter types shared by the `gsc` commands."""

from __future__ import annotations

import functools
import math
import os
import shlex
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from gscompress.errors import InputError, clipped
from gscompress.io.codec import CODECS, SHARE_IDS
from gscompress.io.files import json_text
from gscompress.ops.budget import Budget
from gscompress.ops.icp import DEFAULT_ICP, ICP
from gscompress.selection import is_fraction, percent_hint

from .flags import with_flags
from .progress import Phases, advance

if TYPE_CHECKING:
    from gscompress.datasets.base import FrameSelection

F = TypeVar("F", bound=Callable[..., Any])

INPUT_FILE = click.Path(exists=True, dir_okay=False, path_type=Path)
"""An input file: a missing one is a usage error (exit 2), the same for every command."""
INPUT_SEQUENCE = click.Path(exists=True, path_type=Path)
"""A sequence: a dataset folder or a recording (a ROS 2 bag folder, a .bag, .mcap or .db3
file), checked like INPUT_FILE."""
SEQUENCE_HELP = "RGB-D sequence: a folder (TUM or Replica) or a recording (ROS 1/2 bag, MCAP)."


class OutputFile(click.Path):
    """A file to write. A name ending in a path separator, `.` or `..` names a folder, and an
    empty one names none: all are usage errors (a Path drops the separator or the dot and would
    write the file under the folder's own name)."""

    def __init__(self) -> None:
        super().__init__(dir_okay=False, path_type=Path)

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        text = value if isinstance(value, str) else str(value)
        if not text:
            self.fail("an empty path names no file", param, ctx)
        if os.path.basename(text) in ("", ".", ".."):  # (basename of "dir/" is "")
            self.fail(f"{clipped(text)} names a folder; give a file name in it", param, ctx)
        return super().convert(value, param, ctx)


OUTPUT_FILE = OutputFile()


def force_option(more: str = "") -> Callable[[F], F]:
    """`--force`: allow overwriting existing outputs (never an input); `more` ends its help."""
    return click.option(
        "--force",
        is_flag=True,
        help=f"Overwrite existing output files (inputs are never overwritten){more}.",
    )


def json_option(f: F) -> F:
    """`--json`: print one JSON object instead of text."""
    return click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")(f)


def seed_option(help: str = "Seed of the random strategy.") -> Callable[[F], F]:
    """`--seed N` (default 0) for the random choices a command makes."""
    return click.option(
        "--seed", type=click.IntRange(min=0), default=0, show_default=True, help=help
    )


CODEC_HELP = (
    "How the map is stored: compact (quantised, zstd-compressed columns, about 7-20 bytes per "
    "Gaussian), fp16 or fp32 (a foxglove.PointCloud that Foxglove draws, 54 / 76 bytes per "
    "Gaussian)."
)


def codec_option(default: str | None, more: str = "") -> Callable[[F], F]:
    """`--codec fp32|fp16|compact` for the map a command writes; `more` ends its help."""
    return click.option(
        "--codec",
        type=click.Choice(CODECS),
        default=default,
        show_default=default is not None,
        help=CODEC_HELP + more,
    )


def sums_option(f: F) -> F:
    """`--no-sums`: a compact map without the PWAS sums (the score alone instead)."""
    return click.option(
        "--sums/--no-sums",
        default=True,
        show_default=True,
        help="Send the PWAS sums, so that the receiver can keep accumulating importance and a "
        "merge can weigh each agent's evidence (compact: the two sums as 8-bit log codes beside "
        "the score's, about 1.7 B per Gaussian more); with --no-sums a compact map carries only "
        "the score: about 20% more Gaussians in a byte budget, but no evidence for a merge (fp32 "
        "and fp16 always carry the sums, exactly).",
    )(f)


def map_sums_option(f: F) -> F:
    """`--no-sums` of a command that writes a map, not a share (`gsc prune`)."""
    return click.option(
        "--sums/--no-sums",
        default=True,
        show_default=True,
        help="Keep the PWAS sums in a compact map, so that scoring can go on from them and a "
        "later share or merge can weigh each Gaussian's evidence (compact: the two sums as 8-bit "
        "log codes beside the score's, about 1.7 B per Gaussian more); with --no-sums a compact "
        "map keeps only the score (fp32 and fp16 always keep the sums, exactly).",
    )(f)


def ids_option(f: F) -> F:
    """`--ids`: a compact share with the Gaussians' ids (not by default: `SHARE_IDS`)."""
    return click.option(
        "--ids/--no-ids",
        default=SHARE_IDS,
        show_default=True,
        help="Send each Gaussian's id, which names the sender's Gaussian it came from. A merge "
        "gives the share's Gaussians new ids past the receiver's either way, so the receiver "
        "needs them only to trace a Gaussian back; without them (the default) a compact share "
        "is about 2 B per Gaussian smaller (about 20% more Gaussians in a byte budget) and the "
        "receiver numbers them 0..N-1 (fp32 and fp16 always carry the ids).",
    )(f)


def fold_option(f: F) -> F:
    """`--fold/--no-fold`: fold what a prune or share leaves out into what it keeps."""
    return click.option(
        "--fold/--no-fold",
        default=True,
        show_default=True,
        help="Fold each Gaussian left out into the nearest kept one (within 4x their summed "
        "scales): the kept Gaussian takes the centre, spread, colour and opacity of the group "
        "it stands for, so the surface it covered is not left as a hole. Same count and ids; "
        "--no-fold keeps the selected Gaussians exactly as they were.",
    )(f)


class Ratio(click.ParamType):
    """A fraction in (0, 1]; also accepts percentages such as `30%`."""

    name = "ratio"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> float:
        if isinstance(value, float):
            ratio = value
        else:
            text = str(value).strip()
            try:
                ratio = float(text[:-1]) / 100 if text.endswith("%") else float(text)
            except ValueError:
                self.fail(f"{value!r} is not a number", param, ctx)
        if not is_fraction(ratio):
            hint = percent_hint(ratio)
            meant = f": did you mean {hint}?" if hint else ""
            self.fail(f"{value} is outside (0, 1]{meant}", param, ctx)
        return ratio


class PositiveFloat(click.ParamType):
    """A finite number above zero (click's FloatRange lets nan through)."""

    name = "float"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> float:
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if not (math.isfinite(number) and number > 0.0):
            self.fail(f"{value} is not a finite number above 0", param, ctx)
        return number


class SigmaD(click.ParamType):
    """PWAS's distance scale: `auto` (None: from the scene), `inf` (no proximity weighting) or a
    finite number of metres above zero."""

    name = "auto|inf|metres"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> float | None:
        if value is None or isinstance(value, float):
            return value
        text = str(value).strip().lower()
        if text == "auto":
            return None
        if text in ("inf", "infinity"):
            return math.inf
        return PositiveFloat().convert(value, param, ctx)


class BudgetParam(click.ParamType):
    """A share budget: a fraction (`0.2`, `20%`) or bytes (`2MB`, `1.5MiB`); see `Budget`."""

    name = "budget"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> Budget:
        try:
            return Budget.parse(value)
        except InputError as exc:
            self.fail(with_flags(exc), param, ctx)


def command_line() -> str:
    """The command line of this process, for provenance records."""
    return " ".join(shlex.quote(arg) for arg in ["gsc", *sys.argv[1:]])


def emit(result: dict[str, Any], as_json: bool, text: str) -> None:
    """Print a command's result: the JSON object with --json, else the text."""
    click.echo(json_text(result, indent=2, sort_keys=True) if as_json else text)


class Size(click.ParamType):
    """An image size written `WxH` (e.g. 320x240), converted to the tuple (W, H)."""

    name = "WxH"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> tuple[int, int]:
        if isinstance(value, tuple):
            return value
        from gscompress.datasets.base import parse_size

        size = parse_size(str(value))
        if size is None or min(size) <= 0:
            self.fail(
                f"{clipped(value)} is not a size WxH of positive integers, e.g. 320x240",
                param,
                ctx,
            )
        return size


class FrameSubset(click.ParamType):
    """A frame subset: all, odd, even or START:STOP:STEP (`gscompress.datasets.parse_frames`)."""

    name = "subset"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> FrameSelection:
        # imported here so that commands without --frames never load the dataset readers
        from gscompress.datasets.base import FrameSelection, parse_frames

        if isinstance(value, FrameSelection):
            return value
        try:
            return parse_frames(str(value))
        except InputError as exc:
            self.fail(with_flags(exc), param, ctx)


def size_option(default: str | None = None, help: str | None = None) -> Callable[[F], F]:
    """`--size WxH`: the working image size (None when not given and no default)."""
    return click.option(
        "--size",
        type=Size(),
        default=default,
        show_default=default is not None,
        help=help or "Working image size WxH (resizes colour, depth and intrinsics).",
    )


def frames_option(f: F) -> F:
    """`--frames SUBSET`: all, odd (agent A), even (agent B) or START:STOP:STEP."""
    return click.option(
        "--frames",
        type=FrameSubset(),
        default="all",
        show_default=True,
        help="Frames to use (0-based): all, odd (agent A), even (agent B) or START:STOP:STEP "
        "as a Python slice (10:, :100, ::5; -30: is the last 30).",
    )(f)


def output_option(help: str = "Output log (.mcap).") -> Callable[[F], F]:
    """`-o/--output PATH`, required, passed to the command as `dst`."""
    return click.option("-o", "--output", "dst", required=True, type=OUTPUT_FILE, help=help)


def output_path(given: Path | None, output: Path | None, what: str, argument: str) -> Path:
    """An output given once: as the argument named `argument` (the older form) or with -o."""
    if given is not None and output is not None:
        raise click.UsageError(f"give the {what}'s path once: as {argument} or with -o, not both")
    path = given if output is None else output
    if path is None:
        raise click.UsageError(f"missing the {what}'s path: give {argument} or -o {argument}")
    return path


def seq_option(required: bool = True, help: str = SEQUENCE_HELP) -> Any:
    """`--seq PATH`: the sequence (folder or recording) a command renders or refines against."""
    # no explicit default when required: click skips the required check of an option with one
    return click.option(
        "--seq",
        type=INPUT_SEQUENCE,
        required=required,
        help=help,
    )


def device_option(f: F) -> F:
    """`--device auto|cpu|cuda` (auto: cuda when available)."""
    return click.option(
        "--device",
        type=click.Choice(["auto", "cpu", "cuda"]),
        default="auto",
        show_default=True,
        help="Torch device (auto: cuda when available).",
    )(f)


def backend_option(recorded: str = "") -> Callable[[F], F]:
    """`--backend auto|cpu|torch|gsplat`: the renderer. With `recorded` (where the default is
    read from, e.g. "the config's `backend:`") it defaults to None, passed as such."""
    help = "Render backend (auto: gsplat on CUDA, else the C++ CPU kernel, else pure torch)."
    return click.option(
        "--backend",
        type=click.Choice(["auto", "cpu", "torch", "gsplat"]),
        default=None if recorded else "auto",
        show_default=not recorded,
        help=help + (f" [default: {recorded}]" if recorded else ""),
    )


PRESET_NAMES = ("tiny", "cpu", "paper", "paper-tum")
"""The SLAM presets (`gscompress.slam.config.PRESETS`, named here so that --help needs no torch)."""


def slam_config_options(f: F) -> F:
    """`--preset NAME` and `--config FILE.yaml` (passed as `preset`, `config_path`)."""
    f = click.option(
        "--config",
        "config_path",
        type=INPUT_FILE,
        default=None,
        help="YAML config applied on top of the preset (any subset of --save-config's keys).",
    )(f)
    return click.option(
        "--preset",
        type=click.Choice(PRESET_NAMES),
        default=None,
        help="Starting configuration: tiny (tests, seconds), cpu (160x120, 0.4-0.9 s/frame on 2 "
        "cores), paper / paper-tum (SplaTAM's Replica / TUM settings, full size, for a GPU). "
        "[default: the --config file's `preset:`, else cpu]",
    )(f)


def icp_option(f: F) -> F:
    """`--icp builtin|open3d`: the implementation of the alignment's local step."""
    return click.option(
        "--icp",
        type=click.Choice(tuple(ICP)),
        default=DEFAULT_ICP,
        show_default=True,
        help="ICP of the alignment's local step (coloured ICP, Park et al.): builtin (numpy, "
        "no extra) or open3d (Open3D's, pip install 'gscompress[align]').",
    )(f)


def share_transform_option(f: F) -> F:
    """`--share-transform FILE`: the rigid transform from a share's world frame to ours."""
    return click.option(
        "--share-transform",
        type=INPUT_FILE,
        default=None,
        help="Text file with the rigid transform from the share's world frame to the receiver's "
        "(16 numbers of a 4x4 matrix, or `tx ty tz qx qy qz qw`), for agents whose frames "
        "differ; without it the two logs' recorded world frames must agree.",
    )(f)


ANISOTROPIC_HELP = (
    "With --refine: refine three scales and a rotation per Gaussian, so that each kept one "
    "stretches over the surface it now covers (what is folded in keeps its shape); about 5.5 "
    "bytes more a Gaussian in compact"
)


def refine_options(f: F) -> F:
    """`--refine N`, `--anisotropic/--isotropic`, `--seq FOLDER`, the recording options of
    `recording_options` and `--device`: refine what a share keeps on the log's keyframes
    (`log_refiner` turns them into the refiner)."""
    return _refine_options(
        f, f"{ANISOTROPIC_HELP}, so a share whose byte budget holds the whole map stays isotropic."
    )


def map_refine_options(f: F) -> F:
    """`refine_options` of a command that writes a map, not a share (`gsc prune`)."""
    return _refine_options(f, f"{ANISOTROPIC_HELP}.")


def _refine_options(f: F, anisotropic_help: str) -> F:
    """`refine_options`, with this help of `--anisotropic`."""
    from gscompress.pipeline.logs import KEYFRAME_RULE  # (neither loads torch)
    from gscompress.pipeline.refining import DEFAULT_LR_FINAL

    f = device_option(f)
    f = recording_options(f)
    f = click.option(
        "--anisotropic/--isotropic",
        default=True,
        show_default=True,
        help=f"{anisotropic_help} --isotropic keeps the map's one scale per Gaussian.",
    )(f)
    f = seq_option(False, "The sequence the log was made from (needed by --refine).")(f)
    return click.option(
        "--refine",
        "refine_iters",
        type=click.IntRange(min=0),
        default=0,
        show_default=True,
        help="Refine the kept Gaussians for this many iterations on the log's keyframes at its "
        "estimated poses and on the whole map's renders at poses between them (3 per gap), "
        "with its mapping losses and rates (decaying to "
        f"{DEFAULT_LR_FINAL:g} of them), before writing; none is added or dropped. The "
        f"keyframes are {KEYFRAME_RULE}. 0: no refinement (no torch, no sequence).",
    )(f)


def log_refiner(
    src: Path,
    iters: int,
    seq: Path | None,
    device: str,
    seed: int,
    bar: Any,
    instead: str,
    anisotropic: bool = False,
    recording: Any = None,
) -> Any:
    """The `gscompress.pipeline.refining.LogRefiner` that `refine_options` ask for (drawing on
    `bar`, or on its "refine" phase when it is `Phases`; a recording read with `recording`), or
    None for no refinement.

    Raises:
        click.UsageError: --refine without --seq, or --seq without --refine.
    """
    if iters == 0:
        if seq is not None:
            raise click.UsageError("--seq is only used with --refine N")
        return None
    if seq is None:
        raise click.UsageError("--refine needs the sequence the log was made from: pass --seq")
    from gscompress.pipeline.refining import LogRefiner, RefineOptions

    options = RefineOptions(
        iters, device=device, seed=seed, anisotropic=anisotropic, recording=recording
    )
    if isinstance(bar, Phases):
        return LogRefiner(src, seq, options, functools.partial(bar, "refine"), instead)
    return LogRefiner(src, seq, options, lambda done, total: advance(bar, done, total), instead)


def refined_text(result: dict[str, Any]) -> str:
    """What a command says of the refinement whose `refine_*` results it returns."""
    if not result.get("refine_iters"):
        return ""
    return (
        f" (refined {result['refine_iters']} iterations on {result['refine_views']} views"
        f"{', anisotropic' if result.get('refine_anisotropic') else ''}: "
        f"mean loss {result['refine_loss_before']:.4f} -> {result['refine_loss_after']:.4f})"
    )


VIEW_NAMES = ("frames", "every", "size", "poses", "poses_from")
"""The options of `view_options`, as `ImageOptions` names them."""


def view_options(f: F) -> F:
    """--frames, --every, --size, --poses and --poses-from: which frames a command that draws a
    log's map renders (`gsc eval`, `gsc render`), and at which poses; passed to the command as
    one dict named `view` of `ImageOptions`' fields."""

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        view = {name: kwargs.pop(name) for name in VIEW_NAMES}
        view["frames"] = None if view["frames"] is None else str(view["frames"])
        return f(*args, view=view, **kwargs)

    options = [
        click.option(
            "--frames",
            type=FrameSubset(),
            default=None,
            help="Frames to render: all, odd, even or START:STOP:STEP [default: the log's subset].",
        ),
        click.option(
            "--every",
            type=click.IntRange(min=1),
            default=1,
            show_default=True,
            help="Render every N-th frame that has a pose (ATE uses all of them).",
        ),
        size_option(
            help="Render at this size WxH [default: the log's working size; for a share, "
            "which carries no config, that of --poses-from's log, else the sequence's own]."
        ),
        click.option(
            "--poses",
            type=INPUT_FILE,
            default=None,
            help="Render at the poses of this TUM trajectory (matched to frames within 20 ms; "
            "for a map without poses: a share, an imported PLY or SPZ) [default: the log's "
            "estimated poses].",
        ),
        click.option(
            "--poses-from",
            type=INPUT_FILE,
            default=None,
            metavar="OTHER.mcap",
            help="Render at another log's estimated poses (e.g. the map of agent B on agent "
            "A's frames).",
        ),
    ]
    for option in reversed(options):
        wrapper = option(wrapper)
    return wrapper  # type: ignore[return-value]


def check_recording_seq(recording: Any, seq: Path | None) -> None:
    """Refuse recording options (`recording_options`) given without the recording they are
    for (--seq).

    Raises:
        click.UsageError: options other than the defaults, and no --seq.
    """
    if seq is None and recording is not None and not recording.is_default:
        raise click.UsageError(
            "--rgb, --depth, --camera-info, --max-dt, --gt and --gt-frames are for a recording "
            "given by --seq: pass it"
        )


MAX_DT = 0.02
"""`gscompress.datasets.recording.DEFAULT_MAX_DT`, named here so that --help loads no reader."""


def recording_options(f: F) -> F:
    """--rgb, --depth, --camera-info, --max-dt, --gt and --gt-frames: how a recording becomes a
    sequence, passed to the command as one `RecordingOptions` named `recording`."""

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from gscompress.datasets.recording import RecordingOptions
        from gscompress.errors import OptionError

        names = ("rgb", "depth", "camera_info", "max_dt", "gt", "gt_frames")
        values = {name: kwargs.pop(name) for name in names}
        try:
            kwargs["recording"] = RecordingOptions(**values)
        except OptionError as exc:
            raise click.UsageError(with_flags(exc)) from None
        return f(*args, **kwargs)

    options = [
        click.option(
            "--rgb",
            metavar="TOPIC",
            default=None,
            help="A recording's colour topic [default: chosen when unambiguous].",
        ),
        click.option(
            "--depth",
            metavar="TOPIC",
            default=None,
            help="A recording's depth topic, registered to colour [default: chosen].",
        ),
        click.option(
            "--camera-info",
            metavar="TOPIC",
            default=None,
            help="A recording's CameraInfo / CameraCalibration topic [default: the "
            "colour camera's].",
        ),
        click.option(
            "--max-dt",
            type=PositiveFloat(),
            default=MAX_DT,
            show_default=True,
            help="A recording's colour/depth pairing tolerance in seconds.",
        ),
        click.option(
            "--gt",
            type=INPUT_FILE,
            default=None,
            help="A recording's ground truth: a TUM trajectory (camera-to-world).",
        ),
        click.option(
            "--gt-frames",
            nargs=2,
            metavar="WORLD CAMERA",
            default=None,
            help="A recording's ground truth from /tf: the pose of frame CAMERA in "
            "frame WORLD, interpolated to the colour stamps.",
        ),
    ]
    for option in reversed(options):
        wrapper = option(wrapper)
    return wrapper  # type: ignore[return-value]
