"""Stage configs with groups of parameters, and the ``mosiv`` options generated from them."""

from __future__ import annotations

import dataclasses

import pytest
import yaml

from mosiv_ros.cli import build_parser, fit_options, load_params_file, loop_options, run_config
from mosiv_ros.config import (
    FitConfig,
    IdentifyConfig,
    describe,
    flat,
    from_mapping,
    parameters,
    updated,
    value_of,
    value_range,
)
from mosiv_ros.io.scene import FAMILIES
from mosiv_ros.loop.closure import LoopConfig


def test_a_groups_parameters_are_named_with_its_name_and_a_dot():
    names = [name for name, _, _ in describe(IdentifyConfig)]
    assert names[:4] == ["search.samples", "search.rounds", "search.starts", "search.frames"]
    assert {"curriculum.horizons", "curriculum.iterations", "loss.per_object", "max_modulus",
            "families", "device"} <= set(names)
    assert len(names) == len(set(names))
    assert value_range(IdentifyConfig, "curriculum.windows") == (1, 1000)
    assert value_of(IdentifyConfig(), "search.samples") == IdentifyConfig().search.samples == 32
    assert IdentifyConfig().families == list(FAMILIES)  # one home of the families: io.scene


def test_a_mapping_may_nest_groups_or_name_them_with_dots_and_is_checked():
    nested = from_mapping(IdentifyConfig, {"search": {"samples": 8, "rounds": 1}, "window": 12})
    dotted = from_mapping(IdentifyConfig, {"search.samples": 8, "search.rounds": 1, "window": 12})
    assert nested == dotted
    assert (nested.search.samples, nested.search.rounds, nested.search.starts) == (8, 1, 3)
    assert flat({"a": {"b": {"c": 1}}, "d": [1, 2]}) == {"a.b.c": 1, "d": [1, 2]}
    with pytest.raises(ValueError, match="unknown parameter.s. search.sample;"):
        from_mapping(IdentifyConfig, {"search": {"sample": 8}})
    with pytest.raises(ValueError, match="unknown parameter.s. search;"):  # a group is no value
        from_mapping(IdentifyConfig, {"search": 8})
    with pytest.raises(ValueError, match=r"curriculum.windows: 0 is out of range \[1, 1000\]"):
        from_mapping(IdentifyConfig, {"curriculum": {"windows": 0}})


def test_updated_changes_only_what_it_is_given_and_copies_the_rest():
    config = IdentifyConfig()
    changed = updated(config, {"curriculum.iterations": 3, "loss": {"per_object": False}})
    assert (changed.curriculum.iterations, changed.loss.per_object) == (3, False)
    assert (config.curriculum.iterations, config.loss.per_object) == (20, True)
    changed.curriculum.horizons.append(7)
    assert config.curriculum.horizons == [5, 10, 15, 25, 0]
    with pytest.raises(ValueError, match="search.starts: 0 is out of range"):
        updated(config, {"search.starts": 0})


def test_every_fit_parameter_is_an_option_of_run_and_close_loop_over_the_params_file(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"identify_node": {"ros__parameters": {
        "search": {"samples": 16, "rounds": 1}, "curriculum": {"iterations": 3}}}}))
    for command in (["run", "bag", "--out", "o"], ["close-loop", "bag", "--out", "o"]):
        args = build_parser().parse_args([*command, "--search.samples", "4", "--curriculum.horizons",
                                          "[8, 0]", "--loss.per_object", "false"])
        assert fit_options(args) == {"search.samples": 4, "curriculum.horizons": [8, 0],
                                     "loss.per_object": False}
        identify = run_config(params, fit=fit_options(args)).identify
        assert identify.search.samples == 4  # the option over the file
        assert identify.search.rounds == 1 and identify.curriculum.iterations == 3  # the file's
        assert identify.curriculum.horizons == [8, 0] and identify.loss.per_object is False
    defaults = {name: value_of(FitConfig(), name) for name, _, _ in parameters(FitConfig)}
    every = [text for name, value in defaults.items()  # each default as one would type it
             for text in (f"--{name}", yaml.safe_dump(value, default_flow_style=True).removesuffix("\n...\n")
                          if isinstance(value, bool | list) else str(value))]
    assert fit_options(build_parser().parse_args(["run", "bag", "--out", "o", *every])) == defaults
    assert fit_options(build_parser().parse_args(["run", "bag", "--out", "o"])) == {}
    assert load_params_file(params)["identify_node"] == run_config(params).identify


@pytest.mark.parametrize("argv, message", [
    (["--search.samples", "x"], "argument --search.samples: expected int, got 'x'"),
    (["--loss.per_object", "3"], "argument --loss.per_object: expected a YAML bool, got '3'"),
    (["--curriculum.horizons", "5"], "argument --curriculum.horizons: expected a YAML list.int., got '5'"),
])
def test_a_fit_option_of_the_wrong_type_is_refused_naming_it(argv, message, capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", "bag", "--out", "o", *argv])
    assert message.replace(".int.", "[int]") in capsys.readouterr().err


def test_a_fit_option_out_of_its_range_is_refused_naming_it():
    args = build_parser().parse_args(["run", "bag", "--out", "o", "--search.starts", "0"])
    with pytest.raises(ValueError, match=r"search.starts: 0 is out of range \[1, 100\]"):
        run_config(None, fit=fit_options(args))


def test_loop_options_left_out_keep_the_loop_configs_defaults():
    defaults = dataclasses.asdict(LoopConfig())
    args = build_parser().parse_args(["close-loop", "bag", "--out", "o"])
    assert LoopConfig(**loop_options(args)) == LoopConfig()
    args = build_parser().parse_args(["close-loop", "bag", "--out", "o", "--top-k", "5"])
    assert LoopConfig(**loop_options(args)).top_k == 5
    assert LoopConfig(**loop_options(args)).max_rounds == defaults["max_rounds"]
