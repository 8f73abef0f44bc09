"""Checkpoints load with ``torch.load(weights_only=True)``: a plain state dict loads, a file that needs pickled
Python objects is refused with a message naming it, and loads only once that file is trusted by name."""

from __future__ import annotations

import os
from dataclasses import dataclass

import pytest
import torch

from aeroloc.core import weights
from aeroloc.core.errors import AerolocError
from aeroloc.core.weights import TRUST_ENV, is_trusted, load_state_dict, trust_checkpoints


@dataclass
class TrainingArgs:  # what training scripts often save beside the weights (an argparse Namespace, a config)
    lr: float = 0.1
    epochs: int = 3


class WholeModel:
    """Stands for a pickled model object (``torch.save(model)``): only its state dict is wanted."""

    def __init__(self, state: dict):
        self.state = state

    def state_dict(self) -> dict:
        return self.state


@pytest.fixture(autouse=True)
def no_trust(monkeypatch):
    monkeypatch.setattr(weights, "_TRUSTED", set())
    monkeypatch.delenv(TRUST_ENV, raising=False)


def _state() -> dict:
    torch.manual_seed(0)
    return {"conv.weight": torch.randn(4, 3, 3, 3), "conv.bias": torch.randn(4)}


def _assert_equal(loaded: dict, state: dict) -> None:
    assert loaded.keys() == state.keys()
    assert all(torch.equal(loaded[k], state[k]) for k in state)


def test_a_plain_state_dict_loads(tmp_path):
    state = _state()
    torch.save({"module." + k: v for k, v in state.items()}, tmp_path / "plain.pth")
    torch.save({"state_dict": state, "epoch": 3, "note": "x", "best": 0.5}, tmp_path / "nested.pth")
    torch.save(state, tmp_path / "legacy.pth", _use_new_zipfile_serialization=False)  # can't be memory-mapped

    _assert_equal(load_state_dict(tmp_path / "plain.pth"), state)
    _assert_equal(load_state_dict(tmp_path / "nested.pth", key="state_dict"), state)
    _assert_equal(load_state_dict(tmp_path / "legacy.pth"), state)


def test_a_damaged_file_is_unreadable_not_untrusted(tmp_path):
    path = tmp_path / "damaged.pth"
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(AerolocError, match="not a readable PyTorch checkpoint") as e:
        load_state_dict(path)
    assert "trust" not in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("what", ["object-beside-the-weights", "whole-model"])
def test_a_pickled_object_is_refused_until_the_file_is_trusted(what, tmp_path):
    state = _state()
    path = tmp_path / "pickled.pth"
    torch.save({**state, "args": TrainingArgs()} if what == "object-beside-the-weights" else WholeModel(state), path)

    with pytest.raises(AerolocError) as refused:
        load_state_dict(path)
    msg = str(refused.value)
    assert "\n" not in msg and msg.startswith(f"{path}: ")
    assert ("TrainingArgs" if what == "object-beside-the-weights" else "WholeModel") in msg
    assert f"--trust-checkpoint {path}" in msg and TRUST_ENV in msg

    trust_checkpoints([path])
    loaded = load_state_dict(path)
    if what == "object-beside-the-weights":
        assert loaded.pop("args") == TrainingArgs()
    _assert_equal(loaded, state)


def test_trust_is_by_resolved_path_and_from_the_environment(tmp_path, monkeypatch):
    path = tmp_path / "pickled.pth"
    other = tmp_path / "other.pth"
    torch.save({**_state(), "args": TrainingArgs()}, path)
    torch.save({**_state(), "args": TrainingArgs()}, other)

    monkeypatch.setenv(
        TRUST_ENV, os.pathsep.join([str(tmp_path / "elsewhere.pth"), str(tmp_path / "." / "x/../pickled.pth")])
    )
    assert is_trusted(path) and not is_trusted(other)
    assert load_state_dict(path)["args"] == TrainingArgs()
    with pytest.raises(AerolocError, match=r"other\.pth"):  # trusting one file trusts no other
        load_state_dict(other)

    monkeypatch.chdir(tmp_path)
    trust_checkpoints(["other.pth"])  # a relative --trust-checkpoint names the same file
    assert is_trusted(other)


def test_a_method_with_a_pickled_checkpoint_is_refused_and_loads_when_trusted(tmp_path):
    from aeroloc.retrieval.models import build_method, method_class

    conf = {"backbone": "ResNet18", "dim": 32, "resize": 256}
    state = method_class("cosplace")(conf).state_dict()
    path = tmp_path / "cosplace-whole.pth"
    torch.save(WholeModel(state), path)

    with pytest.raises(AerolocError, match="--trust-checkpoint"):
        build_method("cosplace", conf, path)
    trust_checkpoints([path])
    _assert_equal(build_method("cosplace", conf, path).state_dict(), state)


@pytest.mark.parametrize(
    "argv",
    [
        ["build", "map", "--out", "db", "--weights", "w.pth"],
        ["retrieve", "db", "queries.csv", "--out", "r.csv"],
        ["localize", "db", "queries.csv", "--out", "r.csv"],
    ],
)
def test_the_commands_that_load_weights_take_trust_checkpoint(argv, tmp_path, monkeypatch):
    from aeroloc.cli import build_parser
    from aeroloc.commands.build import trust_from_args

    monkeypatch.chdir(tmp_path)
    args = build_parser().parse_args([*argv, "--trust-checkpoint", "a.pth", "--trust-checkpoint", "b.pth"])
    assert args.trust_checkpoint == ["a.pth", "b.pth"]
    assert not is_trusted("a.pth")
    trust_from_args(args)
    assert is_trusted(tmp_path / "a.pth") and is_trusted(tmp_path / "b.pth") and not is_trusted("c.pth")
