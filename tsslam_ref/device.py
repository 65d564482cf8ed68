"""The compute device: choosing it, the CPU allocator setting, and frames as tensors on it.

Layer 4 (system support): imports ``render`` and ``hash_kernel`` (which code encoded the map); used
by ``slam``, ``parallel``, ``run`` and ``checkpoint``.
"""

import ctypes
import dataclasses
import functools
import hashlib
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from . import __version__, hash_kernel
from .render import RayBatch, frame_rays, sample_pixels


def resolve_device(name: str) -> torch.device:
    """'auto' -> cuda when available, else cpu; 'cpu' / 'cuda' / 'cuda:1' as given."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} was asked for but torch.cuda.is_available() is False")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise ValueError(f"device {name!r} was asked for but this machine has {torch.cuda.device_count()} CUDA "
                         f"device(s), numbered from 0")
    return device


def field_settings_for(device: torch.device, field_cfg):
    """``field_cfg`` (``config.FieldConfig``) for a map on ``device``: off the CPU the compiled
    kernels, which are CPU only, are not asked for, so a GPU run neither builds them (about 30 s,
    with a compiler) nor records a ``kernel_error`` that does not apply to it."""
    if device.type == "cpu":
        return field_cfg
    return dataclasses.replace(field_cfg, compiled_kernel=False, compiled_oneblob=False)


def state_on_device(state, device: torch.device):
    """``state`` (a loop state to resume) when its map lives on ``device``'s kind; ValueError naming
    both and the fix otherwise (``checkpoint.load`` puts a state on the CPU unless told; a CUDA run
    from it failed frames later with a tensor on the wrong device)."""
    where = next(state.field.parameters()).device
    if where.type != device.type:
        raise ValueError(f"the state to resume lives on {where}, the run on {device}: load it there, "
                         f"checkpoint.load(path, device={str(device)!r}), or run it on {where.type}")
    return state


def compute_environment(device: torch.device) -> dict:
    """What decides a run's last bits besides the seed: PyTorch, the device, the CPU kernels, the threads.

    On the CPU PyTorch picks its vectorised kernels by the processor's instruction set
    (``cpu_capability``: ``AVX2``, ``AVX512``, ...).  They add in different orders, and a SLAM loop
    grows a last-bit difference into a different trajectory, so a seed gives the same numbers only
    with the same capability and thread count.  Setting the environment variable
    ``ATEN_CPU_CAPABILITY=avx2`` before Python starts makes an AVX-512 machine use the AVX2 kernels.
    """
    environment = {"torch": str(torch.__version__), "device": str(device),
                   "cpu_capability": torch.backends.cpu.get_cpu_capability(), "threads": torch.get_num_threads()}
    if device.type == "cuda":
        environment["gpu"] = torch.cuda.get_device_name(device)
    return environment


def map_kernels(field, device: torch.device) -> dict:
    """Which code ran the map's encodings: ``{"hash_grid": "compiled" | "pytorch", "oneblob": ...}``,
    with ``"kernel_error"`` when the compiled kernel was asked for and did not load.  The two paths
    agree to rounding, not bit for bit, so a seed's numbers depend on it too."""
    probe = torch.zeros(1, 3, dtype=field.grid.table.dtype, device=device)
    paths = {"hash_grid": "compiled" if field.grid.uses_compiled_kernel(probe) else "pytorch",
             "oneblob": "compiled" if field.oneblob.uses_compiled_kernel(probe) else "pytorch"}
    if hash_kernel.load_error() is not None and (field.grid.compiled or field.oneblob.compiled):
        paths["kernel_error"] = hash_kernel.load_error()
    return paths


@functools.lru_cache(maxsize=None)
def source_version(package: Path = Path(__file__).parent) -> str:
    """Which tsslam_ref runs: ``"0.1.0, source 1a2b3c4d5e6f"``, the version and the first 12 hex digits
    of a SHA-256 over the package's code (each ``.py``, ``.cpp`` and ``.h`` file's path inside
    ``package`` and bytes, line ends as LF, so a Windows checkout's CRLF counts as the same code), in
    sorted order; ``"0.1.0, source unknown"`` where no file can be read (a zip import).  Equal
    digests mean the same code wherever it is installed; any edit changes it, which a version number
    that stays put does not show.  Cached: ``run`` asks once at its start, so an edit during a run is
    not recorded as the code that ran."""
    digest, count = hashlib.sha256(), 0
    for path in sorted(package.rglob("*")):
        if path.suffix in (".py", ".cpp", ".h") and path.is_file():
            code = path.read_bytes().replace(b"\r\n", b"\n")
            digest.update(path.relative_to(package).as_posix().encode() + b"\0" + code + b"\0")
            count += 1
    return f"{__version__}, source {digest.hexdigest()[:12] if count else 'unknown'}"


def run_environment(device: torch.device, field) -> dict:
    """:func:`compute_environment` with ``map_kernels`` (:func:`map_kernels` of ``field``) and the
    code (``tsslam_ref``, :func:`source_version`): what metrics.json and a checkpoint record, and what
    ``--resume`` compares."""
    return {"tsslam_ref": source_version(), **compute_environment(device), "map_kernels": map_kernels(field, device)}


def peak_memory(device: torch.device) -> dict:
    """The process's peak memory so far, in MiB, for ``metrics.json``.

    ``peak_rss_mib``: the peak resident set size as the OS reports it (``getrusage``; absent
    where there is no ``resource`` module, as on Windows; on Linux it also covers the process
    image before ``exec``, which matters only for a process forked from a large one); with
    ``--resume`` it covers the resumed process only.  ``peak_gpu_allocated_mib`` on CUDA: the
    peak of PyTorch's allocator on ``device`` (tensors only, not the CUDA context).
    """
    peaks = {}
    try:
        import resource
    except ImportError:
        resource = None
    if resource is not None:
        max_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        peaks["peak_rss_mib"] = max_rss / 2**20 if sys.platform == "darwin" else max_rss / 1024  # bytes / KiB
    if device.type == "cuda":
        peaks["peak_gpu_allocated_mib"] = torch.cuda.max_memory_allocated(device) / 2**20
    return peaks


def tune_cpu_allocator() -> bool:
    """Keep freed buffers in the process instead of returning them to the OS (glibc only).

    The map's iterations allocate and free the same ~50 MB buffers again and again; with glibc's
    defaults each is a fresh mmap that page-faults on first touch (20-40 % of an iteration on our
    2-core machine).  Raising the mmap and trim thresholds (``mallopt``, the same as the
    ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` / ``MALLOC_TOP_PAD_`` environment
    variables) avoids that.  Process-wide, so only the command-line entry points call it.
    Returns False (and changes nothing) where glibc is not available.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3  # glibc malloc.h
    ok = mallopt(m_mmap_threshold, 1 << 30) and mallopt(m_trim_threshold, 1 << 30)
    return bool(ok and mallopt(m_top_pad, 1 << 28))


@dataclass
class FrameTensors:
    """One RGB-D frame on the compute device."""

    index: int
    timestamp: float
    """Seconds (float64)."""
    rgb: torch.Tensor
    """(H, W, 3) colour in [0, 1]."""
    depth: torch.Tensor
    """(H, W) depth in m (0 = missing)."""
    intrinsics: object

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])

    def rays(self, rows: torch.Tensor, cols: torch.Tensor, frame_id: int = 0) -> RayBatch:
        """(R,) camera-frame rays of the pixels (rows[r], cols[r]) with their colour and depth."""
        return frame_rays(self.rgb, self.depth, self.intrinsics, rows, cols, frame_id=frame_id)

    def all_rays(self) -> RayBatch:
        """Every pixel as a camera-frame ray, (H*W,)."""
        rows, cols = torch.meshgrid(
            torch.arange(self.height, device=self.depth.device),
            torch.arange(self.width, device=self.depth.device),
            indexing="ij",
        )
        return self.rays(rows.reshape(-1), cols.reshape(-1))

    def sampled_rays(self, n: int, generator: torch.Generator, ignore_edge: int = 0) -> RayBatch:
        """(n,) rays of pixels drawn uniformly ``ignore_edge`` pixels away from the border."""
        rows, cols = sample_pixels(self.height, self.width, n, ignore_edge=ignore_edge, generator=generator)
        return self.rays(rows.to(self.depth.device), cols.to(self.depth.device))


def frame_to_device(frame, device: torch.device, dtype: torch.dtype) -> FrameTensors:
    """:class:`tsslam_ref.data.Frame` (numpy) -> :class:`FrameTensors` on ``device``."""
    return FrameTensors(
        index=frame.index,
        timestamp=float(frame.timestamp),
        rgb=torch.as_tensor(np.ascontiguousarray(frame.rgb), dtype=dtype, device=device),
        depth=torch.as_tensor(np.ascontiguousarray(frame.depth), dtype=dtype, device=device),
        intrinsics=frame.intrinsics,
    )
