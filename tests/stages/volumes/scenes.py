"""Tiny scenes for the volume tests: a closed box (a trunk) and an
alpha-tested card whose texture's left half is transparent."""
from __future__ import annotations

import numpy as np

from worldlib.render import Scene


def box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Corner positions and outward-wound triangles of an axis-aligned box."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], float)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [3, 6, 2], [3, 7, 6], [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5]])
    return v, f


def trunk_and_card() -> tuple[Scene, np.ndarray]:
    """A 0.2 x 1 x 0.2 m box (Wood) and a 1 x 0.5 m card (Leaves) facing +z
    whose texture is transparent on its left half: (scene, part per triangle)."""
    v, f = box((-0.1, 0.0, -0.1), (0.1, 1.0, 0.1))
    P = v[f.ravel()]
    tex = np.ones((2, 8, 8, 4), np.float32)
    tex[0, :, :4, 3] = 0.0
    tex[0, ..., 0] = 0.2
    tex[1, ..., :3] = (0.3, 0.2, 0.1)
    card = np.array([[-0.5, 0.5, 0.3], [0.5, 0.5, 0.3], [0.5, 1.0, 0.3], [-0.5, 1.0, 0.3]])
    cf = np.array([[0, 1, 2], [0, 2, 3]])
    cuv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    scene = Scene.concat([
        Scene(P, np.tile([0, 0, 1.0], (len(P), 1)), np.zeros((len(P), 2)), np.arange(len(P)).reshape(-1, 3), (1, 1, 1), 1, tex),
        Scene(card[cf.ravel()], np.tile([0, 0, 1.0], (6, 1)), cuv[cf.ravel()], np.arange(6).reshape(-1, 3), (1, 1, 1), 0, tex)])
    return scene, np.array(["Wood"] * 12 + ["Leaves"] * 2, object)
