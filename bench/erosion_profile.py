"""Measurement of the erosion storm kernels for bench/erosion.py: seconds
per launch of each kernel of a DeviceSim, beside a roofline copy
(bench/roofline.cl), and the bytes each kernel must move. Not part of the
stage (its key does not cover bench/)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.opencl import CachedKernel, load_program
from stages.erosion.physics import THERMAL_C

ROOFLINE = Path(__file__).with_name("roofline.cl")
# the roofline copies: plain float4, 8 float16 per work-item, streaming stores
COPY_KERNELS = ("copy4", "copy16x8", "copy16_stream")
# bytes each kernel must move per cell (compulsory traffic: every array read and written once)
BYTES_PER_CELL = {"flux": 4 * (3 + 4 + 4), "update": 4 * (4 + 4 + 2 + 5), "thermal": 4 * (3 + 2) + 4 * (5 + 1)}
# distinct arrays one storm step (flux + update) touches: Tb, dT, W, S, QE, QS, QW, QN, M, EA
# and the new dT, W, S; the roofline copy's buffers add up to as many padded arrays
WORKING_SET_ARRAYS = 13


def profile(sim, k, reps: int = 10, rounds: int = 5) -> dict[str, float | list[float] | str]:
    """Seconds per launch of each per-step kernel, and of the roofline copy
    kernel, measured back to back in interleaved rounds (a load spike from
    another process hits all of them alike); each entry is the best round,
    and `rounds_<name>` holds every round. Runs on scratch copies of the
    state: the simulation is not advanced.

    The copy of each round is the fastest of three copy kernels (plain
    float4, 8 float16 per work-item, streaming stores; `copy_kernel` names
    the best). It reads one buffer and writes another whose sizes add up to the
    step's working set (WORKING_SET_ARRAYS padded arrays), so the copy runs
    from the same level of the memory hierarchy as flux + update (both from
    the 32 MB L3 at 512^2, both from DRAM at 1024^2 and above). Its source
    is written first, so its reads are real memory (never-written pages all
    map to one zero page and would read from cache). Each
    timed block of `reps` launches follows one untimed launch of the same
    kernel, so every kernel, the copies included, starts its block with its
    own arrays where its timed launches will find them (at 512^2 in the
    L3, which the kernel timed before would otherwise have partly evicted)."""
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    import time

    import pyopencl as cl

    copies = {name: CachedKernel(load_program(cl_env, ROOFLINE), name) for name in COPY_KERNELS}
    q = sim.queue
    R, C, P = sim.R, sim.C, sim.P
    d, w = sim.cd, sim.cw
    ctx = sim.cl.ctx
    mf = cl.mem_flags
    scratch = [cl.Buffer(ctx, mf.READ_WRITE, 4 * sim.npad) for _ in range(3)]
    for b in scratch:
        cl.enqueue_fill_buffer(q, b, np.float32(0), 0, 4 * sim.npad)
    # float4 per buffer: the two together hold the working set (a whole number of 8-float16 blocks)
    n4 = WORKING_SET_ARRAYS * sim.npad // 8 // 32 * 32
    ca = cl.Buffer(ctx, mf.READ_WRITE, 16 * n4)
    cb = cl.Buffer(ctx, mf.READ_WRITE, 16 * n4)
    cl.enqueue_fill_buffer(q, ca, np.float32(1), 0, 16 * n4)
    cl.enqueue_fill_buffer(q, cb, np.float32(0), 0, 16 * n4)
    Qs = [cl.Buffer(ctx, mf.READ_WRITE, 4 * sim.npad) for _ in range(4)]
    for src, dst in zip(sim.Q, Qs):
        cl.enqueue_copy(q, dst, src)
    M2 = cl.Buffer(ctx, mf.READ_WRITE, 4 * sim.npad)
    EA2 = cl.Buffer(ctx, mf.READ_WRITE, 4 * sim.npad)
    cl.enqueue_copy(q, M2, sim.M)
    cl.enqueue_copy(q, EA2, sim.EA)
    launches = {
        "copy4": lambda: copies["copy4"](q, (n4,), (256,) if n4 % 256 == 0 else None, ca, cb, np.int32(n4)),
        "copy16x8": lambda: copies["copy16x8"](q, (n4 // 32,), None, ca, cb),
        "copy16_stream": lambda: copies["copy16_stream"](q, (n4 // 4,), None, ca, cb),
        "flux": lambda: sim._flux(k, Qs, scratch[0], want_wave=False),
        "update": lambda: sim._update(k, Qs, M2, EA2, *scratch),
        "thermal_send": lambda: sim._run("thermal_send", sim.Tb, sim.dT[d], sim.W[w], scratch[0], scratch[1],
                                          R, C, P, sim.t_ax, sim.t_dg, np.float32(THERMAL_C), np.float32(-1)),
        "thermal_apply": lambda: sim._run("thermal_apply", sim.Tb, sim.dT[d], sim.W[w], scratch[0], scratch[1],
                                           scratch[2], R, C, P, sim.t_ax, sim.t_dg, np.float32(-1)),
    }
    times: dict[str, list[float]] = {name: [] for name in launches}
    for _ in range(rounds):  # rounds of `reps` launches each, interleaved
        for name, f in launches.items():
            f()  # one launch outside the clock (first touch; its arrays are where the timed ones find them)
            q.finish()
            t = time.perf_counter()
            for _ in range(reps):
                f()
            q.finish()
            times[name].append((time.perf_counter() - t) / reps)
    # the roofline copy of each round: the fastest of the three (they differ by memory level)
    times["copy"] = [min(times[c][r] for c in COPY_KERNELS) for r in range(rounds)]
    out: dict[str, float | list[float] | str] = {name: min(v) for name, v in times.items()}
    out.update({f"rounds_{name}": v for name, v in times.items()})
    out["copy_bytes"] = 32.0 * n4
    out["copy_kernel"] = min(COPY_KERNELS, key=lambda c: out[c])
    return out
