"""Terrain statistics: does a height field read as eroded land?

Numbers a geomorphologist would check on a DEM, computed from the final
height and its D8 flow tree:

- grid_anisotropy: share of the 2-to-16-cell band's spectral power lying on
  the grid's axes and diagonals, over the share of that band's wavenumbers
  lying there (1 isotropic; D8 routing printed on the surface gives 2 and more);
- grid_anisotropy_local: the same wedges against their flanks a few degrees
  away, so a landform trend near a grid direction is told from grid marks;
- depression_area_fraction: share of the area in closed depressions before
  filling (filled height above the height);
- strahler_order_max: Horton-Strahler order of the channel network
  (cells draining at least the channel threshold);
- hack_exponent: L = c A^h over channel cells, L the longest upstream path
  (Hack 1957; Rigon et al. 1996: 0.5 .. 0.6 in real basins);
- concavity_theta: S = k A^-theta on channel cells (Whipple 2004: 0.35 .. 0.65),
  fitted on the median slope per logarithmic bin of drainage area, the
  slope taken over a reach of SLOPE_REACH_M downstream as on smoothed
  river profiles (Wobus et al. 2006), so that pools and steps a few cells
  long do not decide it; concavity_theta_cell is the same fit with the
  slope to the next cell;
- drainage_density_per_km: channel length per area (km / km^2);
- hypsometric_integral: (mean - min) / (max - min) of the height;
- slope_*: slope percentiles and area shares of the height averaged over
  SLOPE_BLOCK_M blocks (the resolution of public DEMs), so that they compare
  with measurements on real ranges (slope_statistics).

The statistics of the height alone (anisotropy, hypsometry, relief, slopes,
depressions) come from field_statistics, which reads the world by windows
(a tiled world is never held whole) and gives the same numbers whatever
assembles the windows; a world of at most ANISOTROPY_WINDOW cells a side is
read as one window and measured exactly as on the whole array.

D8 codes are the hydrology convention: 0..7 = N, NE, E, SE, S, SW, W, NW,
negative = outlet (no receiver). Everything here is plain numpy, float64.
"""
from __future__ import annotations

import math

import numpy as np

from worldlib.flow import longest_path
from worldlib.flow.reference import subset_receivers, topological_levels

DR = np.array([-1, -1, 0, 1, 1, 1, 0, -1])
DC = np.array([0, 1, 1, 1, 0, -1, -1, -1])
GRID_DIRECTIONS_DEG = (0.0, 45.0, 90.0, 135.0)
ANISOTROPY_HALF_WIDTH_DEG = 1.5
SLOPE_REACH_M = 200.0
SLOPE_BLOCK_M = 30.0
STEEP_DEG, GENTLE_DEG = 40.0, 10.0  # the slope shares reported: steeper than 40 degrees, flatter than 10


def block_weights(n: int, dx: float, block_m: float) -> np.ndarray:
    """(blocks, n) weights averaging n cells of dx into whole blocks of
    block_m (each cell by the length it overlaps the block, so a block need
    not hold a whole number of cells); the remainder at the far edge is dropped."""
    blocks = int(math.floor(n * dx / block_m + 1e-9))
    lo = np.arange(blocks)[:, None] * block_m
    cell = np.arange(n)[None, :] * dx
    overlap = np.clip(np.minimum(lo + block_m, cell + dx) - np.maximum(lo, cell), 0.0, None)
    return overlap / block_m


def block_average(h: np.ndarray, dx: float, block_m: float) -> np.ndarray:
    """The height averaged over block_m x block_m blocks (area-weighted, float64)."""
    h = np.asarray(h, np.float64)
    wr = block_weights(h.shape[0], dx, block_m)
    wc = block_weights(h.shape[1], dx, block_m)
    return wr @ h @ wc.T


def slope_degrees(h: np.ndarray, dx: float) -> np.ndarray:
    """Slope in degrees of the interior cells by Horn's (1981) 3x3 gradient,
    the GIS standard; shape (rows - 2, cols - 2)."""
    z = np.asarray(h, np.float64)
    a, b, c = z[:-2, :-2], z[:-2, 1:-1], z[:-2, 2:]
    d, f = z[1:-1, :-2], z[1:-1, 2:]
    g, hh, i = z[2:, :-2], z[2:, 1:-1], z[2:, 2:]
    gx = ((c + 2.0 * f + i) - (a + 2.0 * d + g)) / (8.0 * dx)
    gy = ((g + 2.0 * hh + i) - (a + 2.0 * b + c)) / (8.0 * dx)
    return np.degrees(np.arctan(np.hypot(gx, gy)))


def slope_statistics(h: np.ndarray, dx: float, block_m: float = SLOPE_BLOCK_M) -> dict:
    """Slope of the height averaged to block_m blocks (block_average, Horn's
    gradient on the blocks, the outer ring of blocks left out): the 10th,
    50th and 90th percentiles in degrees, the shares of the area steeper than
    STEEP_DEG and flatter than GENTLE_DEG, and the mean. Finer cells than the
    block are averaged; coarser grids are measured as they are (block =
    cell size)."""
    h = np.asarray(h, np.float64)
    block = max(float(block_m), float(dx))
    hb = block_average(h, dx, block) if block > dx else h
    return _slope_summary(hb, block, h.shape, dx)


def _slope_summary(hb: np.ndarray, block: float, shape: tuple[int, int], dx: float) -> dict:
    """slope_statistics of the block means hb (block m apart) of a world of shape cells of dx."""
    if min(hb.shape) < 3:
        raise ValueError(f"slope_statistics: {shape} cells of {dx:g} m make fewer than 3 x 3 blocks of {block:g} m")
    s = np.empty((hb.shape[0] - 2, hb.shape[1] - 2))
    step = max(1, STRIP_CELLS // hb.shape[1])  # by strips, so a large block grid has no grid-sized temporaries
    for r in range(0, s.shape[0], step):
        s[r:r + step] = slope_degrees(hb[r:r + step + 2], block)
    p10, p50, p90 = np.percentile(s, [10.0, 50.0, 90.0])
    return {"slope_block_m": block, "slope_p10_deg": float(p10), "slope_median_deg": float(p50),
            "slope_p90_deg": float(p90), "slope_mean_deg": float(s.mean()),
            "slope_share_over_40_deg": float((s > STEEP_DEG).mean()),
            "slope_share_under_10_deg": float((s < GENTLE_DEG).mean())}


def _power(h: np.ndarray) -> np.ndarray:
    """The Hann-windowed power spectrum of the height minus its mean."""
    rows, cols = h.shape
    w = np.outer(np.hanning(rows), np.hanning(cols))
    return np.abs(np.fft.fft2((h - h.mean()) * w)) ** 2


def _band_geometry(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """(band, angle) of a rows x cols spectrum: the wavenumbers of radius
    n/16 .. n/2 (wavelengths 2 to 16 cells; a non-square grid in cycles per
    cell scaled by the shorter side) and each one's direction in degrees, 0 .. 180."""
    n = min(rows, cols)
    ky = np.fft.fftfreq(rows)[:, None] * n
    kx = np.fft.fftfreq(cols)[None, :] * n
    radius = np.hypot(kx, ky)
    band = (radius >= n / 16) & (radius <= n / 2)
    return band, np.degrees(np.arctan2(ky, kx)) % 180.0


def _band_spectrum(height: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(power, band, angle): _power and _band_geometry of the height."""
    h = np.asarray(height, np.float64)
    return (_power(h), *_band_geometry(*h.shape))


def _off_grid_deg(angle: np.ndarray) -> np.ndarray:
    """Angular distance to the nearest of 0, 45, 90 and 135 degrees."""
    return np.min([np.abs((angle - a + 90.0) % 180.0 - 90.0) for a in GRID_DIRECTIONS_DEG], axis=0)


def grid_anisotropy(height: np.ndarray) -> float:
    """The issue's spectral measure of grid marks, exactly: height minus its
    mean, times a separable Hann window, 2-D power spectrum; keep wavenumbers
    of radius n/16 .. n/2 (wavelengths 2 to 16 cells); the share of that
    band's power within +-1.5 degrees of 0, 45, 90 and 135 degrees, divided by
    the share of the band's wavenumbers lying there."""
    return _anisotropy(*_band_spectrum(height))


def _anisotropy(power: np.ndarray, band: np.ndarray, angle: np.ndarray) -> float:
    on_grid = _off_grid_deg(angle) <= ANISOTROPY_HALF_WIDTH_DEG
    p_band = power[band].sum()
    if p_band <= 0:
        return 1.0
    share_power = power[band & on_grid].sum() / p_band
    share_count = (band & on_grid).sum() / band.sum()
    return float(share_power / share_count)


def grid_anisotropy_local(height: np.ndarray, flank_deg: float = 6.0) -> float:
    """Grid marks against the landforms' own orientation: the same band and
    +-1.5 degree wedges as grid_anisotropy, but each wedge's power density
    over that of its flanks (1.5 to flank_deg degrees either side) instead of
    the whole band's. Grid marks are narrow spikes on the grid directions
    (D8 stripes give 2 and more); a landform trend that happens to lie near
    a grid direction (parallel valleys down a range's flank) is a broad peak
    and gives about 1 here while raising grid_anisotropy."""
    return _anisotropy_local(*_band_spectrum(height), flank_deg)


def _anisotropy_local(power: np.ndarray, band: np.ndarray, angle: np.ndarray, flank_deg: float = 6.0) -> float:
    d = _off_grid_deg(angle)
    on = band & (d <= ANISOTROPY_HALF_WIDTH_DEG)
    flank = band & (d > ANISOTROPY_HALF_WIDTH_DEG) & (d <= flank_deg)
    if not on.any() or not flank.any() or power[flank].sum() <= 0:
        return 1.0
    return float((power[on].sum() / on.sum()) / (power[flank].sum() / flank.sum()))


ANISOTROPY_WINDOW = 1024  # worlds up to this many cells a side are measured whole; larger ones by windows of this side
EXACT_SHIFT = 1126  # every float64 is a whole number of 2^-1126 (53-bit mantissas down to the subnormal 2^-1074)
STRIP_CELLS = 1 << 21  # about this many cells read at once for the block means


def exact_sum(values: np.ndarray) -> int:
    """The sum of finite float64 values (any sign) exactly, as an integer
    count of 2^-EXACT_SHIFT: integers add in any order, so a world's sum is
    that of its windows' whatever the split. Per exponent the 53-bit
    mantissas are summed as two halves in float64, 2^24 values at a time
    (every partial sum a whole number below 2^51, so exact)."""
    v = np.asarray(values, np.float64).ravel()
    total = 0
    for at in range(0, v.size, 1 << 24):
        m, e = np.frexp(v[at:at + (1 << 24)])
        mant = m * 2.0 ** 53  # whole numbers, |mant| < 2^53
        hi = np.floor(mant / 2.0 ** 26)
        lo = mant - hi * 2.0 ** 26  # 0 <= lo < 2^26
        e0 = int(e.min())
        his, los = np.bincount(e - e0, weights=hi), np.bincount(e - e0, weights=lo)
        for k in np.flatnonzero((his != 0) | (los != 0)).tolist():
            total += ((int(his[k]) << 26) + int(los[k])) << (e0 + k - 53 + EXACT_SHIFT)
    return total


def exact_mean(total: int, n: int) -> float:
    """exact_sum's total over n values, correctly rounded (Python's int division is)."""
    return total / (n << EXACT_SHIFT) if n else 0.0


def _read(read, r0: int, c0: int, nr: int, nc: int) -> np.ndarray:
    w = np.array(read(r0, c0, nr, nc), np.float64, order="C")  # a fresh array: its bits, not its layout, decide
    if w.shape != (nr, nc):
        raise ValueError(f"field_statistics: read({r0}, {c0}, {nr}, {nc}) returned {w.shape}")
    return w


def window_starts(n: int, w: int) -> list[int]:
    """Starts of the windows of w cells along a side of n: every w cells,
    the last one flush with the far edge (so every cell is in one)."""
    if n <= w:
        return [0]
    starts = list(range(0, n - w + 1, w))
    return starts + [n - w] if starts[-1] + w < n else starts


def block_taps(n: int, dx: float, block_m: float) -> tuple[np.ndarray, np.ndarray]:
    """block_weights without its zeros: (first, weights), block b averaging
    cells first[b] + k by weights[b, k] (zero past its last cell)."""
    blocks = int(math.floor(n * dx / block_m + 1e-9))
    b = np.arange(blocks)

    def weights(first: np.ndarray, taps: int) -> np.ndarray:
        lo = b[:, None] * block_m  # the same operations as block_weights, so the same weights
        cell = (first[:, None] + np.arange(taps)[None, :]) * dx
        return np.clip(np.minimum(lo + block_m, cell + dx) - np.maximum(lo, cell), 0.0, None) / block_m

    near = np.maximum(np.floor(b * block_m / dx).astype(np.int64) - 1, 0)
    w = weights(near, int(math.ceil(block_m / dx)) + 3)
    first = near + np.argmax(w > 0, axis=1)
    taps = int((w > 0).sum(axis=1).max()) if blocks else 1
    w = weights(first, taps)
    w[first[:, None] + np.arange(taps)[None, :] >= n] = 0.0
    return first, w


def _block_rows(strip: np.ndarray, row0: int, rows: tuple, cols: tuple) -> np.ndarray:
    """Block means of the block rows (first, weights) = rows from a strip of
    cells starting at row row0 (across the world's width), each block a sum
    of its cells in a fixed order (rows, then columns), so a block row is
    the same number whatever strip it came in."""
    (rf, rw), (cf, cw) = rows, cols
    acc = np.zeros((rf.size, strip.shape[1]))
    for k in range(rw.shape[1]):
        acc += rw[:, k:k + 1] * strip[np.minimum(rf + k - row0, strip.shape[0] - 1)]
    out = np.zeros((rf.size, cf.size))
    for k in range(cw.shape[1]):
        out += cw[:, k] * acc[:, np.minimum(cf + k, strip.shape[1] - 1)]
    return out


def block_grid(read, shape: tuple[int, int], dx: float, block_m: float, fill: float) -> np.ndarray:
    """The height (no-data = fill) averaged over block_m blocks as
    block_average, read strip by strip: a strip is whole block rows across
    the world's width; the blocks do not depend on the strips."""
    rows, cols = shape
    rtap, ctap = block_taps(rows, dx, block_m), block_taps(cols, dx, block_m)
    per = max(1, int(STRIP_CELLS // max(cols, 1) * dx / block_m))
    out = []
    for b0 in range(0, rtap[0].size, per):
        rf, rw = rtap[0][b0:b0 + per], rtap[1][b0:b0 + per]
        r0, r1 = int(rf[0]), min(int(rf[-1]) + rw.shape[1], rows)
        strip = _read(read, r0, 0, r1 - r0, cols)
        strip = np.where(np.isfinite(strip), strip, fill)
        out.append(_block_rows(strip, r0, (rf, rw), ctap))
    return np.concatenate(out) if out else np.zeros((0, ctap[0].size))


def _height_sums(read, shape: tuple[int, int], window: int, read_filled=None) -> tuple:
    """(cells with data, exact_sum, lowest, highest, cells in depressions)
    over non-overlapping windows of the world."""
    rows, cols = shape
    n, total, lo, hi, dep = 0, 0, math.inf, -math.inf, 0
    for r0 in range(0, rows, window):
        for c0 in range(0, cols, window):
            nr, nc = min(window, rows - r0), min(window, cols - c0)
            h = _read(read, r0, c0, nr, nc)
            data = np.isfinite(h)
            v = h[data]
            if v.size:
                n, total = n + v.size, total + exact_sum(v)
                lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
            if read_filled is not None:
                dep += int(((_read(read_filled, r0, c0, nr, nc) > h) & data).sum())
    return n, total, lo, hi, dep


def welch_spectrum(read, shape: tuple[int, int], window: int, fill: float) -> tuple:
    """(power, band, angle) as _band_spectrum's, the power summed over the
    windows of window cells a side at window_starts (each less its own mean,
    Hann-windowed; no-data = fill) in a fixed order: Welch's estimate."""
    rows, cols = shape
    wr, wc = min(rows, window), min(cols, window)
    power = np.zeros((wr, wc))
    for r0 in window_starts(rows, wr):
        for c0 in window_starts(cols, wc):
            h = _read(read, r0, c0, wr, wc)
            power += _power(np.where(np.isfinite(h), h, fill))
    return (power, *_band_geometry(wr, wc))


def _field_statistics_whole(h: np.ndarray, filled: np.ndarray | None, dx: float) -> dict:
    """field_statistics of a world read whole (at most ANISOTROPY_WINDOW a side)."""
    rows, cols = h.shape
    data = np.isfinite(h)
    hv = h[data]
    hf = np.where(data, h, hv.mean() if hv.size else 0.0)
    spectrum = _band_spectrum(hf)
    span = float(hv.max() - hv.min()) if hv.size else 0.0
    out = {"grid_anisotropy": _anisotropy(*spectrum), "grid_anisotropy_local": _anisotropy_local(*spectrum)}
    if filled is not None:
        out["depression_area_fraction"] = float(((filled > h) & data).sum() / max(int(data.sum()), 1))
    return {**out, "hypsometric_integral": float((hv.mean() - hv.min()) / span) if span > 0 else 0.0,
            **(slope_statistics(hf, dx) if hv.size and min(rows, cols) * dx >= 3 * SLOPE_BLOCK_M else {}),
            "relief_m": span}


def field_statistics(read, shape: tuple[int, int], dx: float, read_filled=None,
                     window: int = ANISOTROPY_WINDOW) -> dict:
    """The statistics of the height alone (grid_anisotropy,
    grid_anisotropy_local, hypsometric_integral, slope_*, relief_m and,
    given read_filled, depression_area_fraction) from a world read by
    windows: read(row0, col0, rows, cols) -> float64 heights (NaN = no-data),
    read_filled the same of the filled height. The result depends on the
    world, never on how read assembles a window.

    A world of at most `window` cells a side is read whole and measured as
    ever. A larger one: the spectrum is Welch's (welch_spectrum) - the
    statistics are shares of the band's power, and the power summed over the
    windows weighs each window by its power, as one spectrum of the whole
    would; no-data is the mean of the data (exact_sum, correctly rounded);
    the block means are block_grid's; mean, lowest and highest from exact
    per-window sums and extremes."""
    rows, cols = shape
    dx = float(dx)
    if rows <= window and cols <= window:
        filled = _read(read_filled, 0, 0, rows, cols) if read_filled is not None else None
        return _field_statistics_whole(_read(read, 0, 0, rows, cols), filled, dx)
    n, total, lo, hi, dep = _height_sums(read, shape, window, read_filled)
    mean = exact_mean(total, n)
    span = hi - lo if n else 0.0
    spectrum = welch_spectrum(read, shape, window, mean)
    out = {"grid_anisotropy": _anisotropy(*spectrum), "grid_anisotropy_local": _anisotropy_local(*spectrum)}
    if read_filled is not None:
        out["depression_area_fraction"] = float(dep / max(n, 1))
    slopes = {}
    if n and min(rows, cols) * dx >= 3 * SLOPE_BLOCK_M:
        block = max(float(SLOPE_BLOCK_M), dx)
        slopes = _slope_summary(block_grid(read, shape, dx, block, mean), block, shape, dx)
    return {**out, "hypsometric_integral": float((mean - lo) / span) if span > 0 else 0.0, **slopes,
            "relief_m": span}


def receivers(code: np.ndarray) -> np.ndarray:
    """Flat index of each cell's D8 receiver, -1 for outlets and no-data."""
    rows, cols = code.shape
    c = np.asarray(code).ravel().astype(np.int64)
    k = np.clip(c, 0, 7)
    idx = np.arange(c.size)
    r = idx // cols + DR[k]
    q = idx % cols + DC[k]
    ok = (c >= 0) & (r >= 0) & (r < rows) & (q >= 0) & (q < cols)
    return np.where(ok, r * cols + q, -1)


def strahler_order(rcv: np.ndarray, channel: np.ndarray, levels: list[np.ndarray]) -> np.ndarray:
    """Horton-Strahler order of the channel cells (0 elsewhere): 1 at heads;
    where two or more donors of the highest order meet, that order + 1."""
    n = rcv.size
    order = np.zeros(n, np.int32)
    top = np.zeros(n, np.int32)  # highest order among donors
    count = np.zeros(n, np.int32)  # how many donors have it
    for lev in levels:
        o = np.where(top[lev] == 0, 1, np.where(count[lev] >= 2, top[lev] + 1, top[lev]))
        order[lev] = o
        t = rcv[lev]
        ok = (t >= 0) & channel[np.maximum(t, 0)]
        t, o = t[ok], o[ok]
        if not t.size:
            continue
        # per receiver: the highest donor order and how many donors reach it
        best = np.zeros(n, np.int32)
        np.maximum.at(best, t, o)
        hit = np.zeros(n, np.int32)
        np.add.at(hit, t, (o == best[t]).astype(np.int32))
        u = np.unique(t)
        higher = best[u] > top[u]
        same = best[u] == top[u]
        count[u] = np.where(higher, hit[u], np.where(same, count[u] + hit[u], count[u]))
        top[u] = np.maximum(top[u], best[u])
    return order


def _fit_slope(x: np.ndarray, y: np.ndarray) -> float:
    if x.size < 3 or np.ptp(x) == 0:
        return float("nan")
    return float(np.polyfit(x, y, 1)[0])


def _concavity(area: np.ndarray, slope: np.ndarray, cells: np.ndarray) -> tuple[float, int]:
    """theta of S = k A^-theta: least squares through the median log S of
    each tenth of a decade of A (bins of at least 5 cells with S > 0)."""
    sa = cells & (slope > 0)
    if sa.sum() < 10:
        return float("nan"), 0
    la, ls = np.log10(area[sa]), np.log10(slope[sa])
    edges = np.arange(math.floor(la.min() * 10) / 10, la.max() + 0.1, 0.1)
    which = np.digitize(la, edges)
    xs, ys = [], []
    for b in np.unique(which):
        m = which == b
        if m.sum() >= 5:
            xs.append(np.median(la[m]))
            ys.append(np.median(ls[m]))
    return -_fit_slope(np.array(xs), np.array(ys)), len(xs)


def terrain_statistics(height: np.ndarray, filled: np.ndarray, code: np.ndarray, area_m2: np.ndarray,
                       cell_size_m: float, channel_area_m2: float, data: np.ndarray | None = None) -> dict:
    """The statistics of the module docstring (float64; JSON-ready dict).

    Parameters
    ----------
    height : (rows, cols) final terrain height, m (NaN = no-data)
    filled : the same, depressions filled (Priority-Flood without epsilon), m
    code : D8 flow codes of the routing (hydrology convention)
    area_m2 : D8 drainage area of each cell, m^2
    cell_size_m : cell edge, m
    channel_area_m2 : drainage area at which a channel starts, m^2
    data : cells with data (default: finite height)
    """
    h = np.asarray(height, np.float64)
    rows, cols = h.shape
    dx = float(cell_size_m)
    data = np.isfinite(h) if data is None else np.asarray(data, bool)
    fl = np.asarray(filled, np.float64)

    def read(r0: int, c0: int, nr: int, nc: int) -> np.ndarray:
        win = np.s_[r0:r0 + nr, c0:c0 + nc]
        return np.where(data[win], h[win], np.nan)

    # the height's statistics by the windows a tiled run reads, so both give the same numbers
    field = field_statistics(read, (rows, cols), dx, lambda r0, c0, nr, nc: fl[r0:r0 + nr, c0:c0 + nc])
    A = np.asarray(area_m2, np.float64).ravel()
    cells = np.flatnonzero(data.ravel() & (A >= channel_area_m2))
    code_c = np.asarray(code).ravel()[cells]
    L = longest_path.length_m(*longest_path.longest_whole(np.asarray(code)), dx)  # step counts: the same in tiles
    net = channel_statistics(subset_receivers(cells, receivers(code)[cells]), code_c, A[cells], h.ravel()[cells],
                             L[cells], int(data.sum()), dx)
    return combined_statistics(field, net, channel_area_m2, rows * cols, dx)


def combined_statistics(field: dict, net: dict, channel_area_m2: float, cells: int, dx: float) -> dict:
    """terrain_statistics' dict from field_statistics' and channel_statistics' (its keys in its order)."""
    return {
        **{k_: field[k_] for k_ in ("grid_anisotropy", "grid_anisotropy_local", "depression_area_fraction")},
        **{k_: net[k_] for k_ in ("strahler_order_max", "hack_exponent", "concavity_theta", "concavity_bins",
                                  "concavity_theta_cell", "concavity_slope_reach_m", "drainage_density_per_km")},
        **{k_: v for k_, v in field.items() if k_ == "hypsometric_integral" or k_.startswith("slope_")},
        "relief_m": field["relief_m"],
        "channel_area_m2": float(channel_area_m2),
        "channel_cells": net["channel_cells"],
        "cells": int(cells),
        "cell_size_m": dx,
    }


def channel_statistics(rcv: np.ndarray, code: np.ndarray, area_m2: np.ndarray, height: np.ndarray, L: np.ndarray,
                       n_data: int, cell_size_m: float) -> dict:
    """The channel network's statistics (Strahler, Hack, concavity,
    drainage density) from its cells alone, ascending flat order however
    gathered: their receivers as indices into them (-1: none), D8 codes,
    drainage areas (m^2), heights (m) and longest upstream paths (m);
    n_data: the world's cells with a height."""
    dx = float(cell_size_m)
    A = np.asarray(area_m2, np.float64)
    h = np.asarray(height, np.float64)
    k = np.clip(np.asarray(code), 0, 7)
    step = np.where(k % 2 == 1, dx * math.sqrt(2.0), dx)
    has_r = rcv >= 0
    order = strahler_order(rcv, np.ones(rcv.size, bool), topological_levels(rcv))
    sel = L > 0
    hack = _fit_slope(np.log(A[sel]), np.log(L[sel])) if sel.sum() >= 10 else float("nan")
    slope = np.zeros(rcv.size)
    slope[has_r] = (h[has_r] - h[rcv[has_r]]) / step[has_r]
    theta_cell, _ = _concavity(A, slope, has_r)
    # the drop over a reach of SLOPE_REACH_M downstream (or to the outlet)
    cells = np.flatnonzero(has_r)
    pos, run = cells.copy(), np.zeros(cells.size)
    for _ in range(int(math.ceil(SLOPE_REACH_M / dx)) + 1):
        go = (run < SLOPE_REACH_M) & (rcv[pos] >= 0)
        if not go.any():
            break
        run[go] += step[pos[go]]
        pos[go] = rcv[pos[go]]
    reach_slope = np.zeros(rcv.size)
    reach_slope[cells] = (h[cells] - h[pos]) / np.maximum(run, dx)
    theta, bins_used = _concavity(A, reach_slope, has_r)
    channel_length_m = float(step[has_r].sum())
    area_km2 = float(n_data) * dx * dx / 1e6
    return {"strahler_order_max": int(order.max()) if order.size else 0, "hack_exponent": hack,
            "concavity_theta": theta, "concavity_bins": bins_used, "concavity_theta_cell": theta_cell,
            "concavity_slope_reach_m": SLOPE_REACH_M,
            "drainage_density_per_km": channel_length_m / 1000.0 / area_km2 if area_km2 > 0 else 0.0,
            "channel_cells": int(rcv.size)}
