"""Fixtures of the track tests (helpers in ``track_synthetic``)."""

from __future__ import annotations

import pytest

from stages.track.synthetic import SyntheticScene, make_scene
from track_synthetic import write_capture


@pytest.fixture(autouse=True)
def _single_blas_thread():
    """The fits solve small dense problems; BLAS threads only contend on a shared CPU."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        yield


@pytest.fixture(scope="module")
def scene() -> SyntheticScene:
    return make_scene()


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    """A rendered 13-frame capture (5 full-on frames) from 5 cameras, shared by a test module."""
    return write_capture(tmp_path_factory.mktemp("capture"), frames=13)
