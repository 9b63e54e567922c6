"""What an experiment reports: results.json, results.csv, results.md (`markdown`) and the plots
(`plots`), from its results rows and verdicts (`results`)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from gscompress.io.files import json_text, write_text_atomic
from gscompress.pipeline.experiment.markdown import results_markdown
from gscompress.pipeline.experiment.plots import write_plots
from gscompress.pipeline.experiment.protocol import ExperimentSettings
from gscompress.pipeline.experiment.results import ROW_KEYS, failed_runs


def write_reports(
    out: Path,
    seq: Path,
    s: ExperimentSettings,
    rows: list[dict[str, Any]],
    verdicts: dict[str, Any],
    full_log: Path | None,
    failed: dict[str, str] | None = None,
) -> dict[str, str]:
    """results.json, results.csv, results.md and plots/*.png; `full_log`: Table 3's unpruned
    run (None: it failed, and the importance plots are left out); `failed`: the name and
    error of each run that failed."""
    write_text_atomic(out / "results.json", json_text(rows, indent=1))
    write_text_atomic(out / "results.csv", _csv(rows))
    plots = write_plots(out / "plots", rows, s, full_log, seq)
    text = results_markdown(seq, s, rows, verdicts, plots, out)
    text += "".join(line + "\n" for line in failed_runs(failed or {}))
    write_text_atomic(out / "results.md", text)
    return {
        "results_md": str(out / "results.md"),
        "results_csv": str(out / "results.csv"),
        "results_json": str(out / "results.json"),
        "plots": ", ".join(str(p) for p in plots),
    }


def _csv(rows: list[dict[str, Any]]) -> str:
    import io

    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=ROW_KEYS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in ROW_KEYS})
    return buffer.getvalue()
