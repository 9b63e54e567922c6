"""The fast part of the fuzz suite: hypothesis-driven structural mutations of valid inputs of
every reader in `fuzzing.TARGETS`; each case must be read or refused with a GscError. The long
run is `make fuzz` (tests/fuzzing.py)."""

import tempfile
from pathlib import Path

import pytest
from fuzzing import TARGETS, FuzzTarget, RandomChooser, run_case
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

SLOW_TARGETS = ("recordings",)
"""Readers whose cases take seconds each (a bag is written and opened per case)."""

MARKED_TARGETS = [
    pytest.param(t, marks=pytest.mark.slow, id=t.name) if t.name in SLOW_TARGETS else t
    for t in TARGETS
]


class HypothesisChooser:
    """A mutator's choices drawn from hypothesis (so that it can shrink a failing case)."""

    def __init__(self, data: st.DataObject):
        self.data = data

    def integer(self, low: int, high: int) -> int:
        return self.data.draw(st.integers(low, high))

    def pick(self, options):
        return self.data.draw(st.sampled_from(list(options)))


def _skip_if_missing(target: FuzzTarget) -> None:
    if target.missing():
        pytest.skip(f"{target.name}: {target.missing()}")


@pytest.mark.parametrize("target", MARKED_TARGETS, ids=lambda t: t.name)
@settings(
    max_examples=150,
    deadline=None,
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate],  # (shrinking a structural case takes minutes)
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(data=st.data())
def test_a_mutated_input_is_read_or_refused_with_a_gsc_error(target: FuzzTarget, data):
    _skip_if_missing(target)
    with tempfile.TemporaryDirectory() as tmp:
        outcome, detail = run_case(target, HypothesisChooser(data), Path(tmp))
    assert outcome in ("ok", "refused"), detail


@pytest.mark.parametrize("target", MARKED_TARGETS, ids=lambda t: t.name)
def test_the_mutations_reach_both_reads_and_refusals(target: FuzzTarget):
    """Mutations that only ever broke the file at its first byte would test little."""
    _skip_if_missing(target)
    outcomes = set()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(40):
            outcomes.add(run_case(target, RandomChooser(seed), Path(tmp))[0])
    assert outcomes == {"ok", "refused"}


def test_every_valid_input_reads():
    from gscompress.errors import PlyFormatError

    with tempfile.TemporaryDirectory() as tmp:
        for target in (t for t in TARGETS if not t.missing()):
            for seed in range(30):
                path = Path(tmp) / f"valid{target.suffix}"
                path.write_bytes(target.make_valid_input(RandomChooser(seed)))
                try:
                    target.read(path)
                except PlyFormatError as exc:  # the packed layout: named, not read
                    assert "compressed PLY" in str(exc)
