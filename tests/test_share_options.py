"""A share's settings (`ShareOptions`): their checks and the record a share keeps of them."""

from __future__ import annotations

from dataclasses import FrozenInstanceError
from pathlib import Path

import pytest

from gscompress.errors import InputError
from gscompress.gaussians import random_map
from gscompress.io.mcap_log import LogMetadata, LogReader, LogWriter
from gscompress.ops.budget import Budget
from gscompress.pipeline.share import cut, share_log
from gscompress.pipeline.share.cut import ShareCut
from gscompress.pipeline.share.options import ShareOptions

# What shares of the map below recorded before the settings were one object (the operation of
# their provenance step, and the settings and counts of their results), for these budgets and
# settings: a share cut with `ShareOptions` records the same.
RECORDED = {
    "default": (
        "5kB",
        ShareOptions(),
        {
            "budget": "5kB",
            "budget_bytes": 5000,
            "codec": "compact",
            "fold": True,
            "ids": False,
            "name": "share",
            "seed": 0,
            "strategy": "pwas",
            "sums": True,
        },
        {
            "budget": "5kB",
            "budget_bytes": 5000,
            "bytes": 2948,
            "codec": "compact",
            "fold": True,
            "ids": False,
            "selected": 186,
            "source": "src.mcap",
            "strategy": "pwas",
            "sums": True,
            "total": 300,
        },
    ),
    "fp32, spread, not folded": (
        0.25,
        ShareOptions(codec="fp32", spread=True, strategy="opacity", seed=3, fold=False),
        {
            "budget": 0.25,
            "codec": "fp32",
            "fold": False,
            "ids": True,
            "name": "share",
            "seed": 3,
            "spread": True,
            "strategy": "opacity",
            "sums": True,
        },
        {
            "budget": 0.25,
            "bytes": 6057,
            "codec": "fp32",
            "fold": False,
            "ids": True,
            "selected": 75,
            "source": "src.mcap",
            "spread": True,
            "strategy": "opacity",
            "sums": True,
            "total": 300,
        },
    ),
    "no sums, ids, random": (
        "40%bytes",
        ShareOptions(sums=False, ids=True, strategy="random", seed=9),
        {
            "budget": "40%bytes",
            "budget_bytes": 9263,
            "budget_fp32_fraction": 0.4,
            "codec": "compact",
            "fold": True,
            "ids": True,
            "name": "share",
            "seed": 9,
            "strategy": "random",
            "sums": False,
        },
        {
            "budget": "40%bytes",
            "budget_bytes": 9263,
            "budget_fp32_fraction": 0.4,
            "bytes": 4095,
            "codec": "compact",
            "fold": True,
            "ids": True,
            "selected": 300,
            "source": "src.mcap",
            "strategy": "random",
            "sums": False,
            "total": 300,
        },
    ),
}


@pytest.fixture(scope="module")
def src(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("share_options") / "src.mcap"
    with LogWriter(path, LogMetadata(command="test")) as log:
        log.write_gaussians(random_map(300, seed=4), 0)
    return path


@pytest.mark.parametrize("name", RECORDED)
def test_a_share_records_its_settings_as_before(
    src: Path, tmp_path: Path, name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    budget, options, operation, results = RECORDED[name]
    share_log(src, tmp_path / "s.mcap", budget, options, command="gsc share x")
    with LogReader(tmp_path / "s.mcap") as log:  # (its names counted as the old code did)
        monkeypatch.setattr(cut, "RECORDED_TEXT_BYTES", cut.path_text_bytes(log.metadata))
    share_log(src, tmp_path / "s.mcap", budget, options, command="gsc share x", force=True)
    with LogReader(tmp_path / "s.mcap") as log:
        meta = log.metadata
    assert meta.provenance[-1]["operation"] == operation
    assert meta.results == results
    resolved = ShareCut(src, Budget.parse(budget), options).budget
    assert options.provenance(resolved) == operation
    settings = options.results("src.mcap", resolved)
    assert settings == {k: v for k, v in results.items() if k not in ("bytes", "selected", "total")}


def test_the_ids_recorded_are_those_sent() -> None:
    assert not ShareOptions().sends_ids and ShareOptions(ids=True).sends_ids
    assert ShareOptions(codec="fp16").sends_ids  # (fp16 and fp32 always carry them)
    assert ShareOptions(codec="fp16").provenance(Budget.parse("0.5"))["ids"] is True


@pytest.mark.parametrize(
    "options, message",
    [
        (ShareOptions(codec="zip"), "codec"),
        (ShareOptions(strategy="loudest"), "unknown strategy 'loudest'"),
    ],
)
def test_bad_settings_are_refused_before_the_map_is_read(
    options: ShareOptions, message: str, tmp_path: Path
) -> None:
    with pytest.raises(InputError, match=message):
        options.check()
    missing = tmp_path / "missing.mcap"  # (refused before it is opened)
    with pytest.raises(InputError, match=message):
        ShareCut(missing, Budget.parse("0.5"), options)
    with pytest.raises(InputError, match=message):
        share_log(missing, tmp_path / "s.mcap", 0.5, options)
    ShareOptions().check()


def test_the_settings_are_one_frozen_value() -> None:
    options = ShareOptions(codec="fp16")
    with pytest.raises(FrozenInstanceError):
        options.codec = "fp32"  # type: ignore[misc]
    assert options == ShareOptions(codec="fp16") != ShareOptions()


def test_the_solver_refuses_to_fix_what_it_does_not_choose(src: Path) -> None:
    pytest.importorskip("torch")
    from gscompress.pipeline.share.solve import solve_share

    with pytest.raises(InputError, match="the solver chooses codec, sums, fold"):
        solve_share(src, Budget.parse("5kB"), ShareOptions(), fixed=("strategy",))
