"""Physical constants of one erosion run, and the float32 kernel constants of
one time step. Shared by the OpenCL simulator and the numpy reference, so both
run the same numbers."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

G = 9.81  # m/s^2
LIMITER_EPS = 2.0 ** -20  # outflow scaling keeps this fraction of the water in the cell
THERMAL_C = 0.5  # Olsen's c: fraction of the largest talus excess moved per iteration
BOUNDARIES = {"closed": 0, "open": 1, "periodic": 2}


@dataclass(frozen=True)
class Physics:
    """Everything the simulation needs, in SI units, for one grid."""

    dx: float  # m
    boundary: str = "open"
    rain: float = 0.0  # m/s
    evaporation: float = 0.0  # m/s
    friction: float = 0.1  # Darcy-Weisbach f (dimensionless)
    capacity: float = 0.0  # Kc, s/m: C = Kc |q| sin(slope)
    min_slope_sin: float = 0.0
    dissolve_rate: float = 0.0  # 1/s
    deposit_rate: float = 0.0  # 1/s
    wet_depth: float = 0.01  # m of water that counts as fully wet
    moisture_tau: float = 1800.0  # s
    talus_tan: float = math.tan(math.radians(35.0))
    bank_diffusivity: float = 0.0  # m^2/s: scree slumping during the storm (0: off)
    cfl: float = 0.5  # target Courant number of the adaptive step
    cfl_limit: float = 0.9  # largest Courant number accepted (fixed dt is refused beyond it)
    min_wave_speed: float = 1.0  # m/s: floor of the speed used for the adaptive step

    @property
    def boundary_code(self) -> int:
        return BOUNDARIES[self.boundary]

    def dt_limit(self, wave_speed: float, courant: float | None = None) -> float:
        """The CFL step dt = C dx / max(|u| + sqrt(g h), floor)."""
        c = self.cfl if courant is None else courant
        return c * self.dx / max(wave_speed, self.min_wave_speed)

    def thermal_iterations_per_second(self, diffusivity: float) -> float:
        """Olsen's rule moves c * dx * (excess slope) of height per iteration; a
        threshold diffusion of diffusivity D (m^2/s) moves D * excess / dx per
        second, so one iteration stands for c dx^2 / D seconds. Counting
        iterations this way keeps the scree fronts resolution independent."""
        return diffusivity / (THERMAL_C * self.dx * self.dx)


@dataclass(frozen=True)
class StepConstants:
    """The float32 constants of one step of length dt, as the kernels receive them."""

    dt: float
    g_dt_dx: np.float32
    fric_dt: np.float32
    dx_dt: np.float32
    c_dt_dx: np.float32
    kc: np.float32
    sin_min2: np.float32
    ks_f: np.float32
    kd_f: np.float32
    rain_dt: np.float32
    evap_dt: np.float32
    inv_wet: np.float32
    am: np.float32
    four_dx2: np.float32


def rain_quantum(max_depth: float, owed: float) -> float:
    """The rain of one step is a whole multiple of this power of two: the spacing
    of float32 values just above twice the deepest water. Adding it to any depth
    below that is then exact (a constant added to floats of one binade would
    otherwise round the same way in every cell: a systematic loss)."""
    top = max(2.0 * max_depth, owed, 1e-3)
    return 2.0 ** (math.ceil(math.log2(top)) - 23)


def step_constants(ph: Physics, dt: float, rain_depth: float | None = None) -> StepConstants:
    """Kernel constants of a step of length dt; rain_depth (m, default rain * dt)
    is the rain this step adds to every cell."""
    f = np.float32
    return StepConstants(
        dt=dt,
        g_dt_dx=f(G * dt / ph.dx),
        fric_dt=f(ph.friction / 8.0 * dt),
        dx_dt=f((1.0 - LIMITER_EPS) * ph.dx / dt),
        c_dt_dx=f(dt / ph.dx),
        kc=f(ph.capacity),
        sin_min2=f(ph.min_slope_sin ** 2),
        ks_f=f(-math.expm1(-ph.dissolve_rate * dt)),
        kd_f=f(-math.expm1(-ph.deposit_rate * dt)),
        rain_dt=f(ph.rain * dt if rain_depth is None else rain_depth),
        evap_dt=f(ph.evaporation * dt),
        inv_wet=f(1.0 / ph.wet_depth),
        am=f(-math.expm1(-dt / ph.moisture_tau)),
        four_dx2=f(4.0 * ph.dx * ph.dx),
    )


def talus_thresholds(ph: Physics) -> tuple[np.float32, np.float32]:
    """Largest stable height difference to an axial and to a diagonal neighbour."""
    return np.float32(ph.dx * ph.talus_tan), np.float32(math.sqrt(2.0) * ph.dx * ph.talus_tan)
