"""The work limit of a stage's run, and the one knob that raises it.

A stage's check estimates the work its run will do (Check.work, in the unit
it names: cell-steps, rays, texels) from its params and the sizes of its
inputs, and states the most a run may do (Check.work_limit), far above its
defaults. The engine (pipeline.bake.check_world) refuses a run estimated past
its limit before any stage runs; WORLDBAKE_MAX_WORK_SCALE multiplies every
stage's limit (erosion's storm steps keep their own WORLDBAKE_MAX_STEPS).
"""
from __future__ import annotations

import math
import os
from typing import Any

from .errors import InputError

WORK_SCALE_ENV = "WORLDBAKE_MAX_WORK_SCALE"


def work_scale() -> tuple[float, str]:
    """The factor every stage's work limit is multiplied by, and how a
    refusal names it: WORLDBAKE_MAX_WORK_SCALE when set, else 1."""
    env = os.environ.get(WORK_SCALE_ENV, "").strip()
    if not env:
        return 1.0, ""
    try:
        scale = float(env)
    except ValueError:
        scale = math.nan
    if not (math.isfinite(scale) and scale > 0):
        raise InputError(f"{WORK_SCALE_ENV} = {env!r}: must be a positive number (the factor on every work limit)")
    return scale, f" x {WORK_SCALE_ENV} = {env}"


def leading_key(params: Any, grows: tuple[str, ...] = (), shrinks: tuple[str, ...] = ()) -> str:
    """Of the params that set a run's work, the one furthest from its default
    in the direction that adds work (value / default for those in `grows`,
    default / value for those in `shrinks`): the key a refusal names. ""
    when none is above its default (the input's size set the work)."""
    best, best_ratio = "", 1.0
    fields = type(params).model_fields
    for key, sign in [(k, 1) for k in grows] + [(k, -1) for k in shrinks]:
        value, default = getattr(params, key), fields[key].default
        if not value or not default:
            continue
        ratio = (value / default) ** sign
        if ratio > best_ratio:
            best, best_ratio = key, ratio
    return best


def work_refusal(stage: str, work: float, limit: float, unit: str, how: str) -> str | None:
    """None when `work` (in `unit`, estimated as `how`) is within `limit`
    times the scale; else the refusal's text (without the key)."""
    if not limit:
        return None
    scale, scale_how = work_scale()
    if work <= limit * scale:
        return None
    return (f"the run would do about {work:.3g} {unit} ({how}), more than the {limit * scale:.3g} a run may do "
            f"(the {stage} stage's limit, {limit:.3g}{scale_how}; {WORK_SCALE_ENV} raises it); lower the values named")
