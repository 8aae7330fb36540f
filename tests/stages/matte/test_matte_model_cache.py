"""The shared cache of trained matting models."""

import logging

import torch

from stages.matte.model_cache import cache_key, load_or_train, state_equal
from stages.matte.modnet import SIZES, MODNet

LOG = logging.getLogger("test")


def _trainer(calls):
    def train():
        calls.append(1)
        torch.manual_seed(len(calls))
        return MODNet(SIZES["tiny"]).eval(), {"training": {"seconds": 1.0}}
    return train


def test_second_load_hits_the_cache(tmp_path):
    calls = []
    key = cache_key({"iterations": 3}, "code")
    first, meta, cached = load_or_train(tmp_path, key, _trainer(calls), LOG)
    second, _, cached_again = load_or_train(tmp_path, key, _trainer(calls), LOG)
    assert (cached, cached_again) == (False, True) and len(calls) == 1
    assert state_equal(first, second) and meta["key"] == key


def test_key_depends_on_params_and_code():
    assert cache_key({"a": 1}, "x") != cache_key({"a": 2}, "x")
    assert cache_key({"a": 1}, "x") != cache_key({"a": 1}, "y")
    assert cache_key({"a": 1, "b": 2}, "x") == cache_key({"b": 2, "a": 1}, "x")


def test_corrupt_entry_is_retrained(tmp_path):
    calls = []
    key = cache_key({}, "c")
    load_or_train(tmp_path, key, _trainer(calls), LOG)
    (tmp_path / "matte_models" / key / "model.safetensors").write_bytes(b"garbage")
    _, _, cached = load_or_train(tmp_path, key, _trainer(calls), LOG)
    assert cached is False and len(calls) == 2
