"""SLAM configuration: presets, YAML round trips, overrides and refusals."""

import json
import math

import pytest

from gscompress.errors import InputError, OptionError
from gscompress.slam.config import (
    PRESETS,
    SlamConfig,
    load_config,
    preset,
    resolve_config,
    save_config,
)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_round_trip_through_yaml(name, tmp_path):
    path = save_config(preset(name), tmp_path / "c.yaml")
    assert load_config(path, "tiny") == preset(name)
    assert SlamConfig.from_dict(preset(name).to_dict()) == preset(name)


def test_partial_file_applies_on_top_of_its_preset(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("preset: paper\nmapping:\n  iters: 7\nsize: [80, 60]\nprune:\n  stages: []\n")
    config = load_config(path, "cpu")
    assert config.mapping.iters == 7 and config.size == (80, 60) and config.prune.stages == ()
    assert config.tracking == preset("paper").tracking
    path.write_text("tracking:\n  iters: 3\n")
    assert load_config(path, "tiny").keyframes == preset("tiny").keyframes


@pytest.mark.parametrize(
    "text, message",
    [
        (
            "mapping:\n  itres: 3\n",
            "c.yaml: unknown key 'mapping.itres' .did you mean 'mapping.iters'",
        ),
        ("mapping: 3\n", "c.yaml: mapping: expected a mapping, got 3"),
        ("mapping:\n  iters: 2.5\n", "expected an integer"),
        ("prune:\n  keep: 1.5\n", "prune.keep"),
        ("prune:\n  by: size\n", "prune.by must be one of pwas, opacity, random, alpha-t"),
        ("prune:\n  refine_iters: -1\n", "refinement iterations"),
        ("mapping:\n  final_iters: -2\n", "refinement iterations"),
        ("mapping:\n  final_iters_per_frame: -1\n", "refinement iterations"),
        ("mapping:\n  final_lr_fraction: 0\n", "mapping.final_lr_fraction must be in"),
        ("mapping:\n  final_lr_fraction: 1.5\n", "mapping.final_lr_fraction must be in"),
        ("mapping:\n  final_views: all\n", "mapping.final_views is one of frames, keyframes"),
        ("size: [80]\n", "size"),
        ("isotropic: 1\n", "true or false"),
        ("prune:\n  refill: all\n", "prune.refill must be one of off, current, keyframes"),
        ("preset: nope\n", "unknown SLAM preset"),
        ("- 1\n", "mapping"),
        ("mapping: [1\n", "cannot read config"),
        ("mapping:\n  lr_means: .inf\n", "mapping.lr_means: expected a finite number, got inf"),
        ("pwas:\n  sigma_d: .nan\n", "pwas.sigma_d: expected a finite number"),
        ("prune:\n  stages: [0.5, .nan]\n", "expected a list of finite numbers"),
        ("mapping:\n  lr_colors: 1.0e+38\n", "learning rates must be at most 1000"),
        ("tracking:\n  lr_translation: 1001\n", "learning rates must be at most 1000"),
        ("size: 9000x10\n", "size: at most 8192 a side"),
    ],
)
def test_bad_files_are_refused_with_a_clear_message(tmp_path, text, message):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        load_config(path)


@pytest.mark.parametrize(
    "text, refill",
    [("true", "keyframes"), ("false", "off"), ("off", "off"), ("current", "current")],
)
def test_refill_reads_its_modes_and_the_old_booleans(tmp_path, text, refill):
    path = tmp_path / "c.yaml"
    path.write_text(f"prune:\n  refill: {text}\n")
    assert load_config(path).prune.refill == refill


def test_resolve_config_applies_command_line_overrides(tmp_path):
    config = resolve_config("tiny", size=(40, 30), keep=0.5)
    assert config.size == (40, 30) and config.prune.keep == 0.5
    assert config.mapping == preset("tiny").mapping
    assert resolve_config("tiny", no_prune=True).prune.stages == ()
    capped = tmp_path / "capped.yaml"
    capped.write_text("prune:\n  max_gaussians: 5000\n")
    assert resolve_config("tiny", capped).prune.max_gaussians == 5000
    assert resolve_config("tiny", capped, no_prune=True).prune.max_gaussians == 0
    assert resolve_config("cpu") == preset("cpu") == resolve_config()
    with pytest.raises(OptionError, match="`keep` does not go with `no_prune`"):
        resolve_config("tiny", keep=0.5, no_prune=True)


def test_a_config_file_and_preset_must_agree(tmp_path):
    """The file's `preset:` is the base when --preset is not given; given, they must agree
    (a saved config names its preset, and silently starting from another was a trap)."""
    named = tmp_path / "named.yaml"
    named.write_text("preset: tiny\nmapping:\n  iters: 4\n")
    plain = tmp_path / "plain.yaml"
    plain.write_text("mapping:\n  iters: 4\n")
    assert resolve_config(None, named) == preset("tiny").with_overrides(**{"mapping.iters": 4})
    assert resolve_config("tiny", named) == resolve_config(None, named)
    assert resolve_config("paper", plain).tracking == preset("paper").tracking
    assert resolve_config(None, plain).preset == "cpu"
    with pytest.raises(OptionError, match="starts from preset 'tiny', not `preset` paper"):
        resolve_config("paper", named)


def test_size_may_be_written_as_on_the_command_line(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("size: 64x48\n")
    assert load_config(path).size == (64, 48)
    path.write_text("size: 64x\n")
    with pytest.raises(InputError, match=r"c.yaml: size: expected WxH"):
        load_config(path)


@pytest.mark.parametrize("name", ["cpu", "paper"])
def test_example_configs_equal_their_presets(name):
    from pathlib import Path

    import yaml

    path = Path(__file__).parents[1] / "examples" / "configs" / f"{name}.yaml"
    assert load_config(path, "tiny") == preset(name), f"regenerate {path} with save_config"
    # every key written out, so that the example shows each setting there is
    assert yaml.safe_load(path.read_text()) == yaml.safe_load(
        yaml.safe_dump(preset(name).to_dict())
    ), f"regenerate {path} with save_config"


def test_the_own_anchor_example_is_the_cpu_preset_tracking_longer():
    from pathlib import Path

    path = Path(__file__).parents[1] / "examples" / "configs" / "own-anchor.yaml"
    config, cpu = load_config(path, "tiny"), preset("cpu")
    assert config.tracking.iters > cpu.tracking.iters
    assert not config.init_from_ground_truth
    as_cpu = config.with_overrides(
        init_from_ground_truth=cpu.init_from_ground_truth,
        **{"tracking.iters": cpu.tracking.iters},
    )
    assert as_cpu == cpu  # nothing else differs from the preset


@pytest.mark.parametrize(
    "text, sigma_d",
    [("auto", None), ("null", None), ("2.5", 2.5), (".inf", math.inf), ("inf", math.inf)],
)
def test_pwas_sigma_d_is_auto_a_distance_or_inf_and_round_trips(tmp_path, text, sigma_d):
    assert preset("cpu").pwas.sigma_d is None  # scale-aware by default
    path = tmp_path / "c.yaml"
    path.write_text(f"pwas:\n  sigma_d: {text}\n")
    config = load_config(path)
    assert config.pwas.sigma_d == sigma_d
    assert load_config(save_config(config, tmp_path / "again.yaml")) == config
    assert json.loads(json.dumps(config.to_dict(), allow_nan=False)) == config.to_dict()
    assert SlamConfig.from_dict(config.to_dict()) == config


@pytest.mark.parametrize("text", ["0", "-1", "-.inf", "near", "true"])
def test_pwas_sigma_d_refuses_what_is_not_a_distance(tmp_path, text):
    path = tmp_path / "c.yaml"
    path.write_text(f"pwas:\n  sigma_d: {text}\n")
    with pytest.raises(InputError, match=r"pwas\.sigma_d: expected a finite number above 0, inf"):
        load_config(path)
