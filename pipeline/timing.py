"""Run time of a stage's steps, for its metrics (a run record, never content)."""
from __future__ import annotations

import time
from contextlib import contextmanager


class StepTimes(dict):
    """Wall seconds per step, in the order the steps ran:
    `with times.lap("fill_s"): ...`."""

    @contextmanager
    def lap(self, name: str):
        t0 = time.perf_counter()
        yield
        self[name] = time.perf_counter() - t0
