"""The reference screen the LOD switch distances are for: how many metres a
pixel covers at a distance, and from where a geometric error is at most
error_px pixels. `params` is the stage's ImpostorsParams (screen_px,
screen_fov_deg, error_px); the bake (stage.py) and the layer (usd_layer.py)
both derive distances here."""
from __future__ import annotations

import math


def pixel_at_1m(params) -> float:
    """Metres one screen pixel covers at 1 m (pinhole: 2 tan(fov / 2) / screen_px)."""
    return 2.0 * math.tan(math.radians(0.5 * params.screen_fov_deg)) / params.screen_px


def switch_distance_m(error_m: float, params) -> float:
    """The distance beyond which `error_m` of geometric error projects to at
    most error_px pixels on the reference screen (pinhole: one pixel covers
    2 d tan(fov / 2) / screen_px metres at distance d)."""
    return error_m / (params.error_px * pixel_at_1m(params))
