"""FlowConfig: validation, the step schedule, and the --flow.* command-line / JSON round trip."""
from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path

import pytest

import pidg  # noqa: F401
from pidg.config_tools import (
    add_config_arguments,
    apply_overrides,
    from_jsonable,
    overrides_from_args,
    to_jsonable,
)
from pidg.flow import FlowConfig


@dataclass
class Wrapper:
    flow: FlowConfig = field(default_factory=FlowConfig)


def test_defaults_follow_the_paper():
    config = FlowConfig()
    assert (config.lambda_lpfm, config.lambda_gaussian, config.lambda_velocity) == (0.01, 0.5, 0.5)
    assert config.kind == "none" and not config.enabled and config.estimator == "dis"


def test_schedule():
    config = FlowConfig(kind="lpfm", start=100)
    assert not config.active(99) and config.active(100) and config.active(10_000)
    assert not FlowConfig(kind="none").active(10_000)


@pytest.mark.parametrize(
    "bad", [{"kind": "flow"}, {"estimator": "farneback"}, {"lambda_gaussian": -1.0}, {"start": -1},
            {"mask_dilation": -2}, {"cache_dir": ""}, {"dis_preset": "slow"}],
)
def test_invalid_values_are_rejected(bad: dict):
    with pytest.raises(ValueError, match="FlowConfig"):
        FlowConfig(**bad)


def test_command_line_and_json_round_trip():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser, Wrapper)
    args = parser.parse_args(["--flow.kind", "lpfm", "--flow.estimator", "tvl1", "--flow.raft_weights", "/w/raft.pt2",
                              "--flow.start", "500", "--flow.mask_dilation", "0"])
    config = apply_overrides(Wrapper(), overrides_from_args(args))
    assert config.flow.kind == "lpfm" and config.flow.estimator == "tvl1" and config.flow.start == 500
    assert config.flow.raft_weights == Path("/w/raft.pt2")
    assert from_jsonable(Wrapper, json.loads(json.dumps(to_jsonable(config)))) == config
