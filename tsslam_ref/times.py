"""Timestamps: float64 seconds, refused in any narrower float.

Every time in the package is float64 seconds of the dataset's clock (TUM stamps are about 1.5e9 s).
float32 holds about 7 significant digits: at 1.5e9 s its spacing is 128 s, so a float32 stamp has lost
its frame's time before any cast to float64 could save it.  Functions that take stamps from a user
call :func:`float64_seconds` first.

Layer 0 (support).  Imports nothing of the package.
"""

import numpy as np
import torch


def check_float64_seconds(name: str, value) -> None:
    """TypeError naming ``name`` when ``value`` (times, t0, dt or knots: a scalar, array, list or
    tensor) is floating-point but narrower than float64 (float16/32 arrays or tensors, NumPy float32
    scalars or lists of them).  Integers and Python floats pass."""
    values = value if isinstance(value, torch.Tensor) else np.asarray(value)  # NumPy scalars and lists too
    dtype = values.dtype
    floating = dtype.is_floating_point if isinstance(values, torch.Tensor) else dtype.kind == "f"
    if floating and dtype.itemsize < 8:
        raise TypeError(f"{name} must be float64 seconds (or Python floats), got {dtype}: float32 keeps about 7 "
                        f"digits (its spacing at a 1.5e9 s stamp is 128 s): the digits are gone before any cast")


def float64_seconds(times, name: str) -> np.ndarray:
    """A float64 NumPy copy of ``times`` (array, tensor, list or scalar; the input is not changed),
    after :func:`check_float64_seconds`."""
    check_float64_seconds(name, times)
    if isinstance(times, torch.Tensor):
        return times.detach().cpu().numpy().astype(np.float64, copy=True)  # from any device
    return np.array(times, dtype=np.float64, copy=True)
