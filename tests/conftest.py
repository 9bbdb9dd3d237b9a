import os
import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

wp.config.quiet = True

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
MESHES = SHARED / "data" / "meshes"


@pytest.fixture(scope="session")
def meshes_dir():
    if not MESHES.is_dir():
        pytest.fail(f"shared meshes not found at {MESHES}")
    return MESHES


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
