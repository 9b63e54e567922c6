"""Byte budgets and fp16 shares: parsing, the exact message size, never over budget, fp16 error."""

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from gscompress.errors import BudgetError, InputError, LogFormatError, MapError
from gscompress.gaussians import random_map
from gscompress.io.codec import CODECS, SHARE_IDS
from gscompress.io.columns import map_from_columns
from gscompress.io.mcap_log import (
    TOPIC_GAUSSIANS,
    LogMetadata,
    LogReader,
    LogWriter,
    gaussians_to_pointcloud,
    pointcloud_bytes,
    pointcloud_to_gaussians,
    read_map,
    record_size,
)
from gscompress.io.ply import read_ply
from gscompress.ops.budget import Budget, largest_count_within
from gscompress.pipeline import log_info, prune_log, share_log
from gscompress.pipeline.share.cut import RECORDED_TEXT_BYTES, ShareCut, smallest_share_bytes
from gscompress.pipeline.share.options import ShareOptions
from gscompress.selection import select_count, strategy_scores, top_k


def write_log(path, gaussians):
    with LogWriter(path, LogMetadata(command="test")) as log:
        log.write_gaussians(gaussians, 0)
    return path


# ---------------------------------------------------------------- parsing


@pytest.mark.parametrize(
    "text, ratio, budget_bytes",
    [
        ("0.2", 0.2, None),
        ("1", 1.0, None),
        ("20%", 0.2, None),
        (0.5, 0.5, None),
        ("2MB", None, 2_000_000),
        ("2mB", None, 2_000_000),
        ("500kB", None, 500_000),
        ("500 KB", None, 500_000),
        ("1.5MiB", None, 1_572_864),
        ("1KiB", None, 1024),
        ("1GB", None, 10**9),
        ("1giB", None, 2**30),
        ("300000B", None, 300_000),
        ("1e6B", None, 1_000_000),
        ("2.5B", None, 2),  # rounded down: a budget is never exceeded
    ],
)
def test_budget_parses_fractions_and_byte_units(text, ratio, budget_bytes):
    budget = Budget.parse(text)
    assert budget.ratio == pytest.approx(ratio) if ratio is not None else budget.ratio is None
    assert budget.budget_bytes == budget_bytes


@pytest.mark.parametrize(
    "text, message",
    [
        ("2", "add a unit, e.g. 2B, 2kB or 2MB"),
        ("2Mb", "a lowercase b means bits; budgets are bytes, e.g. 2MB"),  # megabits, not bytes
        ("1kb", "e.g. 1kB"),
        ("2kib", "e.g. 2KiB"),  # the unit as it is written
        ("20mb", "e.g. 20MB"),
        (3, "add a unit"),
        ("1.5", "add a unit"),
        ("0", r"not a fraction in \(0, 1\]"),
        ("150%", r"not a fraction in \(0, 1\]"),
        ("abc", "neither a fraction"),
        ("", "neither a fraction"),
        ("-1MB", "neither a fraction"),
        ("nan", "neither a fraction"),
        ("2XB", "unknown unit 'XB'"),
        ("2 bits", "unknown unit"),
        ("0B", "at least 1 B"),
        ("0.5B", "at least 1 B"),
        ("1e400B", "at least 1 B"),
    ],
)
def test_bad_budgets_are_refused_with_a_hint(text, message):
    with pytest.raises(InputError, match=message):
        Budget.parse(text)


def test_largest_count_within_is_the_last_that_fits():
    size = lambda k: 100 + 7 * k  # noqa: E731
    assert largest_count_within(100 + 7 * 10, 50, size) == 10
    assert largest_count_within(100 + 7 * 10 + 6, 50, size) == 10
    assert largest_count_within(10**6, 50, size) == 50  # everything fits
    assert largest_count_within(107, 50, size) == 1
    with pytest.raises(BudgetError, match="cannot hold one Gaussian: that takes 107 B"):
        largest_count_within(106, 50, size)


# ---------------------------------------------------------------- the message size


def _varint_boundaries(stride, limit):
    """Counts K-1, K where the varint of the data length K * stride gains a byte."""
    out = [1, 2]
    for bound in (1 << 7, 1 << 14, 1 << 21):
        k = -(-bound // stride)
        if k <= limit:
            out += [k - 1, k]
    return out


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
@pytest.mark.parametrize("sh_degree, isotropic", [(0, True), (1, False), (3, True)])
def test_message_size_model_is_exact_across_varint_boundaries(precision, sh_degree, isotropic):
    full = random_map(40_000 if sh_degree == 0 else 2_000, 3, isotropic, sh_degree)
    for timestamp_ns in (0, 1_234_567_890_123):
        size = pointcloud_bytes(full, precision, timestamp_ns)
        stride = record_size(full, precision)
        for k in [0, *_varint_boundaries(stride, len(full)), len(full)]:
            cloud = gaussians_to_pointcloud(full.select(slice(0, k)), timestamp_ns, precision)
            assert cloud.point_stride == stride
            assert size(k) == len(cloud.SerializeToString()), (k, timestamp_ns)


def test_fp16_records_are_smaller():
    assert record_size(random_map(1)) == 76  # 18 float32 + uint32 id
    assert record_size(random_map(1), "fp16") == 54  # 11 halves, 7 float32, id
    assert record_size(random_map(1, sh_degree=3), "fp32") == 256
    assert record_size(random_map(1, sh_degree=3), "fp16") == 144


# ---------------------------------------------------------------- never over budget


def share_bytes(src, budget_text, count, codec, ids=SHARE_IDS):
    """Bytes of the share file of the `count` best Gaussians under `budget_text`."""
    return ShareCut(src, Budget.parse(budget_text), ShareOptions(codec=codec, ids=ids)).size(count)


@st.composite
def byte_budget_cases(draw):
    n = draw(st.integers(1, 300))
    sh_degree = draw(st.sampled_from([0, 1, 2, 3]))
    isotropic = draw(st.booleans())
    codec = draw(st.sampled_from(CODECS))
    full = random_map(n, draw(st.integers(0, 10_000)), isotropic, sh_degree)
    per = {"fp32": 76, "fp16": 54, "compact": 30}[codec] * (1 + 3 * sh_degree)
    low, high = {
        "any": (1500, 3000 + per * n),  # anywhere up to everything
        "few": (1500, 3000 + per * 5),  # a few Gaussians
        "tiny": (1, 1500),  # below the framing, below one Gaussian, or just one
    }[draw(st.sampled_from(["any", "few", "tiny"]))]
    budget_bytes = draw(st.integers(low, high))
    return full, codec, budget_bytes, draw(st.booleans())


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=byte_budget_cases())
def test_byte_budget_bounds_the_whole_file_and_holds_the_most_that_fit(case):
    """In every codec, the share file as written (framing, schema, metadata, map) never exceeds
    the budget, holds the K best Gaussians, and K + 1 of them would not fit (with the ids sent
    or not: without them the K are checked by count, their choice does not depend on it)."""
    full, codec, budget_bytes, ids = case
    with tempfile.TemporaryDirectory() as tmp:
        src = write_log(Path(tmp) / "a.mcap", full)
        dst = Path(tmp) / "s.mcap"
        try:
            result = share_log(src, dst, f"{budget_bytes}B", ShareOptions(codec=codec, ids=ids))
        except BudgetError as exc:
            event("below one Gaussian")
            assert "raise the budget" in str(exc) and not dst.exists()
            assert share_bytes(src, f"{budget_bytes}B", 1, codec, ids) > budget_bytes  # one won't
            return
        k = result["selected"]
        event("all fit" if k == len(full) else "some fit")
        assert dst.stat().st_size == result["file_bytes"] <= budget_bytes  # what is sent fits
        assert result["budget_bytes"] == budget_bytes and result["codec"] == codec
        index = top_k(strategy_scores(full, "pwas"), full.ids, k)
        sent = read_map(dst)
        if ids or codec != "compact":
            assert sorted(sent.ids.tolist()) == sorted(full.ids[index].tolist())  # K best
        assert len(sent) == k
        if k < len(full):  # one more would not fit: checked on a file really written
            assert share_bytes(src, f"{budget_bytes}B", k + 1, codec, ids) > budget_bytes


@pytest.mark.parametrize("codec", CODECS)
def test_budget_below_one_gaussian_is_a_budget_error(tmp_path, codec):
    full = random_map(100)
    src = write_log(tmp_path / "a.mcap", full)
    for budget_bytes in (1, 500, share_bytes(src, "1000B", 1, codec) - 1):
        with pytest.raises(BudgetError, match=r"cannot hold one Gaussian: that takes"):
            share_log(src, tmp_path / "s.mcap", f"{budget_bytes}B", ShareOptions(codec=codec))
    assert not (tmp_path / "s.mcap").exists()
    one = share_bytes(src, "1000B", 1, codec)  # (a budget written with as many digits)
    exact = share_log(src, tmp_path / "s.mcap", f"{one}B", ShareOptions(codec=codec))
    assert exact["selected"] == 1 and exact["file_bytes"] <= one  # (names counted at a size)
    assert one >= smallest_share_bytes(codec)
    with pytest.raises(
        BudgetError, match=r"0.001 of 100 Gaussians rounds to none; raise the budget"
    ):
        share_log(src, tmp_path / "t.mcap", 0.001, ShareOptions(codec=codec))


def test_a_budget_gives_the_same_share_whatever_the_paths(tmp_path):
    """The command line and the file names a share records count at a fixed size: folders and
    names of other lengths, and a command line too long for that size (recorded shortened),
    give the same Gaussians in the same map message, in files no larger than the budget."""
    full = random_map(3_000, seed=5)
    shares = []
    long_folder = Path(*["c" * 100] * 3)  # (a command line longer than the fixed size)
    for folder, name in [
        (Path("a"), "s.mcap"),
        (Path("b" * 60), "share_of_agent_a_20kB.mcap"),
        (long_folder, "t.mcap"),
    ]:
        (tmp_path / folder).mkdir(parents=True)
        src = write_log(tmp_path / folder / f"{folder.name[:40]}_a.mcap", full)
        dst = tmp_path / folder / name
        command = f"gsc share {src} -o {dst} --budget 20kB"
        result = share_log(src, dst, "20kB", command=command)
        assert result["file_bytes"] == dst.stat().st_size <= 20_000
        with LogReader(dst) as log:
            ((_, _, message),) = log.iter_messages([TOPIC_GAUSSIANS])
            shares.append((result["selected"], message.data, log.metadata.command))
    assert shares[0][0] < len(full)
    assert len({(count, data) for count, data, _ in shares}) == 1
    assert shares[0][2] == command.replace(str(src), str(tmp_path / "a" / "a_a.mcap")).replace(
        str(dst), str(tmp_path / "a" / "s.mcap")
    )
    assert shares[2][2].endswith("\u2026") and len(shares[2][2].encode()) < RECORDED_TEXT_BYTES


def test_smaller_codecs_fit_more_of_the_same_ranking(tmp_path):
    full = random_map(5_000, seed=4)
    src = write_log(tmp_path / "a.mcap", full)
    results = {
        c: share_log(src, tmp_path / f"{c}.mcap", "100kB", ShareOptions(codec=c, ids=True))
        for c in CODECS
    }
    selected = {c: r["selected"] for c, r in results.items()}
    # 76 vs 54 bytes per Gaussian in the message; the file's zstd chunk shrinks float32 more
    assert selected["fp16"] > 1.2 * selected["fp32"]
    assert selected["compact"] > 2 * selected["fp16"]
    ids = {c: set(read_map(tmp_path / f"{c}.mcap").ids.tolist()) for c in CODECS}
    assert ids["fp32"] < ids["fp16"] < ids["compact"]  # longer prefixes of one ranking
    for codec, r in results.items():
        info = log_info(tmp_path / f"{codec}.mcap")
        assert info["map"]["bytes"] == r["bytes"] and info["file_bytes"] == r["file_bytes"]
        assert r["file_bytes"] <= 100_000 and info["map"]["codec"] == codec
        assert info["map"]["bytes_per_gaussian"] == pytest.approx(r["bytes"] / r["selected"])


def test_fraction_budget_with_fp16(tmp_path):
    src = write_log(tmp_path / "a.mcap", random_map(1000, seed=2))
    r = share_log(src, tmp_path / "s.mcap", 0.2, ShareOptions(codec="fp16"), ply=tmp_path / "s.ply")
    assert r["selected"] == 200 and r["budget"] == 0.2 and "budget_bytes" not in r
    shared = read_map(tmp_path / "s.mcap")
    assert read_ply(tmp_path / "s.ply").equals(shared)  # the PLY holds the decoded float32 values
    assert shared.log_scales.dtype == np.float32


# ---------------------------------------------------------------- fp16 values


@pytest.mark.parametrize("sh_degree, isotropic", [(0, True), (3, False)])
def test_fp16_round_trip_error_is_bounded(tmp_path, sh_degree, isotropic):
    g = random_map(2000, seed=7, isotropic=isotropic, sh_degree=sh_degree)
    g.sh_dc[:5, 0] = [1e-6, -3e-7, 6e-8, 65504.0, -1000.5]  # subnormal, the largest half
    path = tmp_path / "h.mcap"
    with LogWriter(path, LogMetadata()) as log:
        log.write_gaussians(g, 0, "fp16")
    back = read_map(path)
    # float32 at every precision: positions, score sums, ids
    for name in ("means", "importance_sum", "importance_weight", "alpha_t_sum", "ids"):
        assert getattr(back, name).tobytes() == getattr(g, name).tobytes(), name
    assert back.isotropic == isotropic and back.sh_degree == sh_degree
    for name in ("log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"):
        orig = getattr(g, name).astype(np.float64)
        got = getattr(back, name)
        assert got.dtype == np.float32 and got.shape == orig.shape
        err = np.abs(got - orig)
        normal = np.abs(orig) >= 2.0**-14  # float16 normal range: relative error <= 2^-11
        assert np.all(err[normal] <= 2.0**-11 * np.abs(orig[normal])), name
        assert np.all(err[~normal] <= 2.0**-25), name  # subnormal: half a step of 2^-24
        assert np.any(err > 0) or (name == "sh_rest" and sh_degree == 0)  # really rounded


def test_fp16_overflow_is_refused_not_written_as_inf(tmp_path):
    g = random_map(10)
    g.opacity_logits[3] = 70_000.0
    with pytest.raises(MapError, match=r"opacity holds 1 value\(s\) beyond the float16 range"):
        gaussians_to_pointcloud(g, precision="fp16")
    g.opacity_logits[3] = 0.0  # (read from a file, it would be clamped to +-80)
    g.sh_dc[3, 0] = 70_000.0
    src = write_log(tmp_path / "a.mcap", g)  # fine at fp32
    with pytest.raises(MapError, match="use precision fp32"):
        share_log(src, tmp_path / "s.mcap", 1.0, ShareOptions(codec="fp16"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap"]  # no partial output
    g.sh_dc[3, 0] = 0.0
    g.importance_sum[3] = 1e9  # scores and sums stay float32: no range limit
    assert pointcloud_to_gaussians(gaussians_to_pointcloud(g, precision="fp16")).importance_sum[
        3
    ] == np.float32(1e9)


@pytest.mark.parametrize("value", [np.inf, np.nan])
def test_non_finite_after_fp16_decode_is_refused(tmp_path, value):
    g = random_map(8)
    g.quats[2, 1] = value
    path = tmp_path / "h.mcap"
    with LogWriter(path, LogMetadata()) as log:
        log.write_gaussians(g, 0, "fp16")
    with pytest.raises(LogFormatError, match=r"quats \(rot_0..3\) has 1 non-finite"):
        read_map(path)


def _rename_field(cloud, old, new, type_=None):
    for f in cloud.fields:
        if f.name == old:
            f.name = new
            if type_ is not None:
                f.type = type_
    return cloud


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda c: _rename_field(c, "scale_1_f16", "scale_1_f16", type_=4), "must be a uint16"),
        (lambda c: _rename_field(c, "id", "id_f16", type_=3), "its fields span|must be a uint16"),
        (lambda c: _rename_field(c, "x", "opacity"), "appears twice"),
        (lambda c: _rename_field(c, "importance", "opacity"), "'opacity' appears twice"),
    ],
)
def test_half_fields_are_checked(mutate, message):
    cloud = mutate(gaussians_to_pointcloud(random_map(8), precision="fp16"))
    with pytest.raises(MapError, match=message):
        pointcloud_to_gaussians(cloud)


def test_fp16_field_layout_and_old_readers(tmp_path):
    cloud = gaussians_to_pointcloud(random_map(8), precision="fp16")
    types = {f.name: f.type for f in cloud.fields}
    assert all(types[n] == 7 for n in ("x", "y", "z", "importance", "importance_sum"))  # FLOAT32
    assert types["opacity_f16"] == 3 and types["rot_0_f16"] == 3  # UINT16 float16 patterns
    assert types["id"] == 5 and "opacity" not in types
    # a profile 1.0 reader (no `_f16` rule) reports missing fields instead of misreading them
    records = np.frombuffer(
        cloud.data,
        dtype=np.dtype(
            {
                "names": [f.name for f in cloud.fields],
                "formats": [{3: "<u2", 5: "<u4", 7: "<f4"}[f.type] for f in cloud.fields],
                "offsets": [f.offset for f in cloud.fields],
                "itemsize": cloud.point_stride,
            }
        ),
    )
    with pytest.raises(MapError, match="lacks required field"):
        map_from_columns({name: records[name] for name in records.dtype.names})


def test_select_count_matches_top_k():
    g = random_map(50, seed=1)
    kept, index = select_count(g, 7)
    assert len(kept) == 7 and index.tolist() == top_k(g.importance, g.ids, 7).tolist()


def test_pruning_an_fp16_share_keeps_it_fp16(tmp_path):
    src = write_log(tmp_path / "a.mcap", random_map(200, 4))
    share = tmp_path / "s.mcap"
    share_log(src, share, 0.5, ShareOptions(codec="fp16"))
    pruned = tmp_path / "p.mcap"
    prune_log(share, pruned, 0.5, fold=False)
    assert log_info(pruned)["map"]["codec"] == "fp16"
    kept, received = read_map(pruned), read_map(share)
    where = {int(i): k for k, i in enumerate(received.ids)}
    index = [where[int(i)] for i in kept.ids]
    assert len(kept) == 50
    np.testing.assert_array_equal(kept.opacity_logits, received.opacity_logits[index])


def test_a_percentage_of_bytes_is_of_the_maps_fp32_message(tmp_path):
    budget = Budget.parse("5%bytes")
    assert budget.fp32_fraction == 0.05 and budget.budget_bytes is None
    assert Budget.parse("5 %Bytes").fp32_fraction == 0.05
    with pytest.raises(InputError, match="resolve it"):
        budget.count(10, lambda k: k)
    resolved = budget.resolve(1_000_000)
    assert resolved.budget_bytes == 50_000 and str(resolved) == "5%bytes"
    assert resolved.record() == {
        "budget": "5%bytes",
        "budget_bytes": 50_000,
        "budget_fp32_fraction": 0.05,
    }
    with pytest.raises(BudgetError, match="under one byte"):
        Budget.parse("0.0001%bytes").resolve(1000)
    with pytest.raises(InputError):
        Budget.parse("0%bytes")
    full = random_map(3000, seed=9)
    src = write_log(tmp_path / "a.mcap", full)
    fp32 = pointcloud_bytes(full, "fp32")(len(full))
    r = share_log(src, tmp_path / "s.mcap", "20%bytes")
    assert r["budget_bytes"] == int(0.2 * fp32) and r["file_bytes"] <= r["budget_bytes"]
    assert r["selected"] > 0.2 * len(full)  # compact sends more than a fifth of the Gaussians


def test_a_byte_budget_reports_each_cut_it_tries(tmp_path):
    """A byte budget's search (each try a fold and an encoding of the whole share) reports as it
    goes, as `gsc share`'s bar shows; a fraction budget tries no cut."""
    src = write_log(tmp_path / "a.mcap", random_map(2_000, seed=5))
    tried: list[int] = []
    result = share_log(src, tmp_path / "s.mcap", "20kB", progress=tried.append)
    assert 0 < result["selected"] < 2_000
    assert tried[0] == 0 and len(tried) > 2 and tried == list(range(len(tried)))
    fraction: list[int] = []
    share_log(src, tmp_path / "f.mcap", 0.2, progress=fraction.append)
    assert fraction == []
