"""Fixtures shared by the avatar tests: the raymarch kernels to run a test on."""

from __future__ import annotations

import pytest

from avatar.raymarch_fused import fused_module


def _skip_unless_fused_builds() -> None:
    if fused_module(required=False) is None:
        pytest.skip("the fused raymarcher cannot be built here (no C++ compiler); CI installs g++")


@pytest.fixture(params=["torch", "fused"])
def kernel(request) -> str:
    """Each CPU fast path of ``avatar.raymarch.raymarch`` in turn."""
    if request.param == "fused":
        _skip_unless_fused_builds()
    return request.param


@pytest.fixture
def fused_kernel() -> str:
    """The fused kernel, for tests that compare it with the tensor path."""
    _skip_unless_fused_builds()
    return "fused"
