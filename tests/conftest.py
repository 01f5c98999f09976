"""Shared test configuration.

* ``shared_reference`` locates ``../shared/reference`` beside the repository and
  skips the test (with the reason) when it is absent.
* ``--hardware`` enables tests marked ``hardware``; without it they are skipped,
  and real hardware is never used as a silent fallback.
* A test marked ``slow`` without a ``timeout`` marker of its own gets ``SLOW_TIMEOUT_S`` instead of the
  project's 600 s: a slow case (a 1584-DOF shell diagnosis is 220-280 s CPU) exceeds 600 s wall on a
  loaded machine, and a timeout there says nothing about the code.
"""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_REFERENCE = REPO.parent / "shared" / "reference"
#: the timeout of a ``slow`` test without its own ``timeout`` marker (pyproject's default is 600 s)
SLOW_TIMEOUT_S = 3600


def pytest_addoption(parser):
    parser.addoption(
        "--hardware",
        action="store_true",
        default=False,
        help="run tests marked 'hardware' against real lab hardware",
    )


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "slow" in item.keywords and item.get_closest_marker("timeout") is None:
            item.add_marker(pytest.mark.timeout(SLOW_TIMEOUT_S))
    if config.getoption("--hardware"):
        return
    skip = pytest.mark.skip(reason="needs real lab hardware: run with --hardware")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


def reference_path(*parts: str) -> Path:
    """Path under ../shared/reference, or skip the calling test with a clear reason."""
    path = SHARED_REFERENCE.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"reference data not found at {path} (../shared beside the repo is absent)")
    return path


def lab_hardware(loopback: str, wiring: str):
    """The lab's hardware config (``read_hardware_config``) with a ``loopback`` channel, or skip.

    ``--hardware`` tests need ``FRFCAL_HARDWARE_CONFIG`` naming the file
    (docs/hardware.md) and a loopback channel wired as ``wiring`` says.
    """
    import os

    from acquisition import read_hardware_config

    path = os.environ.get("FRFCAL_HARDWARE_CONFIG")
    if not path:
        pytest.skip("set FRFCAL_HARDWARE_CONFIG to the lab's hardware TOML file (docs/hardware.md)")
    hw = read_hardware_config(path)
    if loopback not in hw.channels:
        pytest.skip(f"{path}: no [channels.{loopback}] ({wiring})")
    return hw


@pytest.fixture
def shared_reference() -> Path:
    if not SHARED_REFERENCE.is_dir():
        pytest.skip(f"reference data not found at {SHARED_REFERENCE} (../shared beside the repo is absent)")
    return SHARED_REFERENCE
