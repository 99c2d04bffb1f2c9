"""The image sensor: background, shot noise, dark current, hot pixels, cosmic rays, read noise, gain and the ADC.

Electrons in a pixel over one exposure are ``Poisson(star + background + dark) + hot pixel + cosmic ray + read noise``,
then clipped at the full well, divided by the gain, offset by the bias, rounded down and clipped to the ADC range.

Speed without a toy model: the dense part (background + dark, shot noise and read noise) is drawn as one normal
per pixel with the exact mean and variance ``lambda + read^2`` whenever the skewness of ``Poisson(lambda) + read``,
``lambda / (lambda + read^2)^1.5``, is below ``GAUSSIAN_SKEW_LIMIT`` everywhere on the frame (large backgrounds, or
read noise dominating a small one); otherwise the background's Poisson draw is exact.  Star signal, hot pixels and
cosmic rays are always exact Poisson / sampled draws on the few pixels they touch, added to the dense part
(independent Poisson variables add to a Poisson variable).
"""

from __future__ import annotations

import math
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from starenv import checks
from starenv.sim.render import StarSignal

GAUSSIAN_SKEW_LIMIT = 0.05
MIN_BINNED_SPREAD_DN = 1.0  # a background pixel's read-out spread (1 sigma) the binned read-out needs
BINNED_RANGE_SIGMAS = 8.0  # and its distance from the ADC's range ends, in those sigmas


@dataclass(frozen=True)
class DetectorSpec:
    """Sensor noise and readout, in electrons (e-), digital numbers (DN) and seconds.

    Hot pixels are a fixed pattern drawn once per sensor: ``hot_pixel_fraction`` of the pixels with extra dark
    current drawn log-normally around ``hot_pixel_dark_e_per_s`` (sigma 1 in ln).  Cosmic rays arrive as a Poisson
    process of ``cosmic_ray_rate_per_cm2_s`` over the sensor area during the exposure; each deposits a log-normal
    charge (median ``cosmic_ray_electrons``, sigma 0.5 in ln) along a straight track of random direction whose
    length is exponential with mean ``cosmic_ray_track_px``.  ``line_time_s > 0`` makes a rolling shutter.

    Off unless set: ``blooming`` spills the charge a pixel holds above ``full_well_e`` along its column
    (:func:`bloom_columns`); ``prnu_fraction`` is the relative spread (1 sigma) of each pixel's response to light
    and ``dsnu_fraction`` that of its dark current, both fixed patterns drawn once per sensor (after the hot pixels,
    from the same stream); a head's :class:`~starenv.sim.thermal.Thermal` scales the dark current (uniform, hot
    pixels and DSNU) with the sensor temperature.
    """

    read_noise_e: float = 8.0
    dark_current_e_per_s: float = 20.0
    gain_e_per_dn: float = 4.0
    bias_dn: float = 100.0
    full_well_e: float = 30000.0
    adc_bits: int = 12
    hot_pixel_fraction: float = 1e-4
    hot_pixel_dark_e_per_s: float = 3000.0
    cosmic_ray_rate_per_cm2_s: float = 5.0
    cosmic_ray_electrons: float = 2000.0
    cosmic_ray_track_px: float = 2.0
    line_time_s: float = 0.0
    blooming: bool = False
    prnu_fraction: float = 0.0
    dsnu_fraction: float = 0.0

    def __post_init__(self):
        checks.in_range("read_noise_e", self.read_noise_e, 0.0, 1000.0, unit="e-")
        checks.in_range("dark_current_e_per_s", self.dark_current_e_per_s, 0.0, 1e6, unit="e-/s")
        checks.in_range("gain_e_per_dn", self.gain_e_per_dn, 1e-3, 1e4, unit="e-/DN")
        checks.integer("adc_bits", self.adc_bits, 1, 16)
        checks.in_range("bias_dn", self.bias_dn, 0.0, 2.0**self.adc_bits - 1, unit="DN")
        checks.in_range("full_well_e", self.full_well_e, 0.0, 1e8, low_open=True, unit="e-")
        checks.probability("hot_pixel_fraction", self.hot_pixel_fraction)
        checks.in_range("hot_pixel_dark_e_per_s", self.hot_pixel_dark_e_per_s, 0.0, 1e9, unit="e-/s")
        checks.in_range("cosmic_ray_rate_per_cm2_s", self.cosmic_ray_rate_per_cm2_s, 0.0, 1e5, unit="1/cm^2/s")
        checks.in_range("cosmic_ray_electrons", self.cosmic_ray_electrons, 0.0, 1e8, unit="e-")
        checks.in_range("cosmic_ray_track_px", self.cosmic_ray_track_px, 0.0, 1e3, unit="px")
        checks.in_range("line_time_s", self.line_time_s, 0.0, 1e-3, unit="s")
        if not isinstance(self.blooming, bool):
            raise ValueError(f"blooming must be true or false, got {self.blooming!r}")
        checks.in_range("prnu_fraction", self.prnu_fraction, 0.0, 0.2)
        checks.in_range("dsnu_fraction", self.dsnu_fraction, 0.0, 1.0)

    @property
    def max_dn(self) -> int:
        return 2**self.adc_bits - 1


class Detector:
    """One head's sensor: fixed pattern (hot pixels) drawn at construction, noise drawn per exposure."""

    def __init__(
        self,
        spec: DetectorSpec,
        width: int,
        height: int,
        pixel_pitch_m: float,
        background_e_per_px_s: float | np.ndarray,
        fixed_pattern_rng: np.random.Generator,
    ):
        self.spec = spec
        self.shape = (int(height), int(width))
        self.pixel_area_cm2 = (pixel_pitch_m * 100.0) ** 2
        self.set_background(background_e_per_px_s)
        n_pix = self.shape[0] * self.shape[1]
        n_hot = int(fixed_pattern_rng.binomial(n_pix, spec.hot_pixel_fraction)) if spec.hot_pixel_fraction else 0
        self.hot_index = np.sort(fixed_pattern_rng.choice(n_pix, size=n_hot, replace=False))
        self.hot_rate_e_per_s = spec.hot_pixel_dark_e_per_s * fixed_pattern_rng.lognormal(0.0, 1.0, size=n_hot)
        # Fixed-pattern noise, drawn only when asked for (so the hot pixels and every stream stay as they were):
        # response (PRNU) and dark-current (DSNU) factors per pixel, mean 1, clipped at 0.
        self.prnu = self.dsnu = None
        for name, fraction in (("prnu", spec.prnu_fraction), ("dsnu", spec.dsnu_fraction)):
            if fraction > 0:
                factor = 1.0 + fraction * fixed_pattern_rng.standard_normal(self.shape)
                setattr(self, name, np.maximum(factor, 0.0).astype(np.float32))
        self._work = np.empty(self.shape, dtype=np.float32)  # read-out scratch, reused so its pages stay mapped

    def set_background(self, background_e_per_px_s: float | np.ndarray) -> None:
        """The light background (sky, stray light), e-/px/s, a scalar or a (height, width) map; the sensor replaces
        it frame by frame where bright bodies' stray light changes."""
        bg = np.asarray(background_e_per_px_s, dtype=np.float32)
        if bg.ndim not in (0, 2) or (bg.ndim == 2 and bg.shape != self.shape):
            raise ValueError(f"background_e_per_px_s must be a scalar or a {self.shape} map, got shape {bg.shape}")
        checks.finite("background_e_per_px_s", bg)
        if np.any(bg < 0):
            raise ValueError("background_e_per_px_s must be >= 0 e-/px/s")
        self.background_e_per_px_s = bg
        self._background_cache: tuple[tuple[float, float], np.ndarray, np.ndarray | None] | None = None

    def background(self, exposure_s: float, dark_factor: float = 1.0) -> tuple[np.ndarray, np.ndarray | None]:
        """Mean background + dark electrons per pixel over an exposure (scalar or map), and the per-pixel std of the
        Gaussian fast path (None when the exact Poisson path is used); ``dark_factor`` scales the dark current (the
        sensor temperature's, :meth:`~starenv.sim.thermal.Thermal.dark_factor`)."""
        key = (exposure_s, dark_factor)
        if self._background_cache is None or self._background_cache[0] != key:
            light = self.background_e_per_px_s if self.prnu is None else self.background_e_per_px_s * self.prnu
            dark = np.float32(self.spec.dark_current_e_per_s * dark_factor)
            if self.dsnu is not None:
                dark = dark * self.dsnu
            lam = (light + dark) * np.float32(exposure_s)
            read2 = self.spec.read_noise_e**2
            lo, hi = float(np.min(lam)), float(np.max(lam))
            worst = min(max(2.0 * read2, lo), hi)  # lambda / (lambda + r^2)^1.5 peaks at lambda = 2 r^2
            skew = worst / (worst + read2) ** 1.5 if worst + read2 > 0 else math.inf
            std = np.sqrt(lam + np.float32(read2)).astype(np.float32) if skew < GAUSSIAN_SKEW_LIMIT else None
            self._background_cache = (key, lam, std)
        return self._background_cache[1], self._background_cache[2]

    def peak_snr(self, peak_e: np.ndarray, xy: np.ndarray, exposure_s: float, dark_factor: float = 1.0) -> np.ndarray:
        """Signal-to-noise of a star whose brightest pixel (at ``xy``, px) expects ``peak_e`` electrons."""
        lam, _ = self.background(exposure_s, dark_factor)
        if lam.ndim:
            col = np.clip(np.rint(xy[:, 0]), 0, self.shape[1] - 1).astype(np.intp)
            row = np.clip(np.rint(xy[:, 1]), 0, self.shape[0] - 1).astype(np.intp)
            lam = lam[row, col]
        return peak_e / np.sqrt(peak_e + lam + self.spec.read_noise_e**2)

    def draw_background(self, exposure_s: float, rng: np.random.Generator, dark_factor: float = 1.0) -> np.ndarray:
        """The read-out's frame before the stars, float32 DN (height, width), in the detector's scratch frame: the
        background and dark electrons of an exposure (s), the dark current scaled by ``dark_factor``, with their shot
        and read noise, through the gain and bias.  The first draws of a read-out from ``rng``: :meth:`read_out` makes
        it, or takes it made ahead (on another thread while the stars render, numpy's draws releasing the GIL)."""
        spec = self.spec
        inv_gain = np.float32(1.0 / spec.gain_e_per_dn)
        lam, std = self.background(exposure_s, dark_factor)
        dn = self._work
        if std is not None:
            rng.standard_normal(dtype=np.float32, out=dn)
            dn *= std * inv_gain
            dn += lam * inv_gain + np.float32(spec.bias_dn)
        else:
            dn[...] = rng.poisson(np.broadcast_to(lam, self.shape))
            if spec.read_noise_e > 0:
                dn += rng.normal(0.0, spec.read_noise_e, self.shape).astype(np.float32)
            dn *= inv_gain
            dn += np.float32(spec.bias_dn)
        return dn

    def read_out(self, signal: StarSignal, exposure_s: float, rng: np.random.Generator,
                 dark_factor: float = 1.0, background: Future | None = None) -> np.ndarray:
        """A uint16 frame (height, width) in DN for the given star signal (expected e-) and exposure (s), the dark
        current scaled by ``dark_factor``; ``background``: its :meth:`draw_background` for this exposure and dark
        factor, started ahead on ``rng`` (which must serve nothing else meanwhile; the frame is then the same bit for
        bit), or None to draw it here.

        Works in DN from the start (``e / gain + bias``) so the full-frame passes are few; the full well
        (``min(e, full_well)``) is the clip at ``full_well / gain + bias``.  With blooming the charge above the full
        well spills along the columns first (:func:`bloom_columns`, on the charge with the read noise already in
        it: a few read-noise sigmas of the full well).
        """
        spec = self.spec
        inv_gain = np.float32(1.0 / spec.gain_e_per_dn)
        dn = self.draw_background(exposure_s, rng, dark_factor) if background is None else background.result()
        flat = dn.reshape(-1)
        if signal.shape != self.shape:
            raise ValueError(f"signal is for a {signal.shape} sensor, this one is {self.shape}")
        electrons = signal.electrons if self.prnu is None else signal.electrons * self.prnu.ravel()[signal.index]
        flat[signal.index] += rng.poisson(electrons).astype(np.float32) * inv_gain
        if len(self.hot_index):
            hot = rng.poisson(self.hot_rate_e_per_s * exposure_s * dark_factor)
            flat[self.hot_index] += hot.astype(np.float32) * inv_gain
        self._add_cosmic_rays(dn, exposure_s, rng, inv_gain)
        if spec.blooming:
            bloom_columns(dn, spec.full_well_e / spec.gain_e_per_dn + spec.bias_dn, spec.bias_dn)
        top = min(float(spec.max_dn), spec.full_well_e / spec.gain_e_per_dn + spec.bias_dn)
        # clip and convert in one pass (the cast truncates: the ADC's floor for non-negative values)
        return np.clip(dn, 0.0, np.float32(top), out=np.empty(self.shape, np.uint16), casting="unsafe")

    def _add_cosmic_rays(self, dn: np.ndarray, exposure_s: float, rng: np.random.Generator, inv_gain) -> None:
        index, value = self._cosmic_ray_hits(exposure_s, rng, inv_gain)
        np.add.at(dn.reshape(-1), index, value)

    def _cosmic_ray_hits(self, exposure_s: float, rng: np.random.Generator,
                         inv_gain) -> tuple[np.ndarray, np.ndarray]:
        """The cosmic rays of one exposure: flat pixel indices and float32 DN, one entry per track segment (a
        pixel may repeat; the entries are added in order)."""
        spec = self.spec
        h, w = self.shape
        mean_hits = spec.cosmic_ray_rate_per_cm2_s * self.pixel_area_cm2 * h * w * exposure_s
        n_hits = int(rng.poisson(mean_hits)) if mean_hits > 0 else 0
        if n_hits == 0:
            return np.zeros(0, np.intp), np.zeros(0, np.float32)
        start = rng.uniform([0.0, 0.0], [w - 1.0, h - 1.0], size=(n_hits, 2))
        angle = rng.uniform(0.0, 2 * np.pi, n_hits)
        length = rng.exponential(spec.cosmic_ray_track_px, n_hits) if spec.cosmic_ray_track_px > 0 else np.zeros(n_hits)
        charge = spec.cosmic_ray_electrons * rng.lognormal(0.0, 0.5, n_hits)
        index, value = [], []
        for (x, y), a, length_px, q in zip(start, angle, length, charge, strict=True):
            n_seg = max(1, math.ceil(length_px * 2))
            s = (np.arange(n_seg) + 0.5) / n_seg * length_px
            cols = np.clip(np.rint(x + s * math.cos(a)), 0, w - 1).astype(np.intp)
            rows = np.clip(np.rint(y + s * math.sin(a)), 0, h - 1).astype(np.intp)
            index.append(rows * w + cols)
            value.append(np.full(n_seg, np.float32(q / n_seg) * inv_gain, dtype=np.float32))
        return np.concatenate(index), np.concatenate(value)

    def read_out_binned(self, signal: StarSignal, exposure_s: float, rng: np.random.Generator, block: int,
                        dark_factor: float = 1.0) -> np.ndarray:
        """The frame :meth:`read_out` gives, averaged over ``block`` x ``block`` px blocks (float64 DN, (height /
        block, width / block)), drawn without the whole frame: equal in distribution to those block means.

        The pixels that hold star signal, a hot pixel or a cosmic ray are read out one by one as :meth:`read_out`
        reads them (Poisson signal, the Gaussian background, the full well, the ADC's floor and range).  The others
        hold background alone; their sum over a block is drawn as one normal with the exact mean and variance of the
        sum of their read-outs: each is ``floor(x)`` with ``x`` normal (the Gaussian background path), whose mean is
        ``E[x] - 1/2`` and variance ``var(x) + 1/12`` when ``x`` spreads over more than ``MIN_BINNED_SPREAD_DN``
        (the fractional part is then uniform to within 1e-8), and a sum of hundreds of them is normal.  Refused
        where that does not hold: the exact Poisson background path, blooming, a block that does not tile the frame,
        or background pixels within ``BINNED_RANGE_SIGMAS`` of the ADC's range ends.
        """
        spec = self.spec
        h, w = self.shape
        if block < 1 or h % block or w % block:
            raise ValueError(f"read_out_binned: {block} px blocks do not tile a {w} x {h} px frame")
        if spec.blooming:
            raise ValueError("read_out_binned: blooming moves charge between pixels; read the whole frame out")
        if signal.shape != self.shape:
            raise ValueError(f"signal is for a {signal.shape} sensor, this one is {self.shape}")
        lam, std = self.background(exposure_s, dark_factor)
        if std is None:
            raise ValueError("read_out_binned: the background takes the exact Poisson path here (a small background "
                             "against the read noise); read the whole frame out")
        inv_gain = 1.0 / spec.gain_e_per_dn
        top = min(float(spec.max_dn), spec.full_well_e / spec.gain_e_per_dn + spec.bias_dn)
        mean_dn = np.asarray(lam, np.float64) * inv_gain + spec.bias_dn  # a background pixel's E[x]
        sd_dn = np.asarray(std, np.float64) * inv_gain
        if np.min(sd_dn) < MIN_BINNED_SPREAD_DN or np.min(mean_dn - BINNED_RANGE_SIGMAS * sd_dn) < 0 or np.max(
                mean_dn + BINNED_RANGE_SIGMAS * sd_dn) > top:
            raise ValueError("read_out_binned: the background read-out is too narrow or too near the ADC's range "
                             "for the block sums' closed form; read the whole frame out")
        electrons = signal.electrons if self.prnu is None else signal.electrons * self.prnu.ravel()[signal.index]
        index = [signal.index.astype(np.intp)]
        extra = [rng.poisson(electrons).astype(np.float32) * np.float32(inv_gain)]
        if len(self.hot_index):
            index.append(self.hot_index.astype(np.intp))
            extra.append(rng.poisson(self.hot_rate_e_per_s * exposure_s * dark_factor).astype(np.float32)
                         * np.float32(inv_gain))
        cr_index, cr_value = self._cosmic_ray_hits(exposure_s, rng, np.float32(inv_gain))
        index.append(cr_index)
        extra.append(cr_value)
        pixels, where = np.unique(np.concatenate(index), return_inverse=True)
        added = np.bincount(where, np.concatenate(extra).astype(np.float64), minlength=len(pixels))
        own_mean = mean_dn if mean_dn.ndim == 0 else mean_dn.ravel()[pixels]
        own_sd = sd_dn if sd_dn.ndim == 0 else sd_dn.ravel()[pixels]
        own = np.floor(np.clip(rng.standard_normal(len(pixels)) * own_sd + own_mean + added, 0.0, top))
        hb, wb = h // block, w // block
        cell = (pixels // w) // block * wb + (pixels % w) // block
        n_own = np.bincount(cell, minlength=hb * wb)
        var_dn = sd_dn**2 + 1.0 / 12.0
        if mean_dn.ndim == 0:
            n_rest = block * block - n_own
            rest_mean, rest_var = n_rest * (mean_dn - 0.5), n_rest * var_dn
        else:
            def block_sums(x):
                return x.reshape(hb, block, wb, block).sum(axis=(1, 3)).ravel()
            rest_mean = block_sums(mean_dn - 0.5) - np.bincount(cell, own_mean - 0.5, minlength=hb * wb)
            rest_var = block_sums(var_dn) - np.bincount(cell, var_dn.ravel()[pixels], minlength=hb * wb)
        rest = rng.standard_normal(hb * wb) * np.sqrt(np.maximum(rest_var, 0.0)) + rest_mean
        total = rest + np.bincount(cell, own, minlength=hb * wb)
        return (total / (block * block)).reshape(hb, wb)

def _spill(charge: np.ndarray, source: np.ndarray, full: float) -> float:
    """Move ``source`` (rows, cols) charge from each pixel towards row ``rows - 1`` of ``charge`` (rows, cols), every
    pixel on the way filled up to ``full`` before the rest passes on; in place.  Returns the charge that left the
    last row.  The flow out of pixel ``k`` is Lindley's recursion ``W_k = max(0, W_{k-1} + s_k - room_k)``, in
    closed form ``W_k = S_k - min(0, min_{j<=k} S_j)`` with ``S`` the running sum of ``s - room``."""
    room = full - charge
    running = np.cumsum(source - room, axis=0)
    flow = running - np.minimum(np.minimum.accumulate(running, axis=0), 0.0)
    inflow = np.vstack([np.zeros((1, charge.shape[1])), flow[:-1]])
    charge += inflow + source - flow
    return float(flow[-1].sum())


def bloom_columns(image: np.ndarray, full: float, empty: float = 0.0) -> float:
    """Blooming, in place on ``image`` (rows, cols; any units, ``empty`` the level of no charge): the charge each
    pixel holds above ``full`` leaves it, half towards row 0 and half towards the last row, filling the pixels of
    its column on the way up to ``full``; what passes the sensor's first or last row is lost.  Charge is conserved:
    returns the lost amount, so the image's sum before equals its sum after plus that.  Only the columns holding a
    pixel above ``full`` are touched."""
    cols = np.flatnonzero(np.any(image > full, axis=0))
    if len(cols) == 0:
        return 0.0
    charge = image[:, cols].astype(np.float64) - empty
    top = full - empty
    excess = np.maximum(charge - top, 0.0)
    charge -= excess
    lost = _spill(charge[::-1], 0.5 * excess[::-1], top)  # towards row 0: the columns read bottom-up
    lost += _spill(charge, 0.5 * excess, top)
    image[:, cols] = charge + empty
    return lost
