"""pipeline.opencl: CachedKernel must launch exactly what a plain kernel call
launches, whichever arguments change between launches; the AVX-512 path is
offered only where the device and the CPU allow it."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from pipeline import opencl
from pipeline.opencl import CachedKernel, get_cl, x86_avx512

SOURCE = """
__kernel void axpb(__global const float *x, __global float *y, const float a, const float b, const int n)
{
    int i = get_global_id(0);
    if (i < n) y[i] = a * x[i] + b;
}
"""


def test_cached_kernel_sets_every_changed_argument():
    import pyopencl as cl

    env = get_cl()
    prg = cl.Program(env.ctx, SOURCE).build()
    mf = cl.mem_flags
    n = 37
    xs = [np.arange(n, dtype=np.float32) * s for s in (1.0, -2.0)]
    bx = [cl.Buffer(env.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x) for x in xs]
    by = [cl.Buffer(env.ctx, mf.READ_WRITE, 4 * n) for _ in range(2)]
    k = CachedKernel(prg, "axpb", max_sets=2)
    # buffers alternate (double buffering), scalars change some of the time; three
    # buffer sets with room for two also exercise the eviction
    launches = [(0, 0, 2.0, 1.0), (1, 1, 2.0, 1.0), (0, 0, 3.0, 1.0), (0, 1, 3.0, -5.0),
                (1, 0, 3.0, -5.0), (0, 0, 3.0, -5.0), (1, 1, 0.5, 0.25)]
    for ix, iy, a, b in launches:
        k(env.queue, (64,), None, bx[ix], by[iy], np.float32(a), np.float32(b), np.int32(n))
        out = np.empty(n, np.float32)
        cl.enqueue_copy(env.queue, out, by[iy])
        np.testing.assert_array_equal(out, np.float32(a) * xs[ix] + np.float32(b), err_msg=str((ix, iy, a, b)))
    assert len(k._sets) <= 2


def test_avx512_path_needs_pocl_on_a_cpu_with_avx512_and_can_be_turned_off(monkeypatch):
    import pyopencl as cl

    device = get_cl().device
    pocl_cpu = "portable computing language" in device.platform.name.lower() and bool(
        device.type & cl.device_type.CPU)
    monkeypatch.setattr(opencl, "_host_cpu_flags", lambda: {"avx2", "avx512f", "avx512vl", "avx512dq"})
    assert x86_avx512(device) == pocl_cpu
    monkeypatch.setattr(opencl, "_host_cpu_flags", lambda: {"avx2", "avx512f"})  # no VL, DQ
    assert not x86_avx512(device)
    monkeypatch.setattr(opencl, "_host_cpu_flags", lambda: {"avx2", "avx512f", "avx512vl", "avx512dq"})
    monkeypatch.setenv("WORLDBAKE_CL_AVX512", "0")
    assert not x86_avx512(device)


# --- device choice -------------------------------------------------------------

def fake(index, platform, kind="CPU"):
    return opencl.Candidate(index, platform, f"dev{index}", kind, f"{platform} {index}", device=object())


FAKES = [fake("0:0", "Portable Computing Language"), fake("1:0", "Intel(R) OpenCL"), fake("2:0", "Acme GPU", "GPU"),
         fake("3:0", "Other CL")]


def test_order_is_named_device_then_gpus_then_cpu_runtimes_by_preference():
    order = [c.index for c in opencl.order_candidates([opencl.Candidate(**{**vars(c)}) for c in FAKES])]
    assert order == ["2:0", "0:0", "1:0", "3:0"]
    assert [c.index for c in opencl.order_candidates(list(FAKES), "portable")] == ["0:0"]
    assert [c.index for c in opencl.order_candidates(list(FAKES), "3:0")] == ["3:0"]
    with pytest.raises(opencl.OpenCLError, match="matches no device"):
        opencl.order_candidates(list(FAKES), "nvidia")


def test_a_failing_preferred_runtime_is_skipped_with_one_line(monkeypatch, capsys):
    import sys as _sys

    monkeypatch.setattr(opencl, "list_devices", lambda: [opencl.Candidate(**vars(c)) for c in FAKES])

    def probe(device):
        if device is FAKES[2].device or device is FAKES[0].device:  # the GPU and PoCL fail
            raise opencl.OpenCLError("OpenCL build failed:\nerror: unknown target CPU 'generic'\nmore log")

    monkeypatch.setattr(opencl, "_probe", probe)
    candidates, chosen = opencl.probe_all("", log=_sys.stderr)
    assert chosen.index == "1:0"  # Intel's runtime, the next CPU runtime
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and all("skipped" in line for line in lines)
    assert "unknown target CPU 'generic'" in lines[1]
    assert [c.ok for c in candidates] == [False, False, True, None]  # the last one is never probed


def test_the_next_real_device_is_used_when_the_first_fails(monkeypatch):
    real = [c for c in opencl.order_candidates(opencl.list_devices())]
    if len(real) < 2:
        pytest.skip("one OpenCL device on this machine")
    first = real[0]
    original = opencl._probe

    def probe(device):
        if device.int_ptr == first.device.int_ptr:
            raise opencl.OpenCLError("simulated: cannot compile for this CPU")
        original(device)

    monkeypatch.setattr(opencl, "_probe", probe)
    candidates, chosen = opencl.probe_all("")
    assert chosen is not None and chosen.index != first.index and chosen.index == candidates[1].index


@pytest.fixture
def fresh_device_choice():
    """The process-wide choice is made again inside the test and after it."""
    opencl._default_cl.cache_clear()
    yield
    opencl._default_cl.cache_clear()


def test_no_working_device_exit_3_names_each_device_and_writes_nothing(monkeypatch, tmp_path, capsys,
                                                                         fresh_device_choice):
    import shutil

    from pipeline import cli

    def probe(device):
        raise opencl.OpenCLError("OpenCL build failed:\nerror: unknown target CPU 'generic'")

    monkeypatch.setattr(opencl, "_probe", probe)
    monkeypatch.delenv("WORLDBAKE_CL_DEVICE", raising=False)
    shutil.copytree(Path(__file__).resolve().parents[2] / "configs", tmp_path / "configs")
    for command in ("plan", "bake"):
        rc = cli.main(["--project", str(tmp_path), "--build", str(tmp_path / "build"), command,
                       str(tmp_path / "configs" / "default.toml"), "--set", "heightmap.resolution=64"])
        err = capsys.readouterr().err
        assert rc == 3, err
        assert "no usable OpenCL device" in err and "WORLDBAKE_CL_DEVICE" in err and "worldbake devices" in err
        for c in opencl.list_devices():
            assert c.label in err
    assert not (tmp_path / "build" / "artifacts").exists() or not any((tmp_path / "build" / "artifacts").rglob("*.exr"))
    assert not (tmp_path / "build" / "worlds").exists()


def test_bundled_runtime_is_registered_beside_the_system_vendors(monkeypatch, tmp_path):
    prefix = tmp_path / "env"
    (prefix / "lib").mkdir(parents=True)
    (prefix / "lib" / "libintelocl.so").write_bytes(b"")
    system = tmp_path / "vendors"
    system.mkdir()
    (system / "gpu.icd").write_text("/opt/gpu/libgpu.so\n")
    monkeypatch.setattr(opencl.sys, "prefix", str(prefix))
    monkeypatch.setattr(opencl.sys, "base_prefix", str(prefix))
    monkeypatch.setattr(opencl, "SYSTEM_VENDORS", system)
    monkeypatch.delenv("WORLDBAKE_OCL_VENDORS_SET", raising=False)
    monkeypatch.delenv("OCL_ICD_VENDORS", raising=False)
    folder = opencl.register_bundled_runtimes()
    assert folder == prefix / "etc" / "OpenCL" / "worldbake-vendors"
    assert os.environ["OCL_ICD_VENDORS"] == str(folder)
    files = {p.name: p.read_text() for p in folder.glob("*.icd")}
    assert files == {"worldbake-intel-cpu.icd": f"{(prefix / 'lib' / 'libintelocl.so').resolve()}\n",
                     "system-gpu.icd": "/opt/gpu/libgpu.so\n"}


def test_devices_command_lists_a_working_device():
    import json
    import subprocess
    import sys as _sys

    proc = subprocess.run([_sys.executable, "-m", "pipeline.cli", "devices", "--json"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    working = [d for d in report["devices"] if d["probe"] == "ok"]
    assert working and report["used"] == working[0]["index"]
    assert all(d["error"] for d in report["devices"] if d["probe"] == "failed")


def test_the_device_handle_travels_to_another_process_as_its_device(tmp_path):
    """A pickled handle (a plants job for the worker process) opens the same
    device there, in a context of that process's own."""
    import pickle
    import subprocess
    import sys

    env = get_cl()
    script = "import pickle, sys; env = pickle.load(sys.stdin.buffer); print(env.fingerprint); env.queue.finish()"
    out = subprocess.run([sys.executable, "-c", script], input=pickle.dumps(env), capture_output=True, check=True,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.stdout.decode().strip() == env.fingerprint


def test_code_that_needs_the_device_refuses_to_run_without_one():
    from worldlib.flow import device as flow

    with pytest.raises(opencl.OpenCLError, match="no OpenCL device handed in"):
        flow.d8(None, np.zeros((4, 4), np.float32), np.zeros((4, 4), np.uint8), 1.0)
