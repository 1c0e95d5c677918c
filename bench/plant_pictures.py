"""Pictures of the baked plants, rendered with worldlib.render (not part of
`make test`): what a technical artist sees when opening the assets.

    python -m bench.plant_pictures ARTIFACT_FOLDER_OR_PLANTS_USDA OUT_FOLDER

Reads each species' USD asset as written (every LOD, its textures through the
materials' UsdUVTexture file paths), and writes
    closeup_<species>.png   one plant, LOD0, from the side (3x3 samples, AO);
    lods_<species>.png      LOD0 .. LODn side by side;
    stand.png               a stand of many instances of every plant species
                            but grass (random positions, scales, turns; LOD2,
                            the level a game would show at this distance) on a
                            ground plane, from a perspective camera.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np


def load_species(usdc: Path, size: int = 256):
    """Per LOD a render Scene of the asset (worldlib.render.usd_asset)."""
    from worldlib.render.usd_asset import load_asset

    return [level.scene for level in load_asset(usdc, size)]


def _write(path: Path, linear: np.ndarray) -> None:
    import OpenImageIO as oiio

    from worldlib.render import srgb8

    oiio.ImageBuf(np.ascontiguousarray(srgb8(linear))).write(str(path))


def closeup(scene, size=480):
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from worldlib.render import Camera, Prepared, Settings

    p = scene.positions.astype(np.float64)
    lo, hi = p.min(0), p.max(0)
    c = 0.5 * (lo + hi)
    h = float(max(hi[1] - lo[1], hi[0] - lo[0], hi[2] - lo[2])) * 1.08
    a = math.radians(35.0)
    d = np.array([math.cos(a), -0.12, math.sin(a)])
    d /= np.linalg.norm(d)
    cam = Camera(tuple(c - d * (2 * h)), tuple(d), (0.0, 1.0, 0.0), ortho_height_m=h)
    img = Prepared(cl_env, scene).render(cam, Settings(size, size, samples=3, ao_rays=6, ao_radius_m=0.08 * h, seed=1))
    return img.shaded()


def stand(species: dict, n_per: int = 30, size=(900, 500), level: int = 2):
    """Many instances on a ground plane, seen in perspective."""
    from pipeline.opencl import get_cl

    cl_env = get_cl()  # the engine's choice of device
    from worldlib.render import Camera, Prepared, Scene, Settings

    rng = np.random.default_rng(4)
    parts = []
    extent = 28.0
    for name, scenes in species.items():
        s = scenes[min(level, len(scenes) - 1)]
        n = n_per * (3 if name == "meadow_flower" else 1)
        for _ in range(n):
            x, z = rng.uniform(-extent, extent, 2)
            if z < -extent * 0.2 and abs(x) < 6:  # keep a clearing in front of the camera
                continue
            k = rng.uniform(0.8, 1.3)
            a = rng.uniform(0, 2 * np.pi)
            m = np.eye(4)
            m[:3, :3] = k * np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
            m[:3, 3] = (x, 0.0, z)
            parts.append(s.transformed(m))
    stack = next(iter(species.values()))[0].textures
    g = 80.0
    ground = Scene([[-g, 0, -g], [g, 0, -g], [g, 0, g], [-g, 0, g]], [[0, 1, 0]] * 4, [[0, 0]] * 4, [[0, 1, 2], [0, 2, 3]],
                   (0.16, 0.2, 0.08), -1, np.ones((1,) + stack.shape[1:], np.float32))
    # one texture stack per scene: each species keeps its own three slots
    scene = Scene.concat([ground] + parts)
    cam = Camera((0.0, 9.0, -extent - 18.0), (0.0, -0.28, 1.0), (0.0, 1.0, 0.0), fov_y_deg=42.0)
    img = Prepared(cl_env, scene).render(cam, Settings(size[0], size[1], samples=2, ao_rays=4, ao_radius_m=1.5, seed=2))
    return img.shaded()


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    src, out = Path(argv[0]), Path(argv[1])
    out.mkdir(parents=True, exist_ok=True)
    folder = src.parent if src.suffix == ".usda" else src
    species = {p.stem: load_species(p) for p in sorted(folder.glob("*.usdc"))}
    for name, scenes in species.items():
        _write(out / f"closeup_{name}.png", closeup(scenes[0]))
        row = np.concatenate([closeup(s, 240) for s in scenes], 1)
        _write(out / f"lods_{name}.png", row)
        print(name, [s.n_triangles for s in scenes])
    trees = {k: v for k, v in species.items() if k != "grass"}
    _write(out / "stand.png", stand(trees))
    print("wrote", out)


if __name__ == "__main__":
    main()
