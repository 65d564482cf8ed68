"""Common fixtures: the location of the real test data (``../shared/data`` beside the checkout) and deterministic torch settings.

Tests that need the real data in ``../shared/data`` (present beside the checkout in CI, absent in a
user's clone) take the ``shared_data`` fixture.  Without the folder they are skipped with a reason
in a user's clone, and they *fail* when ``CI`` is set, so a CI run never counts a skip as a pass.
``TSSLAM_SHARED_DATA`` may point at the folder explicitly.

Tests of the compiled hash-grid kernel take the ``compiled_kernel`` fixture: skipped with a reason
where no C++ compiler or ninja exists (a user's machine), failed under ``CI``; with the tools
present, a kernel that does not build fails the test.
"""

import os
import shutil
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    return Path(os.environ.get("TSSLAM_SHARED_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = shared_data_dir()
    if not (path / "tum_fr3_teddy_120").is_dir():
        message = (f"needs real data that does not ship with the package (full-resolution TUM teddy frames, "
                   f"complete ground-truth trajectories), not found at {path}; set TSSLAM_SHARED_DATA to that folder")
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


@pytest.fixture(scope="session")
def compiled_kernel() -> bool:
    from tsslam_ref import hash_kernel

    if shutil.which("c++") is None or shutil.which("ninja") is None:
        message = "no C++ compiler or ninja on this machine: the compiled hash-grid kernel cannot be built"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    assert hash_kernel.available(), hash_kernel.load_error()
    return True


@pytest.fixture(autouse=True)
def _torch_determinism():
    torch.manual_seed(0)
    torch.set_num_threads(2)
    yield
