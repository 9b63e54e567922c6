"""`gsc experiment`: the paper's two-agent protocol on any sequence, with tables and plots."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import click

from gscompress.pipeline.experiment import (
    EXECUTORS,
    MERGE_HOWS,
    SPLITS,
    ExperimentSettings,
    run_experiment,
)
from gscompress.pipeline.experiment.protocol import FULL_STUDY, PROTOCOLS, protocol_of
from gscompress.pipeline.merge import DEFAULT_REFINE_VIEWS
from gscompress.pipeline.refining import DEFAULT_LR_FINAL
from gscompress.pipeline.share.formats import REFERENCE_FORMATS
from gscompress.slam.views import REFINE_VIEWS

from .options import (
    INPUT_SEQUENCE,
    BudgetParam,
    F,
    Ratio,
    device_option,
    emit,
    ids_option,
    json_option,
    recording_options,
    size_option,
    slam_config_options,
    sums_option,
)
from .progress import advance, progress_bar


def _comma_list(value: str) -> tuple[str, ...]:
    """The non-empty items of a comma-separated option, stripped."""
    return tuple(v.strip() for v in value.split(",") if v.strip())


def _budget_list(ctx: click.Context, param: click.Parameter, value: str) -> tuple[str, ...]:
    """Comma-separated budgets, each checked as `--budget` is (kept as written)."""
    items = _comma_list(value)
    if not items:
        raise click.BadParameter("give at least one budget")
    return tuple(str(BudgetParam().convert(item, param, ctx)) for item in items)


def _plan_text(plan: dict[str, Any], s: ExperimentSettings) -> str:
    """What the experiment will do, said before it starts: its steps and about how long."""
    minutes = plan["seconds"] / 60
    took = f"roughly {minutes:.0f} minutes" if minutes >= 1.5 else "roughly a minute or more"
    study = f"{s.seeds} seed(s), strategies {','.join(s.strategies)}, " + (
        f"sweep on {s.sweep_seeds} seed(s)" if s.sweep_seeds else "no sweep"
    )
    return (
        f"experiment: {plan['steps']} steps ({study}; protocol "
        f"{protocol_of(s.fold, s.merge_how)}), {took} of SLAM-like iterations on this machine "
        "as it is now (one timed now; starting, writing and LPIPS not counted; steps a rerun "
        "reuses take none)"
    )


def _formats(value: str) -> tuple[str, ...]:
    """Comma-separated reference formats, or none."""
    items = _comma_list(value)
    if items == ("none",):
        return ()
    unknown = [v for v in items if v not in REFERENCE_FORMATS]
    if unknown:
        raise click.BadParameter(
            f"unknown format {unknown[0]!r}: give none or some of {', '.join(REFERENCE_FORMATS)}"
        )
    return items


SETTINGS_OPTIONS = (
    "preset",
    "config_path",
    "budget",
    "keep",
    "full",
    "seeds",
    "sweep",
    "sweep_seeds",
    "references",
    "strategies",
    "size",
    "frames",
    "split",
    "overlap",
    "every",
    "anchor",
    "refine_poses",
    "mode",
    "merge_iters",
    "merge_views",
    "merge_lr_final",
    "protocol",
    "merge_how",
    "fold",
    "spread",
    "sums",
    "ids",
    "no_lpips",
    "recording",
    "device",
)
"""The options of `gsc experiment` its `ExperimentSettings` are made of (`_settings`)."""


def _settings_option(f: F) -> F:
    """The options of `SETTINGS_OPTIONS`, passed to the command as one `ExperimentSettings`
    named `settings` (`_settings`)."""

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        given = {name: kwargs.pop(name) for name in SETTINGS_OPTIONS}
        return f(*args, settings=_settings(given), **kwargs)

    return wrapper  # type: ignore[return-value]


def _settings(o: dict[str, Any]) -> ExperimentSettings:
    """The experiment's settings from its options (`SETTINGS_OPTIONS`, by name): --full's study
    or a first look's, and --protocol's fold and merge unless given."""
    study = FULL_STUDY if o["full"] else {f: getattr(ExperimentSettings, f) for f in FULL_STUDY}
    chosen = PROTOCOLS[o["protocol"]]
    return ExperimentSettings(
        preset=o["preset"],
        config_path=str(o["config_path"]) if o["config_path"] else None,
        budget=str(o["budget"]),
        keep=o["keep"],
        seeds=study["seeds"] if o["seeds"] is None else o["seeds"],
        sweep=o["sweep"],
        sweep_seeds=study["sweep_seeds"] if o["sweep_seeds"] is None else o["sweep_seeds"],
        references=o["references"],
        strategies=study["strategies"] if o["strategies"] is None else _comma_list(o["strategies"]),
        size=o["size"],
        frames=o["frames"],
        split=o["split"],
        overlap=o["overlap"],
        every=study["every"] if o["every"] is None else o["every"],
        mode=o["mode"],
        anchor=o["anchor"],
        refine_poses=study["refine_poses"] if o["refine_poses"] is None else o["refine_poses"],
        merge_iters=o["merge_iters"],
        merge_views=o["merge_views"],
        merge_lr_final=o["merge_lr_final"],
        merge_how=chosen["merge_how"] if o["merge_how"] is None else o["merge_how"],
        fold=chosen["fold"] if o["fold"] is None else o["fold"],
        spread=o["spread"],
        sums=o["sums"],
        ids=o["ids"],
        lpips=not o["no_lpips"],
        device=o["device"],
        recording=None if o["recording"].is_default else o["recording"],
    )


@click.command("experiment", short_help="Run the paper's two-agent protocol: tables and plots.")
@click.argument("seq", type=INPUT_SEQUENCE)
@click.option(
    "-o",
    "--output",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Experiment folder: runs/, results.md/.csv/.json and plots/ (a rerun reuses runs).",
)
@click.option(
    "--budget",
    type=BudgetParam(),
    default="0.2",
    show_default=True,
    help="Main share budget (Table 4): a fraction (0.2, 20%) or bytes (2MB).",
)
@click.option(
    "--keep",
    type=Ratio(),
    default=None,
    help="Fraction kept at each PWAS pruning stage [default: the config's, 0.3].",
)
@slam_config_options
@click.option(
    "--full",
    is_flag=True,
    help="The whole study instead of a first look: 3 seeds, the strategies random, opacity, "
    "alpha-t, pwas and pwas-inf, the --sweep with the --references on the first seed, every "
    "frame scored with 100 tracking iterations (--seeds, --strategies, --sweep-seeds, --every "
    "and --refine-poses, when given, still decide). On a 16-frame "
    "160x120 sequence with the tiny preset: 128-129 steps instead of 18.",
)
@click.option(
    "--seeds",
    type=click.IntRange(1, 1000),
    default=None,
    help="How many seeds to run: 0 to N-1, each the two-agent runs' SLAM seed and the random "
    "share's seed [default: 1; 3 with --full].",
)
@click.option(
    "--sweep",
    default="0.05,0.1,0.2,0.4",
    show_default=True,
    callback=_budget_list,
    help="Comma-separated budgets of the rate-distortion sweep.",
)
@click.option(
    "--sweep-seeds",
    type=click.IntRange(min=0),
    default=None,
    help="How many of the seeds (the first ones) run the sweep, at most --seeds (0: none) "
    "[default: 0; 1 with --full].",
)
@click.option(
    "--references",
    default=",".join(REFERENCE_FORMATS),
    show_default=True,
    callback=lambda ctx, param, value: _formats(value),
    help="On the sweep seeds, A's whole map also sent whole in these formats and received by "
    "B like a share: the field's points on the rate-distortion plot and a table beside the "
    "PWAS curve at the same bytes. fp32: our fp32 codec; spz: SPZ v4; sog: PlayCanvas SOG, "
    "written by @playcanvas/splat-transform (left out, with a note, where it is missing: "
    "`make js-deps`). none: no such points.",
)
@click.option(
    "--strategies",
    default=None,
    help="Comma-separated share strategies to compare (random and pwas required) [default: "
    "random,pwas; random,opacity,alpha-t,pwas,pwas-inf with --full]. pwas-inf: "
    "PWAS without its proximity weight, A's finished map scored again from A's frames (`gsc "
    "score --sigma-d inf`); pwas-final: the same with the scene's sigma_d, which separates "
    "what scoring again changes from what the weight does. NAME-for-b cuts that strategy's "
    "shares for B (`gsc share --for`: what B has not seen first).",
)
@size_option(help="Working size WxH of every run [default: the preset's].")
@click.option(
    "--frames",
    default="all",
    show_default=True,
    help="Frames of the experiment: all or START:STOP:STEP with START >= 0 (no counting from "
    "the end), split between A and B by --split.",
)
@click.option(
    "--split",
    type=click.Choice(SPLITS),
    default="odd-even",
    show_default=True,
    help="odd-even: A gets the odd positions among the frames, B the even ones (the paper's "
    "protocol). halves: A the first ceil(N(1+overlap)/2) of the N frames, B the last as many.",
)
@click.option(
    "--overlap",
    type=click.FloatRange(0.0, 1.0, max_open=True),
    default=0.2,
    show_default=True,
    help="With --split halves, the fraction of the frames both agents get.",
)
@click.option(
    "--every",
    type=click.IntRange(min=1),
    default=None,
    help="Evaluate (and score across agents) every N-th frame of each run [default: 2; 1 with "
    "--full].",
)
@click.option(
    "--anchor",
    type=click.Choice(["gt", "own"]),
    default="gt",
    show_default=True,
    help="Where each agent's world frame starts: gt, at the ground-truth pose of its first "
    "frame (the two maps share a frame); own, at the identity at its own first frame: A's map "
    "is aligned to B's as `gsc align` does, shares are moved by that transform, and the "
    "report adds its error against the true one and B with the PWAS share at the true one. "
    "Needs `pip install 'gscompress[align]'`.",
)
@click.option(
    "--refine-poses",
    type=click.IntRange(min=0),
    default=None,
    help="Cross-agent scoring: the centralised run, A, B, B refined without a share, B with "
    "each share at each budget and B with A's whole map are scored on A's frames, B's frames "
    "and all frames after refining each frame's pose against the fixed map with this many "
    "tracking iterations (`gsc eval --refine-poses`), starting from the poses of the agent "
    "that made the map on its frames, the other agent's on the other's (moved by the "
    "alignment with --anchor own), and on all frames the map's own where it has them, the "
    "other agent's on the rest. 0: each run scored on its own frames only [default: 20; "
    "100 with --full].",
)
@click.option(
    "--mode",
    type=click.Choice(["merge", "inject"]),
    default="merge",
    show_default=True,
    help="How B receives a share: merged into its finished map and refined (the paper's "
    "protocol; B's poses do not change), or injected before its first frame (a new B run).",
)
@click.option(
    "--protocol",
    type=click.Choice(list(PROTOCOLS)),
    default="commands",
    show_default=True,
    help="What each share and merge does: commands, as `gsc share` and `gsc merge` do by "
    "default (folded shares; merges aligned and resolved); paper, the paper's exact protocol "
    "(--no-fold --merge exact). --fold/--no-fold and --merge, when given, still decide.",
)
@click.option(
    "--merge",
    "merge_how",
    type=click.Choice(MERGE_HOWS),
    default=None,
    help="How each merge combines the maps: default (`gsc merge`'s: the share aligned, the "
    "surfaces both maps hold resolved, its Gaussians moving as much as B's views see them) or "
    "exact (every Gaussian of both, refined as one: the paper's merge) [default: the "
    "--protocol's].",
)
@click.option(
    "--fold/--no-fold",
    default=None,
    help="Fold what each share leaves out into what it sends (`gsc share`'s default); "
    "without, the shares are the paper's top K, the strategies differing only in their choice "
    "[default: the --protocol's].",
)
@click.option(
    "--spread/--no-spread",
    default=False,
    show_default=True,
    help="Spread every strategy's order over space (`gsc share --spread`): the best Gaussian "
    "of each of K distinct places first.",
)
@sums_option
@ids_option
@click.option(
    "--merge-iters",
    type=click.IntRange(min=0),
    default=200,
    show_default=True,
    help="Refinement iterations of each merge.",
)
@click.option(
    "--merge-views",
    type=click.Choice(REFINE_VIEWS),
    default=DEFAULT_REFINE_VIEWS,
    show_default=True,
    help="What each merge refines on: all of B's frames, or B's keyframes only (`gsc merge "
    "--views`).",
)
@click.option(
    "--merge-lr-final",
    type=click.FloatRange(0.0, 1.0, min_open=True),
    default=DEFAULT_LR_FINAL,
    show_default=True,
    help="Each merge's learning rates decay to this fraction by its last iteration; 1 keeps "
    "them constant (`gsc merge --lr-final`).",
)
@click.option(
    "--jobs",
    type=click.IntRange(1, 256),
    default=1,
    show_default=True,
    help="Runs at once, each in its own process with an equal share of the torch threads "
    "(`gsc --threads`, default one per core); a run starts as soon as the runs it reads have "
    "finished. The figures match a --jobs 1 table only at the same threads per run (`gsc "
    "--threads 4 ... --jobs 2` as `gsc --threads 2 ... --jobs 1`): thread counts change "
    "the rounding.",
)
@click.option(
    "--executor",
    type=click.Choice(EXECUTORS),
    default="local",
    show_default=True,
    help="What runs the runs: this machine (--jobs at once), or Ray tasks on a cluster "
    "(--address), each started as soon as the runs it reads have finished. Needs the "
    "gscompress[cluster] extra; see docs/cluster.md.",
)
@click.option(
    "--address",
    default=None,
    help="With --executor ray: the cluster, `auto` (the one this machine joined with `ray "
    "start`, or RAY_ADDRESS) or the head's HOST:PORT [default: start Ray on this machine]. "
    "The sequence and -o must be on storage every node sees at the same path.",
)
@click.option(
    "--cpus-per-run",
    type=click.FloatRange(0.0, 1024.0, min_open=True),
    default=None,
    help="With --executor ray: CPUs each run declares, and its torch threads (rounded up) "
    "[default: 1].",
)
@click.option("--no-lpips", is_flag=True, help="Skip LPIPS in the evaluations.")
@recording_options
@device_option
@json_option
@_settings_option
def experiment(
    seq: Path,
    out_dir: Path,
    settings: ExperimentSettings,
    jobs: int,
    executor: str,
    address: str | None,
    cpus_per_run: float | None,
    as_json: bool,
) -> None:
    """Run the paper's protocol on the sequence in SEQ and write its tables and plots.

    By default a first look: one seed, random against PWAS at --budget, no rate-distortion
    sweep, every 2nd frame scored, 20 tracking iterations a frame in the cross-agent scoring
    (18 steps; minutes on a 16-frame 160x120 sequence with --preset tiny). --full runs the
    whole study (3 seeds, five strategies, the sweep and its references, every frame, 100
    iterations: 128-129 steps). Before it starts
    it says how many steps it will run and about how long they take; the bar counts them.
    Each share and merge is what `gsc share` and `gsc merge` make by default (--protocol
    commands); --protocol paper runs the paper's exact protocol (top-K shares, nothing folded;
    the exact merge), and results.md names the protocol.

    \b
    - Table 3: the whole sequence without and with PWAS pruning.
    - Table 4, per seed: agent A maps the odd frames, agent B the even ones (--split
      halves: A the first part, B the last, --overlap of them shared); B receives A's
      share (each of --strategies at --budget) and A's whole map (the upper
      bound): merged into B's map and refined on B's frames (--mode merge; --merge-views
      keyframes for its keyframes only), or injected before B's first frame so that its
      tracking uses it too (--mode inject).
    - Rate-distortion (with --full or --sweep-seeds N): PSNR and ATE of B against the
      share's bytes, per strategy, with A's whole map as our compact share and as fp32, SPZ
      and SOG (--references).
    Table 3's PWAS run (one agent on all the frames, the agents' preset) is the centralised
    reference.
    Every run is scored with `gsc eval` on its own frames; with --refine-poses N (not 0)
    the centralised run, A and every run of B are also scored on A's frames, B's frames
    and all frames at poses refined against the fixed map, and the shares are ranked on all
    frames (PWAS against each strategy, cell by cell, in results.md). Outputs: results.md
    (tables like the paper's), results.csv, results.json, plots/*.png; each run's log stays
    in runs/. A rerun reuses every finished run whose settings are unchanged. A run that
    fails is tried once more, then listed in results.md with its error (the runs it feeds are
    not run, the rest go on) and the command exits with status 1 once the reports are written.

    \b
    Examples:
      gsc experiment demo_seq -o exp --preset tiny               # a first look, minutes
      gsc experiment demo_seq -o exp --preset tiny --frames 0:10 --size 80x60 \\
          --refine-poses 10                                      # a smoke test
      gsc experiment data/office -o exp_office --full            # cpu preset, the whole study
      gsc experiment data/office -o exp_paper --full --protocol paper
      gsc --threads 8 experiment data/office -o exp_office --jobs 4   # 4 runs at a time
      gsc experiment /shared/office -o /shared/exp --executor ray --address auto
    """
    with progress_bar("experiment", "run", hidden=as_json) as bar:

        def progress(name: str, done: int, total: int) -> None:
            bar.set_postfix_str(name, refresh=False)
            advance(bar, done, total)

        def announce(plan: dict[str, Any]) -> None:
            if not as_json:  # (above the bar, which may be shown already)
                with bar.external_write_mode():
                    click.echo(_plan_text(plan, settings), err=True)

        try:
            result = run_experiment(
                seq,
                out_dir,
                settings,
                progress=progress,
                jobs=jobs,
                executor=executor,
                address=address,
                cpus_per_run=cpus_per_run,
                announce=announce,
            )
        except KeyboardInterrupt:
            bar.close()
            click.echo(
                f"Interrupted: the finished runs are kept in {out_dir / 'runs'}; the same "
                "command reuses them and redoes the rest",
                err=True,
            )
            raise SystemExit(130) from None
    emit(result, as_json, _result_text(result))
    if result["failed"]:
        click.echo(
            f"{len(result['failed'])} run(s) failed or were not run (listed in "
            f"{result['results_md']}); the same command redoes them",
            err=True,
        )
        raise SystemExit(1)


def _result_text(result: dict[str, Any]) -> str:
    """The lines `gsc experiment` prints of what it wrote, and PWAS against random."""
    v = result["verdicts"]
    return (
        f"wrote {result['results_md']} ({result['rows']} rows; {result['steps']} steps, "
        f"{result['reused']} reused)\n"
        f"PWAS beats random at {v['budget']}: PSNR in {v['pwas_beats_random_psnr']}/{v['seeds']}"
        + (
            " seeds (a merge leaves B's ATE as it was; --mode inject compares it)"
            if v["mode"] == "merge"
            else f" seeds, ATE in {v['pwas_beats_random_ate']}/{v['seeds']}"
        )
    )
