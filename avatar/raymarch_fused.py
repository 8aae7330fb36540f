"""The fused CPU raymarcher (``raymarch_fused.cpp``), built on first use, and its autograd function.

``avatar.raymarch.raymarch`` uses it for CPU float tensors when ``kernel`` is ``"auto"`` or
``"fused"``. It renders the same images and gradients as the PyTorch fast path (tests
compare the two forward and backward, and against the slow reference), at a fraction of
the time and memory: no (sample, primitive) pair tensors are built.

The C++ source is compiled with ``torch.utils.cpp_extension.load`` the first time a process
needs it (~20 s on 2 cores; needs a C++ compiler) and cached under
``$TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``); later processes load the
cached build in well under a second, and concurrent processes share one build (an OS lock,
which also clears the file lock a build killed midway leaves behind). Without a compiler, ``"auto"`` falls back to the PyTorch path with one warning
and ``"fused"`` raises ``FusedKernelUnavailable`` saying what to install.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
import threading
from pathlib import Path

import torch

# The C++ source this module compiles (declared here so every importer's code digest covers it).
CODE_FILES = ("raymarch_fused.cpp",)
SOURCE = Path(__file__).with_name(CODE_FILES[0])
EXTENSION_NAME = "relightable_raymarch_fused"

log = logging.getLogger(__name__)
_lock = threading.Lock()
_module = None
_build_error: str | None = None


class FusedKernelUnavailable(RuntimeError):
    """The fused raymarcher could not be built here (no C++ compiler, or a failed build)."""


@contextlib.contextmanager
def _exclusive_build(build_dir: Path):
    """Hold an OS lock on ``build_dir`` while building, and clear a lock file a killed build left behind.

    torch's own lock is a plain file (``lock``) that a process killed mid-build never removes, and
    every later build then waits on it forever. An ``flock`` dies with its process, so while this
    process holds it no other build of ours is running: a ``lock`` file found then is stale.
    """
    build_dir.mkdir(parents=True, exist_ok=True)
    with open(build_dir / "build.flock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            stale = build_dir / "lock"
            if stale.exists():
                log.warning("removing %s, left by a build of the fused raymarcher that was killed", stale)
                stale.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _build():
    from torch.utils import cpp_extension

    path = os.environ.get("PATH", "")
    if shutil.which("ninja") is None:
        # torch runs `ninja` from PATH; the pip package's binary is not on it when the venv's
        # python runs without the venv activated (as `make` does).
        try:
            import ninja

            os.environ["PATH"] = ninja.BIN_DIR + os.pathsep + path
        except ImportError:
            pass
    build_dir = Path(cpp_extension._get_build_directory(EXTENSION_NAME, False))
    try:
        with _exclusive_build(build_dir):
            return cpp_extension.load(name=EXTENSION_NAME, sources=[str(SOURCE)], extra_cflags=["-O3"],
                                      build_directory=str(build_dir), verbose=False)
    finally:
        os.environ["PATH"] = path


def fused_module(required: bool):
    """The built extension; None if it cannot be built and ``required`` is False.

    The build is tried once per process; its failure is remembered (and warned about once)
    so that an ``"auto"`` caller does not retry it on every render.
    """
    global _module, _build_error
    with _lock:
        if _module is None and _build_error is None:
            try:
                _module = _build()
            except Exception as error:  # a missing compiler shows up as several exception types
                _build_error = f"{type(error).__name__}: {error}".strip()
                log.warning("fused raymarcher unavailable (%s); using the PyTorch raymarcher, the training "
                            "step ~2x slower on the CPU. Install a C++ compiler (e.g. apt-get install g++) to "
                            "build it.", _build_error.splitlines()[0])
    if _module is None and required:
        raise FusedKernelUnavailable(
            f"the fused raymarcher ({SOURCE.name}) could not be built: {_build_error}. Install a C++ "
            "compiler (e.g. `apt-get install g++`), or set the raymarch kernel to 'torch' or 'auto'.")
    return _module


class _FusedRaymarch(torch.autograd.Function):
    @staticmethod
    def forward(ctx, table, lfh, cl, prim, rays_o, rays_d, near, far, t, dt, m, with_added):
        rgb, alpha, sigma, sigma_rgb, added = fused_module(required=True).forward(
            table, lfh, cl, prim, rays_o, rays_d, near, far, t, dt, m, with_added)
        ctx.save_for_backward(table, lfh, cl, prim, rays_o, rays_d, near, far, t, dt, sigma, sigma_rgb)
        ctx.voxels_per_side = m
        ctx.mark_non_differentiable(added)
        return rgb, alpha, added

    @staticmethod
    def backward(ctx, grad_rgb, grad_alpha, _grad_added):
        table, lfh, cl, prim, rays_o, rays_d, near, far, t, dt, sigma, sigma_rgb = ctx.saved_tensors
        grad_table, grad_lfh, grad_cl = fused_module(required=True).backward(
            grad_rgb, grad_alpha, table, lfh, cl, prim, rays_o, rays_d, near, far, t, dt, sigma, sigma_rgb,
            ctx.voxels_per_side)
        return (grad_table, grad_lfh, grad_cl) + (None,) * 9


def fused_raymarch(table: torch.Tensor, local_from_head: torch.Tensor, centre_local: torch.Tensor,
                   prim: torch.Tensor, rays_o: torch.Tensor, rays_d: torch.Tensor, near: torch.Tensor,
                   far: torch.Tensor, t: torch.Tensor, dt: torch.Tensor, m: int, with_added: bool = False
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Colour [R, 3] and opacity [R] of R rays, each against its K candidate boxes, and ``added``.

    ``added`` [R, K] (empty unless ``with_added``; not differentiable): the opacity each
    candidate box added to its ray below saturation (``RenderResult.prim_alpha``'s input).

    Args:
        table: [Q*M^3, 4] voxels (linear RGB, density), z-major M^3 rows per box; differentiable.
        local_from_head: [Q, 3, 3] per box, ``y = x @ local_from_head - centre_local`` takes a
            head-space point into the box's [-1, 1]^3; differentiable.
        centre_local: [Q, 3] per box (see above); differentiable.
        prim: [R, K] int64 box of each candidate (row of ``local_from_head``), -1 for an empty slot.
        rays_o, rays_d: [R, 3] head-space origins and unit directions (not differentiated).
        near, far: [R, K] entry and exit distance of the ray in each candidate box.
        t: [R, S] sample distances; dt: [R] step length.
        m: voxels per side.
    """
    tensors = [x.contiguous() for x in (table, local_from_head, centre_local, prim, rays_o.detach(), rays_d.detach(),
                                        near, far, t, dt)]
    return _FusedRaymarch.apply(*tensors, int(m), bool(with_added))
