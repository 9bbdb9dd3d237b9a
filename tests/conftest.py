import os
import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

wp.config.quiet = True

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT / "examples" / "meshes"  # shipped with the repository (see its README)
#: the solver, contact, adjoint, multigrid and step-pipeline tests that also run in strict device
#: mode (tests/test_strict_device.py) and on a GPU (``make gpu-check``): one pytest node id a line
DEVICE_SUBSET = ROOT / "tests" / "device_subset.txt"


def device_subset():
    """The node ids of DEVICE_SUBSET (comments and blank lines dropped)."""
    lines = (ln.split("#", 1)[0].strip() for ln in DEVICE_SUBSET.read_text().splitlines())
    return [ln for ln in lines if ln]


def pytest_addoption(parser):
    parser.addoption("--device", default=None,
                     help="Warp device the tests' simulators and arrays default to (cpu, cuda:0, ...; default: "
                          "WARPFEM_TEST_DEVICE, else cpu). Tests that name a device keep theirs.")


def pytest_configure(config):
    name = config.getoption("--device") or os.environ.get("WARPFEM_TEST_DEVICE", "").strip() or "cpu"
    if name == "cpu":
        return
    from warpfem.device import DeviceError, get_device

    try:
        dev = get_device(name)
    except DeviceError as e:
        raise pytest.UsageError(f"--device / WARPFEM_TEST_DEVICE: {e}") from None
    wp.set_device(dev)  # arrays made without a device
    # the simulators' default device (keyword-only ``device="cpu"``)
    from warpfem.reduced.simulator import ReducedSimulator
    from warpfem.simulator import Simulator
    from warpfem.solvers.stiffness_warping import StiffnessWarpingSimulator

    for cls in (Simulator, StiffnessWarpingSimulator, ReducedSimulator):
        defaults = cls.__init__.__kwdefaults__
        if defaults and "device" in defaults:
            defaults["device"] = dev.alias


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
