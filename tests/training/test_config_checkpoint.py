"""Config round trips and command-line overrides; atomic checkpoints."""
import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest
import torch

from pidg.config_tools import (
    add_config_arguments,
    apply_overrides,
    validate_config,
    field_docs,
    load_config,
    overrides_from_args,
    save_config,
    undocumented_options,
)
from pidg.checkpoint import atomic_torch_save, load_checkpoint


@dataclass
class Inner:
    rate: float = 0.1
    mode: Literal["a", "b"] = "a"
    size: float | tuple[int, int] = 1.0
    path: Path | None = None


@dataclass
class Outer:
    steps: int = 10
    flag: bool = False
    inner: Inner = field(default_factory=Inner)
    maybe: Inner | None = None


def test_cli_overrides_and_json_round_trip(tmp_path):
    parser = argparse.ArgumentParser()
    add_config_arguments(parser, Outer)
    args = parser.parse_args(["--steps", "5", "--inner.mode", "b", "--inner.size", "400x300", "--flag", "true", "--maybe.rate", "2"])
    cfg = apply_overrides(Outer(), overrides_from_args(args))
    assert cfg == Outer(steps=5, flag=True, inner=Inner(mode="b", size=(400, 300)), maybe=Inner(rate=2.0))
    save_config(cfg, tmp_path / "c.json")
    assert load_config(Outer, tmp_path / "c.json") == cfg


def test_several_values_are_separate_words_or_one_comma_separated_word():
    """``--data.splits train val test`` (as the help's defaults print them) and ``train,val,test`` mean the same; a
    single-valued option still takes one word."""
    from pidg.training.config import TrainConfig

    parser = argparse.ArgumentParser()
    add_config_arguments(parser, TrainConfig)
    spaced = parser.parse_args(["--data.splits", "train", "val", "test", "--gaussian_optim.betas", "0.8", "0.99"])
    commas = parser.parse_args(["--data.splits", "train,val,test", "--gaussian_optim.betas", "0.8,0.99"])
    for args in (spaced, commas):
        cfg = apply_overrides(TrainConfig(), overrides_from_args(args))
        assert cfg.data.splits == ("train", "val", "test") and cfg.gaussian_optim.betas == (0.8, 0.99)
    with pytest.raises(SystemExit):
        parser.parse_args(["--optim.iterations", "5", "6"])


def test_an_int_or_three_option_takes_one_word_three_words_or_commas():
    """A hash grid's resolution is one int or three (x y z): as separate words (the help's form), comma-separated, or
    one int; two words are an error that names the option."""
    from pidg.training.config import TrainConfig

    parser = argparse.ArgumentParser()
    add_config_arguments(parser, TrainConfig)
    option = "--deformation.grid4d.temporal_grid.finest_resolution"
    for words, expected in ((["32", "32", "64"], (32, 32, 64)), (["32,32,64"], (32, 32, 64)), (["48"], 48)):
        cfg = apply_overrides(TrainConfig(), overrides_from_args(parser.parse_args([option, *words])))
        assert cfg.deformation.grid4d.temporal_grid.finest_resolution == expected
    with pytest.raises(ValueError, match="finest_resolution"):
        apply_overrides(TrainConfig(), overrides_from_args(parser.parse_args([option, "32", "64"])))


def test_sizes_parse_with_x_but_names_keep_it():
    @dataclass
    class Names:
        nets: tuple[str, ...] = ("vgg",)

    assert apply_overrides(Outer(), {"inner.size": "2.5"}).inner.size == 2.5
    assert apply_overrides(Names(), {"nets": "alex,vgg"}).nets == ("alex", "vgg")


@pytest.mark.parametrize("override,match", [({"inner.mode": "c"}, "one of a, b"), ({"steps": "x"}, "--steps"), ({"rate": "1"}, "did you mean inner.rate")])
def test_bad_overrides(override, match):
    with pytest.raises(ValueError, match=match):
        apply_overrides(Outer(), override)


def test_malformed_config_file(tmp_path):
    (tmp_path / "c.json").write_text('{"steps": 3,,}')
    with pytest.raises(ValueError, match="line 1 column"):
        load_config(Outer, tmp_path / "c.json")


def test_atomic_save_keeps_old_file_on_failure(tmp_path):
    path = tmp_path / "ckpt.pt"
    atomic_torch_save({"step": 1, "w": torch.ones(3)}, path)

    class Unpicklable:
        def __reduce__(self):
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        atomic_torch_save({"step": 2, "bad": Unpicklable()}, path)
    assert load_checkpoint(path)["step"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # no temporary left behind
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(RuntimeError, match="junk.pt"):
        load_checkpoint(tmp_path / "junk.pt")
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.pt")


@dataclass
class Documented:
    """A config whose fields say what they are."""

    mode: Literal["fast", "exact"] = "fast"
    """How to compute it."""
    size: int = 3  # a comment is not documentation
    """Side in pixels."""
    bare: float = 1.0

    def __post_init__(self) -> None:
        validate_config(self)


def test_docstrings_are_the_help_and_literals_the_choices():
    assert field_docs(Documented) == {"mode": "How to compute it.", "size": "Side in pixels.", "bare": ""}
    assert undocumented_options(Documented) == ["bare"]
    parser = argparse.ArgumentParser()
    add_config_arguments(parser, Documented)
    text = parser.format_help()
    assert "--mode {fast,exact}" in text and "How to compute it. (default: fast)" in text
    with pytest.raises(ValueError, match=r"Documented.mode must be one of fast, exact, got 'slow'"):
        Documented(mode="slow")  # type: ignore[arg-type]  # Python callers get the command line's check


def test_the_run_config_round_trips_through_json_with_every_section_changed(tmp_path):
    from pidg.models.deformation import HashGridConfig
    from pidg.training.config import TrainConfig, apply_preset

    cfg = apply_overrides(apply_preset(TrainConfig(), "cpu"), {
        "data.downscale": "400x300", "data.splits": "train,val", "gaussians.random_init_box": "none",
        "deformation.kind": "mlp", "deformation.mlp.skips": "1,2", "material.stress": "false", "physics.kind": "cmr",
        "flow.raft_weights": "/w/raft.pt2", "gaussian_optim.betas": "0.8,0.99", "optim.time_budget_minutes": "2.5",
    })
    cfg.gaussians.random_init_box = ((-1.0, -2.0, -3.0), (1.0, 2.0, 3.0))
    save_config(cfg, tmp_path / "config.json")
    back = load_config(TrainConfig, tmp_path / "config.json")
    assert back == cfg
    assert back.deformation.grid4d.temporal_grid == HashGridConfig(16, 2, 15, (8, 8, 8), (32, 32, 16))  # tuples again
    assert isinstance(back.flow.raft_weights, Path) and back.data.downscale == (400, 300)
    (tmp_path / "bad.json").write_text('{"physics": {"kind": "pde"}}')
    with pytest.raises(ValueError, match=r"bad.json: TrainConfig.physics.kind must be one of none, cmr"):
        load_config(TrainConfig, tmp_path / "bad.json")


def test_pidg_train_help_documents_every_option(capsys):
    from pidg.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "-h"])
    text = capsys.readouterr().out
    assert "--physics.samples VALUE" in text and "M: random particles per step" in text
    assert "--deformation.kind {grid4d,mlp,identity}" in text and "--material.stress {true,false}" in text
