"""The compact map codec: round trips within its stated bounds, corrupt messages refused, the
schema file, and compact maps in logs."""

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gscompress.errors import InputError, LogFormatError, MapError
from gscompress.gaussians import MAX_ABS_LOG_SCALE, SH_C0, random_map
from gscompress.io import compact as codec
from gscompress.io.compact import (
    COMPACT_DEFAULTS,
    ROTATION_BITS,
    CompactColumn,
    CompactGaussians,
    CompactOptions,
    decode_compact_bytes,
    encode_compact,
)
from gscompress.io.mcap_log import LogMetadata, LogReader, LogWriter, read_map
from gscompress.io.quantise import (
    MAX_POSITION_BITS,
    morton_codes,
    morton_grid,
    morton_order,
    position_step,
    sigmoid,
)
from gscompress.pipeline import log_info, prune_log


def round_trip(g, options=COMPACT_DEFAULTS):
    message = encode_compact(g, options)
    data = message.SerializeToString()
    back, _ = decode_compact_bytes(data)
    return back, message, data


def by_id(g):
    return g.select(np.argsort(g.ids, kind="stable"))


def check_bounds(g, back, message):
    """Every attribute of `back` (decoded, in id order) within its code's half step of `g`."""
    g, back = by_id(g), by_id(back)
    assert back.ids.tolist() == g.ids.tolist()
    if not len(g):
        return
    assert back.isotropic == g.isotropic and back.sh_degree == g.sh_degree
    cols = {c.name: c for c in message.columns}
    step = message.step
    # positions: half a grid step per axis (plus float32 rounding of the decoded value)
    tolerance = step / 2 + 4 * np.finfo(np.float32).eps * (np.abs(g.means).max(initial=0) + 1)
    assert np.all(np.abs(back.means - g.means) <= tolerance)
    for name, got, want in (
        ("log_scale", back.log_scales, g.log_scales),
        ("f_dc", np.arcsinh(back.sh_dc.astype(np.float64)), np.arcsinh(g.sh_dc.astype(np.float64))),
        ("opacity", back.opacities(), sigmoid(g.opacity_logits)),
    ):
        c = cols[name]
        half = (np.array(c.high) - np.array(c.low)) / ((1 << c.bits) - 1) / 2
        err = np.abs(
            np.asarray(got, np.float64).reshape(len(g), -1) - np.asarray(want).reshape(len(g), -1)
        )
        assert np.all(err <= half * (1 + 1e-5) + 1e-6), name
    if not g.isotropic:
        a = g.quats / np.linalg.norm(g.quats, axis=1, keepdims=True)
        b = back.quats / np.linalg.norm(back.quats, axis=1, keepdims=True)
        # each of three components within half a 10-bit step of [-1/sqrt2, 1/sqrt2]
        angle = 2 * np.arccos(np.clip(np.abs((a * b).sum(axis=1)), 0, 1))
        assert np.all(angle < 4 * np.sqrt(2) / ((1 << ROTATION_BITS) - 1))


maps = st.builds(
    lambda n, seed, iso, deg: random_map(n, seed, iso, deg),
    st.integers(0, 400),
    st.integers(0, 10_000),
    st.booleans(),
    st.sampled_from([0, 1, 3]),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(g=maps, ids=st.booleans(), sums=st.booleans())
def test_round_trip_within_the_stated_bounds(g, ids, sums):
    back, message, _ = round_trip(g, CompactOptions(ids=ids, sums=sums))
    assert len(back) == len(g)
    if not ids:  # numbered in the stored order
        assert back.ids.tolist() == list(range(len(g)))
        back.ids[:] = g.ids[np.argsort(morton_codes_of(g, message), kind="stable")]
    check_bounds(g, back, message)
    if len(g):  # the score within half an 8-bit log step: a receiver ranks by it
        check_log_sums(g, back, message, ("importance",))
    if sums:  # the sums within half an 8-bit log step: accumulation and evidence carry on
        check_log_sums(g, back, message)


def test_a_score_written_in_16_bits_still_decodes_to_its_finer_step(monkeypatch):
    """Messages from before the score had 8 bits hold 16-bit score codes; the reader follows
    each column's recorded bits."""
    g = random_map(500, seed=5)
    monkeypatch.setitem(codec.BITS, "importance", 16)
    back, message, _ = round_trip(g)
    (score,) = [c for c in message.columns if c.name == "importance"]
    assert score.bits == 16
    a, b = by_id(g).importance, by_id(back).importance
    assert np.all(np.abs(b - a) <= 1e-3 * a + 1e-30)  # half a 16-bit step: far below 8 bits'
    check_log_sums(g, back, message)


def test_colours_written_as_linear_codes_still_decode(monkeypatch):
    """Messages from before the asinh colour code hold `linear` f_dc codes; the reader follows
    each column's recorded transform."""
    g = random_map(500, seed=6)
    monkeypatch.setattr(codec, "COLOUR_TRANSFORM", "linear")
    monkeypatch.setitem(codec.BITS, "f_dc", 8)
    back, message, _ = round_trip(g)
    (c,) = [c for c in message.columns if c.name == "f_dc"]
    assert c.transform == "linear" and c.bits == 8
    half = (np.array(c.high) - np.array(c.low)) / 255 / 2
    assert np.all(np.abs(by_id(back).sh_dc - by_id(g).sh_dc) <= half * (1 + 1e-5) + 1e-6)


def test_asinh_colours_keep_the_visible_range_fine_despite_outliers(monkeypatch):
    """A few colours far outside [0, 1] (optimisation leaves f_dc up to 20) stretch a linear
    code over every colour; 7-bit asinh codes keep the visible ones finer than 8-bit linear."""
    g = random_map(2000, seed=7)
    rng = np.random.default_rng(7)
    g.sh_dc[:] = rng.uniform(-0.5 / SH_C0, 0.5 / SH_C0, g.sh_dc.shape)  # colours in [0, 1]
    g.sh_dc[:20] = rng.uniform(-4.0, 21.0, (20, 3))
    want = by_id(g).sh_dc
    visible = np.all(np.abs(want) <= 0.5 / SH_C0, axis=1)

    def colour_error() -> float:
        back, message, _ = round_trip(g)
        (c,) = [c for c in message.columns if c.name == "f_dc"]
        assert c.bits == codec.BITS["f_dc"] and c.transform == codec.COLOUR_TRANSFORM
        return float(np.abs(by_id(back).sh_dc - want)[visible].mean())

    asinh = colour_error()
    monkeypatch.setattr(codec, "COLOUR_TRANSFORM", "linear")
    monkeypatch.setitem(codec.BITS, "f_dc", 8)
    assert asinh < 0.75 * colour_error()


def check_log_sums(g, back, message, names=codec.SUMS):
    """The log-coded columns `names` (default: the weight and alpha x T sums) of `back` within
    half a log code step of `g`'s, zero exactly where `g`'s are."""
    cols = {c.name: c for c in message.columns}
    a, b = by_id(g), by_id(back)
    for name in names:
        c, want, got = cols[name], getattr(a, name), getattr(b, name)
        assert c.transform == "log-linear" and c.bits == codec.BITS[name]
        half = (c.high[0] - c.low[0]) / ((1 << c.bits) - 2) / 2
        assert np.array_equal(got > 0, want > 0), name
        ratio = got[want > 0].astype(np.float64) / want[want > 0]
        assert np.all(np.abs(np.log(ratio)) <= half + 1e-6), name


def morton_codes_of(g, message):
    origin, step = np.array(message.origin), message.step
    grid = np.rint((g.means.astype(np.float64) - origin) / step).astype(np.int64)
    return morton_codes(np.clip(grid, 0, (1 << message.position_bits) - 1))


def test_extreme_but_valid_values():
    g = random_map(300, seed=3, isotropic=False, sh_degree=1)
    g.means[0] = [-1e4, 5e3, 0.0]  # a far outlier: the step grows to keep 21 bits per axis
    g.log_scales[1] = [-MAX_ABS_LOG_SCALE, MAX_ABS_LOG_SCALE, 0.0]
    g.opacity_logits[2:4] = [60.0, -60.0]  # opacity 1 and 0 to float precision
    g.quats[4] = [0.0, 0.0, 0.0, -1e-3]  # tiny, negative largest component
    g.sh_dc[5] = [-40.0, 40.0, 0.0]
    g.importance_sum[6], g.importance_weight[6] = 3e30, 1.0
    g.importance_sum[7], g.alpha_t_sum[7] = 1e-44, 1e-44  # subnormal: log below -88
    back, message, _ = round_trip(g)
    assert 0 < back.alpha_t_sum[back.ids == g.ids[7]][0] < 1e-37
    assert message.position_bits == MAX_POSITION_BITS
    assert message.step >= 1e4 / ((1 << MAX_POSITION_BITS) - 1)  # x spans 10 km
    check_bounds(g, back, message)
    assert np.all(np.isfinite(back.opacity_logits))


def test_isotropic_map_has_no_rotation_and_one_scale():
    g = random_map(500, seed=1)
    _, message, _ = round_trip(g)
    names = [c.name for c in message.columns]
    assert "rotation" not in names
    assert next(c for c in message.columns if c.name == "log_scale").components == 1
    _, message, _ = round_trip(random_map(500, seed=1, isotropic=False))
    assert "rotation" in [c.name for c in message.columns]


def test_options_decide_the_columns_and_the_bytes():
    g = random_map(2000, seed=2)
    sizes = {}
    for ids, sums, score in [(True, True, True), (True, False, True), (False, False, False)]:
        _, message, data = round_trip(g, CompactOptions(ids=ids, sums=sums, score=score))
        names = {c.name for c in message.columns}
        assert ("id" in names) == ids
        assert ("alpha_t_sum" in names) == ("importance_weight" in names) == sums
        assert ("importance" in names) == (score or sums)
        assert "importance_sum" not in names  # (importance_sum = score x (weight + eps))
        sizes[(ids, sums, score)] = len(data)
    assert sizes[(False, False, False)] < sizes[(True, False, True)] < sizes[(True, True, True)]


def test_float32_sums_of_earlier_messages_decode_exactly():
    g = random_map(500, seed=4)
    message = encode_compact(g, CompactOptions(sums=False, score=False))
    order = np.argsort(morton_codes_of(g, message), kind="stable")
    zstd = codec.zstandard.ZstdCompressor()
    for name in codec.RAW_SUMS:
        values = getattr(g, name)[order].astype("<f4")
        message.columns.append(codec._column(name, "raw", values, compressor=zstd))
    back, _ = decode_compact_bytes(message.SerializeToString())
    for name in codec.RAW_SUMS:
        assert getattr(by_id(back), name).tobytes() == getattr(by_id(g), name).tobytes(), name
    del message.columns[-1]  # importance_sum and importance_weight without alpha_t_sum
    with pytest.raises(MapError, match="some of the PWAS sums"):
        decode_compact_bytes(message.SerializeToString())


def test_coded_sums_need_the_score_and_both_sums():
    message = encode_compact(random_map(300, seed=5))
    names = [c.name for c in message.columns]
    for drop, what in (("importance", "not the score"), ("alpha_t_sum", "some of the PWAS")):
        broken = CompactGaussians()
        broken.CopyFrom(message)
        del broken.columns[names.index(drop)]
        with pytest.raises(MapError, match=what):
            decode_compact_bytes(broken.SerializeToString())


def test_morton_codes_invert_and_order_neighbours():
    rng = np.random.default_rng(0)
    grid = rng.integers(0, 1 << MAX_POSITION_BITS, (1000, 3))
    assert np.array_equal(morton_grid(morton_codes(grid)), grid)
    assert morton_codes(np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]])).tolist() == [1, 2, 4]


@pytest.mark.parametrize("bits", [3, 16, 17, 42, 3 * MAX_POSITION_BITS])
def test_morton_order_is_the_stable_argsort(bits: int) -> None:
    """The radix sort the encoder orders Gaussians by equals numpy's stable argsort, ties (one
    grid cell) in index order, at every code width."""
    rng = np.random.default_rng(bits)
    codes = rng.integers(0, 1 << bits, 5000, dtype=np.uint64)
    codes[1::9] = codes[::9][: len(codes[1::9])]  # (ties)
    expected = np.argsort(codes, kind="stable")
    np.testing.assert_array_equal(morton_order(codes, bits), expected)
    assert morton_order(codes[:0], bits).tolist() == []


def test_position_step_rule():
    g = random_map(100, seed=0)
    _, step, bits = position_step(g)
    median = float(np.median(np.exp(g.log_scales)))
    assert step == pytest.approx(codec.POSITION_STEP_FRACTION * median)
    extent = float((g.means.max(0) - g.means.min(0)).max())
    assert (1 << (bits - 1)) <= extent / step + 1.5 <= (1 << bits)
    assert position_step(g, 0.01)[1] == 0.01
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="position step"):
            position_step(g, bad)


def test_schema_file_matches_the_descriptor():
    text = (Path(codec.__file__).parents[2] / "schemas" / "compact_gaussians.v1.proto").read_text()
    kinds = {
        1: "double",
        4: "uint64",
        8: "bool",
        9: "string",
        11: "CompactColumn",
        12: "bytes",
        13: "uint32",
    }
    for message in (CompactGaussians, CompactColumn):
        body = re.search(rf"message {message.DESCRIPTOR.name} {{(.*?)\n}}", text, re.S).group(1)
        in_file = re.findall(r"^\s*(repeated )?(\w+) (\w+) = (\d+);", body, re.M)
        in_code = [
            (
                "repeated " if f.is_repeated else "",
                kinds[f.type],
                f.name,
                str(f.number),
            )
            for f in message.DESCRIPTOR.fields
        ]
        assert in_file == in_code


# ---------------------------------------------------------------- hostile messages


def _message(n=50, **options):
    return encode_compact(random_map(n, seed=5, isotropic=False), CompactOptions(**options))


def _column(message, name):
    return next(c for c in message.columns if c.name == name)


@pytest.mark.parametrize(
    "mutate, error",
    [
        (lambda m: setattr(_column(m, "f_dc"), "data", _column(m, "f_dc").data[:-5]), "f_dc"),
        (lambda m: setattr(m, "count", m.count + 1), "declares|bytes"),
        (lambda m: setattr(m, "count", 2**31), "declares 2147483648 Gaussians"),
        (lambda m: setattr(m, "step", 0.0), "grid step 0.0"),
        (lambda m: setattr(m, "step", float("nan")), "grid step nan"),
        (lambda m: m.origin.__setitem__(1, float("inf")), "no finite grid origin"),
        (lambda m: setattr(m, "position_bits", 22), "22 position bits"),
        (lambda m: setattr(m, "version", 2), "has version 2"),
        (lambda m: setattr(_column(m, "opacity"), "raw_bytes", 10**12), "declares 1000000000000"),
        (lambda m: setattr(_column(m, "opacity"), "dtype", "<f8"), "'opacity' is"),
        (lambda m: setattr(_column(m, "log_scale"), "components", 1), "has 1 components"),
        (lambda m: _column(m, "f_dc").low.__setitem__(0, float("nan")), "range beyond"),
        (lambda m: _column(m, "opacity").low.__setitem__(0, -1e300), r"beyond \+-3.40282e\+38"),
        (lambda m: _column(m, "f_dc").high.__setitem__(0, 90.0), r"range beyond \+-89.4"),
        (lambda m: m.origin.__setitem__(0, 1e39), "beyond the float32 range"),
        (lambda m: setattr(_column(m, "f_dc"), "bits", 9), "9 bits in u1"),
        (lambda m: setattr(_column(m, "f_dc"), "data", b"garbage!"), "not a zstd frame"),
        (lambda m: m.columns.remove(_column(m, "rotation")), "lacks column"),
        (lambda m: m.columns.add().CopyFrom(_column(m, "f_dc")), "'f_dc' twice"),
        (lambda m: setattr(_column(m, "id"), "name", "colour"), "unknown column"),
        (lambda m: m.columns.remove(_column(m, "alpha_t_sum")), "not all of them"),
        (lambda m: setattr(m, "isotropic", True), "components|rotations"),
        (lambda m: setattr(m, "sh_degree", 7), "SH degree 7"),
    ],
)
def test_corrupt_messages_are_refused_with_one_line(mutate, error):
    message = _message()
    mutate(message)
    with pytest.raises(MapError, match=error) as caught:
        decode_compact_bytes(message.SerializeToString(), "share.mcap")
    assert "\n" not in str(caught.value) and str(caught.value).startswith("share.mcap")


def test_a_column_declaring_more_than_it_holds_is_refused_before_inflating():
    import zstandard

    message = _message(200)
    c = _column(message, "position")
    bomb = zstandard.ZstdCompressor().compress(bytes(64 << 20))  # 64 MiB of zeros in ~2 kB
    c.data = bomb
    with pytest.raises(MapError, match="declares 67108864 bytes, not 1600"):
        decode_compact_bytes(message.SerializeToString())
    c.data = zstandard.ZstdCompressor(write_content_size=False).compress(bytes(64 << 20))
    with pytest.raises(MapError, match="column 'position'"):
        decode_compact_bytes(message.SerializeToString())


def test_positions_beyond_the_grid_are_refused():
    message = _message()
    c = _column(message, "position")
    deltas = np.full(message.count, (1 << 62), dtype="<u8")  # the sum wraps around 2^64
    import zstandard

    planes = deltas.view(np.uint8).reshape(-1, 8).T.tobytes()
    c.data = zstandard.ZstdCompressor().compress(planes)
    with pytest.raises(MapError, match="outside its"):
        decode_compact_bytes(message.SerializeToString())


def test_not_a_message_is_refused():
    with pytest.raises(MapError, match="corrupt compact map message"):
        decode_compact_bytes(b"\xff\xff\xff\xff")


# ---------------------------------------------------------------- in logs


def test_compact_snapshots_in_a_log_and_info(tmp_path):
    g = random_map(1000, seed=6)
    path = tmp_path / "c.mcap"
    with LogWriter(path, LogMetadata(command="test")) as log:
        log.write_gaussians(g, 0, "fp32")
        log.write_gaussians(g, 1, "compact")
    info = log_info(path)
    assert [s["codec"] for s in info["snapshots"]] == ["fp32", "compact"]
    assert info["map"]["codec"] == "compact" and info["map"]["bytes_per_gaussian"] < 25
    assert info["snapshots"][0]["bytes"] > 3 * info["snapshots"][1]["bytes"]
    with LogReader(path) as log:
        assert {c.schema for c in log.channels} == {
            "foxglove.PointCloud",
            "gscompress.CompactGaussians",
        }
        assert log.read_map(0).equals(g)
    assert len(read_map(path)) == 1000


def test_prune_to_compact_and_back(tmp_path):
    g = random_map(1000, seed=7)
    src = tmp_path / "a.mcap"
    with LogWriter(src, LogMetadata()) as log:
        log.write_gaussians(g, 0)
    prune_log(src, tmp_path / "c.mcap", 0.5, codec="compact")
    assert log_info(tmp_path / "c.mcap")["map"]["codec"] == "compact"
    prune_log(tmp_path / "c.mcap", tmp_path / "d.mcap", 1.0)  # stays compact
    assert log_info(tmp_path / "d.mcap")["map"]["codec"] == "compact"
    prune_log(tmp_path / "c.mcap", tmp_path / "e.mcap", 1.0, codec="fp32")
    assert by_id(read_map(tmp_path / "e.mcap")).equals(by_id(read_map(tmp_path / "c.mcap")))


def test_a_corrupt_compact_snapshot_is_a_log_format_error(tmp_path):
    g = random_map(100, seed=8)
    message = encode_compact(g)
    message.step = -1.0
    path = tmp_path / "bad.mcap"
    with LogWriter(path, LogMetadata()) as log:
        log.write_protobuf("/gaussians", message, 0)
    with pytest.raises(LogFormatError, match=r"bad\.mcap: compact map has grid step -1\.0"):
        read_map(path)
