"""Shared test set-up: kernel tests run on every OpenCL device that works.

A test (or module, with `pytestmark`) marked `every_device` runs once per
device whose probe passes (pyopencl's own suite does the same with
`pytest_generate_tests_for_pyopencl`): on a machine where PoCL and Intel's CPU
runtime both work, every kernel is compared with its numpy reference on both,
with the same strictness. Unmarked tests run on the device a bake would use.
A test takes the device as the `cl_env` fixture and hands it to the code it
tests (the code never looks the device up).
"""
from __future__ import annotations

import atexit
import functools
import os
import shutil
import tempfile

import pytest

# pysheds (the hydrology tests' peer) JIT-compiles with numba's on-disk cache; a
# numba generator it uses can fail to compile in a process that finds it in a cache
# another process wrote ("KeyError: int64 generator(func=<function count ...>)"): one
# CI run from a fresh clone hit it. Each test process gets a cache of its own.
_NUMBA_CACHE_PREFIX = "worldbake-numba-"
if _NUMBA_CACHE_PREFIX in os.environ.get("NUMBA_CACHE_DIR", _NUMBA_CACHE_PREFIX):  # unset, or inherited from pytest's controller
    os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix=_NUMBA_CACHE_PREFIX)
    atexit.register(shutil.rmtree, os.environ["NUMBA_CACHE_DIR"], True)

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


def _parametrized_device(request):
    callspec = getattr(request.node, "callspec", None)
    return callspec.params.get("cl_device") if callspec is not None else None


@pytest.fixture
def cl_env(request):
    """The OpenCL device handle (pipeline.opencl.CL) a test passes to the
    code it tests, as pyopencl's suite takes `ctx_factory`: the parametrized
    device of an `every_device` test, else the one a bake would use."""
    from pipeline import opencl

    candidate = _parametrized_device(request)
    return opencl.get_cl() if candidate is None else opencl.context_for(candidate.device)


@pytest.fixture(autouse=True)
def _run_on_parametrized_device(request):
    """A marked test that does not take `cl_env` (one that bakes: the engine
    chooses the device) runs with the parametrized device as the engine's
    choice (get_cl) for its duration."""
    candidate = _parametrized_device(request)
    if candidate is None or "cl_env" in request.fixturenames:
        yield
        return
    from pipeline.opencl import use_device

    with use_device(candidate.device):
        yield

