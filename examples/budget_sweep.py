"""What each share budget buys: one map cut at several budgets by several strategies, each cut
rendered at the log's own poses (no refinement) and scored against the sequence.

For every budget (a fraction of the Gaussians) and strategy it reports the Gaussians kept, the
bytes of their `/gaussians` message in each codec (fp32, fp16, compact), and PSNR and
SSIM over the sequence's frames. It is the receiving side's best case with nothing of its own:
how much of the sender's view the share alone redraws. `gsc experiment` measures what a share
adds to another agent's map instead.

Usage: python examples/budget_sweep.py LOG.mcap --seq SEQ [--budgets 0.05,0.1,0.2,0.4,1]
           [--strategies pwas,opacity,random] [--every 4] [--json OUT.json]
  e.g. python examples/budget_sweep.py demo_out/map.mcap --seq demo_out/synthetic
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from gscompress.errors import GscError
from gscompress.io.codec import CODECS
from gscompress.io.codec import SHARE_DEFAULTS as SHARE
from gscompress.io.files import check_output
from gscompress.io.mcap_log import LogReader, encoded_size
from gscompress.pipeline import evaluate_log, prune_log
from gscompress.pipeline.images import ImageOptions
from gscompress.selection import STRATEGIES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("--seq", type=Path, required=True, help="the log's sequence folder")
    parser.add_argument(
        "--budgets", default="0.05,0.1,0.2,0.4,1", help="fractions, comma-separated"
    )
    parser.add_argument("--strategies", default="pwas,opacity,random")
    parser.add_argument("--every", type=int, default=4, help="score every N-th frame")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON")
    opts = parser.parse_args()
    try:
        budgets = [float(b) for b in opts.budgets.split(",")]
    except ValueError:
        parser.error(f"--budgets takes fractions, comma-separated, got {opts.budgets!r}")
    if not all(0 < b <= 1 for b in budgets) or opts.every < 1:
        parser.error("--budgets are fractions in (0, 1] and --every a positive integer")
    unknown = set(opts.strategies.split(",")) - set(STRATEGIES)
    if unknown:
        parser.error(f"unknown --strategies {sorted(unknown)}; choose from {', '.join(STRATEGIES)}")
    if opts.json is not None:
        try:  # before the work: the log or the sequence itself, or a missing folder
            check_output(opts.json, [opts.log, opts.seq], force=True)
        except GscError as exc:
            parser.error(str(exc))
    try:
        sweep(opts, budgets, opts.strategies.split(","))
    except GscError as exc:  # (the library's errors: one line, as gsc prints them)
        raise SystemExit(f"error: {exc}") from None


def sweep(opts: argparse.Namespace, budgets: list[float], strategies: list[str]) -> None:
    """Cut, score and print each budget and strategy (and write --json)."""
    with LogReader(opts.log) as log:  # what every cut needs, said of the log the user named
        if len(log.read_poses()[0]) == 0:
            raise GscError(f"{opts.log} has no estimated poses to render at: not a SLAM log")
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for budget in budgets:
            for strategy in strategies if budget < 1 else ["whole map"]:
                cut = Path(scratch) / f"{strategy}_{budget}.mcap"
                prune_log(opts.log, cut, budget, by=strategy if budget < 1 else "pwas")
                with LogReader(cut) as log:
                    gaussians = log.read_map()
                scores = evaluate_log(cut, opts.seq, ImageOptions(every=opts.every, lpips=False))
                rows.append(
                    {
                        "budget": budget,
                        "strategy": strategy,
                        "gaussians": len(gaussians),
                        **{f"bytes_{c}": encoded_size(gaussians, c, SHARE) for c in CODECS},
                        "psnr": scores["psnr"],
                        "ssim": scores["ssim"],
                    }
                )
                r = rows[-1]
                print(
                    f"{budget:>5.0%} {strategy:<10} {r['gaussians']:>8} Gaussians, MB "
                    f"{r['bytes_fp32'] / 1e6:.3f} fp32 / {r['bytes_fp16'] / 1e6:.3f} fp16 / "
                    f"{r['bytes_compact'] / 1e6:.3f} compact, "
                    f"PSNR {r['psnr']:6.2f} dB, SSIM {r['ssim']:.3f}",
                    flush=True,
                )
    if opts.json:
        opts.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
