"""Shared test set-up: kernel tests run on every OpenCL device that works.

A test (or module, with `pytestmark`) marked `every_device` runs once per
device whose probe passes (pyopencl's own suite does the same with
`pytest_generate_tests_for_pyopencl`): on a machine where PoCL and Intel's CPU
runtime both work, every kernel is compared with its numpy reference on both,
with the same strictness. Unmarked tests run on the device a bake would use.
"""
from __future__ import annotations

import functools
import os

import pytest

# The suite's many small bakes write no report.html (its world picture costs seconds
# a bake); tests/pipeline/test_handoff.py bakes with it and checks it.
os.environ.setdefault("WORLDBAKE_REPORT", "0")


@functools.lru_cache(maxsize=1)
def working_devices() -> list:
    from pipeline import opencl

    candidates, _ = opencl.probe_all(stop_at_first=False)
    return [c for c in candidates if c.ok]


def device_id(candidate) -> str:
    platform = candidate.platform.lower()
    short = "pocl" if "portable computing language" in platform else "intel" if platform.startswith("intel") else platform.split()[0]
    return f"{short}-{candidate.index.replace(':', '.')}"


def pytest_generate_tests(metafunc):
    if metafunc.definition.get_closest_marker("every_device") is None:
        return
    devices = working_devices()
    if not devices:  # the suite's other tests report the missing device; do not hide it here
        pytest.fail("no OpenCL device passes the probe (see `worldbake devices`)")
    metafunc.fixturenames.append("cl_device")
    metafunc.parametrize("cl_device", devices, ids=[device_id(c) for c in devices], scope="module")


@pytest.fixture(autouse=True)
def _run_on_parametrized_device(request):
    """Make get_cl() return the parametrized device for the test's duration."""
    callspec = getattr(request.node, "callspec", None)
    candidate = callspec.params.get("cl_device") if callspec is not None else None
    if candidate is None:
        yield
        return
    from pipeline.opencl import use_device

    with use_device(candidate.device):
        yield


def pytest_collection_modifyitems(items):
    """Group the tests for `pytest -n auto --dist loadgroup` (make test): one group per file, so a
    module's fixtures are built on one worker; the plants tests together, since they share
    session-scoped builds of every preset (tests/stages/plants/conftest.py); the CLI tests apart."""
    for item in items:
        path = item.path.as_posix()
        if path.endswith("/tests/pipeline/test_cli.py"):
            group = item.nodeid  # each test bakes its own project: the longest tests, spread over the workers
        elif "/tests/stages/plants/" in path:
            group = "tests/stages/plants"
        else:
            group = path
        item.add_marker(pytest.mark.xdist_group(group))
