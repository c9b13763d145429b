"""Config round trips and command-line overrides; atomic checkpoints."""
import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest
import torch

from pidg.config_tools import add_config_arguments, apply_overrides, load_config, overrides_from_args, save_config
from pidg.training.checkpoint import atomic_torch_save, load_checkpoint


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
