import os
import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

wp.config.quiet = True

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT / "examples" / "meshes"  # shipped with the repository (see its README)


@pytest.fixture(scope="session")
def meshes_dir():
    if not MESHES.is_dir():
        pytest.fail(f"repository meshes not found at {MESHES}")
    return MESHES


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def cpu_rules():
    """Strict device mode off inside the test: for tests of rules that are the CPU's own (``auto``
    may pick the host's direct solver there; strict device mode chooses as on CUDA)."""
    from warpfem.transfer import strict_device_mode

    with strict_device_mode(False):
        yield
