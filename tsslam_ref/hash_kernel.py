"""The compiled CPU hash-grid lookup (and OneBlob encoding): build on first use, autograd wrappers, fallback.

TS-SLAM §III-A keeps Co-SLAM's multi-resolution hash grid V(x).  On two CPU cores the PyTorch fast
path (``field._TrilinearLookup``) is memory-bound: it writes and re-reads an (8, L, N) index and an
(8, L, N, F) block of gathered rows, so most of a mapping iteration goes to moving memory
(our measurements, docs/map.md).  ``csrc/hash_grid.cpp`` does hash + gather + trilinear interpolation
per point in one pass and recomputes the rows in the backward instead of storing them.  Same
formulas, same corner order; the values agree with the PyTorch paths to rounding
(tests/test_field.py).

Built with ``torch.utils.cpp_extension`` (a C++ compiler with OpenMP, from the system, and ninja,
from environment.txt, are needed; no ``-march=native``, so a cached build runs on any x86-64: the
OneBlob loops carry an AVX2 copy that is chosen at run time, with the same numbers) into
``$TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``) the first time a process asks
for it: about 30 s once, then a cached load.  Each build has its own folder there,
``tsslam_hash_grid_<digest>`` (:func:`build_name`: the sources, the flags, the checkout and the
PyTorch install), so two checkouts or two virtual environments never rebuild over each other's
kernel, and switching between them loads the build each already has.  Where the build fails
the field falls back to the PyTorch fast path with one warning (:func:`available`).  CPU only: a
CUDA field always uses the PyTorch path.

Layer 1 (map): imports torch only.
"""

import contextlib
import hashlib
import os
import re
import shutil
import sys
import sysconfig
import threading
import time
import warnings
from pathlib import Path
from typing import Optional

import torch

SOURCE = Path(__file__).parent / "csrc" / "hash_grid.cpp"
ONEBLOB_SOURCE = Path(__file__).parent / "csrc" / "oneblob.cpp"
"""The OneBlob encoding's kernel, built into the same extension (``field.compiled_oneblob``)."""
CFLAGS = ["-O3", "-ffp-contract=off", "-fopenmp"]  # -fopenmp: at::parallel_for's threads; fp-contract off: no fused multiply-add
LDFLAGS = ["-fopenmp"]
_LOCK = threading.Lock()
_STATE = {"loaded": None, "error": None}  # loaded: None = not tried, True / False after the try
STALE_LOCK_SECONDS = 600.0
"""A build lock older than this (a build takes about 30 s) was most likely left by a process that
was killed while building; ``torch.utils.cpp_extension`` then waits for it forever."""


def available() -> bool:
    """True when the compiled kernel is loaded (building it on the first call of the process).

    Set ``TSSLAM_NO_COMPILED_KERNEL=1`` to skip it (the PyTorch fast path is then used)."""
    if _STATE["loaded"] is not None:
        return _STATE["loaded"]
    with _LOCK:
        if _STATE["loaded"] is None:
            if os.environ.get("TSSLAM_NO_COMPILED_KERNEL", "") not in ("", "0"):
                _STATE["loaded"], _STATE["error"] = False, "TSSLAM_NO_COMPILED_KERNEL is set"
            else:
                _STATE["loaded"] = _build()
    return _STATE["loaded"]


def load_error() -> Optional[str]:
    """Why the kernel is not available (None when it is, or before :func:`available` ran)."""
    return _STATE["error"]


def build_name() -> str:
    """The extension's name and cache folder: ``tsslam_hash_grid_`` and 12 hex digits of a SHA-256
    over the two sources' bytes, the compiler flags, the checkout's ``csrc`` path and PyTorch's
    version and install path.

    ``cpp_extension`` rebuilds a folder whenever its generated build file changes, and that file
    names the sources' paths and PyTorch's include paths: under one fixed name, two checkouts (or
    two virtual environments) sharing ``~/.cache/torch_extensions`` rebuilt the kernel each time
    a process of the other one had built it, and could hold each other's build lock.  The C++
    operators keep their namespace (``torch.ops.tsslam_hash_grid``)."""
    digest = hashlib.sha256()
    for source in (SOURCE, ONEBLOB_SOURCE):
        digest.update(source.read_bytes())
    for part in (CFLAGS, LDFLAGS, str(SOURCE.parent.resolve()), torch.__version__, str(Path(torch.__file__).parent)):
        digest.update(repr(part).encode())
    return "tsslam_hash_grid_" + digest.hexdigest()[:12]


def stale_lock_message(build_directory, now: Optional[float] = None) -> Optional[str]:
    """A message naming the build lock in ``build_directory`` when it is older than
    :data:`STALE_LOCK_SECONDS` (None when there is none or it is recent).  now: time.time() default."""
    lock = Path(build_directory) / "lock"
    try:
        age = (time.time() if now is None else now) - lock.stat().st_mtime
    except OSError:
        return None
    if age < STALE_LOCK_SECONDS:
        return None
    return (f"tsslam_ref: the kernel build lock {lock} is {age / 60:.0f} min old; PyTorch waits until it is "
            "gone. If no other process is building the kernel, a killed build left it: delete the file.")


def ninja_search_path(path: str, scripts: Optional[str] = None) -> str:
    """``path`` (a PATH value) with the Python environment's scripts folder appended when ``ninja``
    is not on ``path`` but is there: ``pip install -r environment.txt`` puts it in ``.venv/bin``,
    which is not on PATH when the venv's python is run without activating the venv, and
    ``torch.utils.cpp_extension`` looks for ``ninja`` on PATH only."""
    scripts = sysconfig.get_path("scripts") if scripts is None else scripts
    if shutil.which("ninja", path=path) is None and shutil.which("ninja", path=scripts) is not None:
        return os.pathsep.join(part for part in (path, scripts) if part)
    return path


def failure_summary(message: str, limit: int = 400) -> str:
    """The lines of a build failure that say why (a compiler's ``error:``, ``not found``, ...), else its
    end: torch's message starts with the whole compiler command line, which says nothing (and lines
    that long are commands, not causes)."""
    lines = [line.strip() for line in message.splitlines() if line.strip()]
    telling = [line for line in lines if _TELLING.search(line) and len(line) < 300]
    summary = " | ".join(telling or lines[-3:])
    return summary if len(summary) <= limit else "..." + summary[-limit:]


_TELLING = re.compile(r"error:|not found|no such file|permission denied|fatal|required|cannot|killed", re.IGNORECASE)


@contextlib.contextmanager
def _standard_streams():
    """stdout and stderr for the build while the process has none (``>&-``): torch flushes them
    while it loads, and an AttributeError on None made every such run take the PyTorch path."""
    missing = [name for name in ("stdout", "stderr") if getattr(sys, name) is None]
    with open(os.devnull, "w") as sink:
        for name in missing:
            setattr(sys, name, sink)
        try:
            yield
        finally:
            for name in missing:
                setattr(sys, name, None)


def _build() -> bool:
    try:
        from torch.utils import cpp_extension

        os.environ["PATH"] = ninja_search_path(os.environ.get("PATH", ""))

        if os.name == "nt":  # MSVC ignores these flags (no optimisation, no threads): the PyTorch path is better
            raise RuntimeError("the kernel is built with GCC/Clang flags (-O3, -fopenmp), which Windows' MSVC ignores")
        compiler = os.environ.get("CXX", "c++")
        if shutil.which(compiler) is None:  # before torch, whose banner would blame the compiler's version
            raise RuntimeError(f"no C++ compiler: {compiler!r} ({'$CXX' if 'CXX' in os.environ else 'the default'}) "
                               f"is not found on PATH; install one (e.g. g++) or set CXX")
        name = build_name()
        try:
            folder = cpp_extension._get_build_directory(name, verbose=False)
        except Exception:  # a private helper of torch: never let it break the build
            folder = None
        message = stale_lock_message(folder) if folder else None  # a stale lock makes load wait without a word
        if message:
            warnings.warn(message, RuntimeWarning, stacklevel=3)

        try:
            with _standard_streams():
                cpp_extension.load(name=name, sources=[str(SOURCE), str(ONEBLOB_SOURCE)], extra_cflags=CFLAGS,
                                   extra_ldflags=LDFLAGS, is_python_module=False, verbose=False)
        except PermissionError:  # a cache this user may read but not write (its lock file): use a finished build
            built = Path(folder or "") / f"{name}.so"
            if not folder or not built.is_file():
                raise
            torch.ops.load_library(str(built))  # the name holds the sources' and flags' hash: never stale
        return True
    except Exception as error:  # no compiler, no ninja, a failed build: fall back, say why once
        _STATE["error"] = f"{type(error).__name__}: {error}"
        warnings.warn(
            "tsslam_ref: the compiled hash-grid kernel could not be built, using the PyTorch path (slower, more "
            "memory; each operation agrees to rounding, so a run's poses differ slightly). Reason: "
            f"{failure_summary(_STATE['error'])} (the whole message: metrics.json, environment.map_kernels)",
            RuntimeWarning,
            stacklevel=3,
        )
        return False


class _HashGridLookup(torch.autograd.Function):
    """features (N, L, F) = V(points_unit) on the compiled kernel; hand-written backward.

    Inputs: points_unit (N, 3), table (T, F), then the level geometry (scales (L,) float64,
    resolutions, sizes, offsets (L,) long) and the number of dense levels.  The table gradient is
    computed only when the map is optimised, the point gradient only when the points carry one
    (tracking, BA); when both are needed (BA) one kernel pass computes them together."""

    @staticmethod
    def forward(points_unit, table, scales, resolutions, sizes, offsets, n_dense):
        return torch.ops.tsslam_hash_grid.forward(points_unit, table, scales, resolutions, sizes, offsets, n_dense)

    @staticmethod
    def setup_context(ctx, inputs, output):
        points_unit, table, scales, resolutions, sizes, offsets, n_dense = inputs
        ctx.save_for_backward(points_unit, table)
        ctx.levels = (scales, resolutions, sizes, offsets, n_dense)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_features):
        points_unit, table = ctx.saved_tensors
        grad_points = grad_table = None
        grad_features = grad_features.contiguous()
        if ctx.needs_input_grad[0] and ctx.needs_input_grad[1]:  # BA: one pass for both
            grad_points, grad_table = torch.ops.tsslam_hash_grid.backward(grad_features, points_unit, table, *ctx.levels)
            return grad_points, grad_table, None, None, None, None, None
        if ctx.needs_input_grad[0]:
            grad_points = torch.ops.tsslam_hash_grid.backward_points(grad_features, points_unit, table, *ctx.levels)
        if ctx.needs_input_grad[1]:
            grad_table = torch.ops.tsslam_hash_grid.backward_table(grad_features, points_unit, table, *ctx.levels)
        return grad_points, grad_table, None, None, None, None, None


def hash_grid_lookup(points_unit: torch.Tensor, table: torch.Tensor, scales: torch.Tensor, resolutions: torch.Tensor,
                     sizes: torch.Tensor, offsets: torch.Tensor, n_dense: int) -> torch.Tensor:
    """(N, 3) box-unit points, (T, F) table, level geometry -> (N, L, F) features (CPU, compiled);
    point-major, so ``.view(N, L * F)`` is the MLP's input without a copy."""
    return _HashGridLookup.apply(points_unit, table, scales, resolutions, sizes, offsets, int(n_dense))


class _OneBlob(torch.autograd.Function):
    """codes (N, 3 n_bins) = OneBlob(points_unit (N, 3)) on the compiled kernel; forward and backward
    round as the PyTorch path and its autograd gradient do (``csrc/oneblob.cpp``): equal bit for bit."""

    @staticmethod
    def forward(points_unit, n_bins, allow_avx2):
        return torch.ops.tsslam_hash_grid.oneblob_forward(points_unit, n_bins, allow_avx2)

    @staticmethod
    def setup_context(ctx, inputs, output):
        points_unit, n_bins, allow_avx2 = inputs
        ctx.save_for_backward(points_unit)
        ctx.n_bins, ctx.allow_avx2 = n_bins, allow_avx2

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_codes):
        (points_unit,) = ctx.saved_tensors
        if not ctx.needs_input_grad[0]:
            return None, None, None
        grad_points = torch.ops.tsslam_hash_grid.oneblob_backward(grad_codes.contiguous(), points_unit, ctx.n_bins,
                                                                  ctx.allow_avx2)
        return grad_points, None, None


def oneblob_encode(points_unit: torch.Tensor, n_bins: int, allow_avx2: bool = True) -> torch.Tensor:
    """(N, 3) box-unit points -> (N, 3 n_bins) OneBlob codes, dim-major (CPU, compiled).

    ``allow_avx2=False`` runs the portable loops even where the AVX2 copy would (the same numbers;
    :func:`oneblob_uses_avx2` says which copy the default runs)."""
    return _OneBlob.apply(points_unit, int(n_bins), bool(allow_avx2))


def oneblob_uses_avx2() -> bool:
    """Whether the compiled OneBlob runs its AVX2 copy (16 bins, an x86-64 processor with AVX2)."""
    return bool(torch.ops.tsslam_hash_grid.oneblob_uses_avx2())
