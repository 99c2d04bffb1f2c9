"""A scenario from a star sensor's datasheet (``starenv new``): a handful of values in, a complete scenario TOML
out, with every figure derived from them in a comment beside the keys.

Closed forms, with ``f`` the focal length, ``p`` the pixel pitch, ``D`` the aperture, ``t`` the exposure, all in
consistent units:

* focal length from a field of view across the width: ``f = (W p / 2) / tan(FOV / 2)``; in pixels ``f / p``;
  f-number ``f / D``; field of view edge to edge ``2 atan(W p / 2 f)`` (height and diagonal alike);
* IFOV (plate scale per pixel) ``p / f`` rad, as the simulator takes a pixel's solid angle; plate scale ``1 / f``;
* the flux of a magnitude-0 star through the pupil, ``Phi0 pi (D / 2)^2`` photons/s (``Phi0``:
  :data:`starenv.sim.photometry.ZERO_POINT_PHOTONS_M2_S`), times transmission and QE for electrons/s;
* noise per pixel in one exposure, ``sigma_px^2 = R^2 + (dark + sky) t``; a star's SNR over the noise-equivalent
  area of the Gaussian spot, ``A = 4 pi sigma_psf^2`` px, is ``S / sqrt(S + A sigma_px^2)``, so the faintest star at
  a given SNR ``k`` holds ``S = (k^2 + sqrt(k^4 + 4 k^2 A sigma_px^2)) / 2`` electrons (limiting magnitude
  ``-2.5 log10(S / (e0 t))``);
* saturation: a star centred on a pixel puts ``erf(1 / (2 sqrt(2) sigma_psf))^2`` of its light in that pixel;
* smear: ``f / p x t`` px per rad/s of rate across the boresight;
* stars in the field: the Hipparcos-2 count brighter than the limiting magnitude (log-interpolated between whole
  magnitudes, :data:`starenv.scenario.HIP_COUNT_AT_MAG`) times the field's share of the sky, a rectangular field of
  full angles ``a`` x ``b`` covering ``4 asin(sin(a / 2) sin(b / 2))`` sr.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from starenv import scenario as scenario_mod
from starenv.config import toml_value
from starenv.sim.conventions import ARCSEC
from starenv.sim.gyro import GyroSpec
from starenv.sim.imager import DetectorSpec
from starenv.sim.photometry import Photometry

DEFAULT_DETECTOR = DetectorSpec()
WAVELENGTH_M = 550e-9  # the diffraction figure's wavelength: the middle of a silicon sensor's band


@dataclass(frozen=True)
class SensorSheet:
    """One star sensor head's datasheet values: give ``fov_deg`` (full field across the width, edge to edge) or
    ``focal_length_mm``; ``snr`` is the signal-to-noise ratio the limiting magnitude is stated for."""

    width: int
    height: int
    pixel_pitch_um: float
    aperture_mm: float
    exposure_ms: float
    frame_rate_hz: float
    focal_length_mm: float | None = None
    fov_deg: float | None = None
    read_noise_e: float = DEFAULT_DETECTOR.read_noise_e
    dark_current_e_per_s: float = DEFAULT_DETECTOR.dark_current_e_per_s
    full_well_e: float = DEFAULT_DETECTOR.full_well_e
    gain_e_per_dn: float = DEFAULT_DETECTOR.gain_e_per_dn
    quantum_efficiency: float = 0.6
    transmission: float = 0.8
    adc_bits: int = DEFAULT_DETECTOR.adc_bits
    psf_sigma_px: float = 1.0
    snr: float = 5.0
    sky_mag_per_arcsec2: float = 22.0
    duration_s: float = 10.0
    name: str = "my_sensor"

    def __post_init__(self):
        if (self.fov_deg is None) == (self.focal_length_mm is None):
            raise ValueError("give the field of view (--fov DEG) or the focal length (--focal-mm F), one of them")
        if self.fov_deg is not None and not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"--fov {self.fov_deg:g}: expected a full field of view in (0, 180) deg")
        for flag, value in (("--pixel-um", self.pixel_pitch_um), ("--aperture-mm", self.aperture_mm),
                            ("--exposure-ms", self.exposure_ms), ("--rate-hz", self.frame_rate_hz),
                            ("--snr", self.snr), ("--duration-s", self.duration_s)):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{flag} {value}: expected a number > 0")
        if self.exposure_ms * 1e-3 > 1.0 / self.frame_rate_hz:
            raise ValueError(f"--exposure-ms {self.exposure_ms:g}: expected at most the frame period "
                             f"{1e3 / self.frame_rate_hz:g} ms of --rate-hz {self.frame_rate_hz:g}")
        if not self.name.replace("_", "").replace("-", "").isalnum():
            raise ValueError(f"--name {self.name!r}: expected letters, digits, '_' or '-'")

    @property
    def focal_mm(self) -> float:
        """The focal length (mm): as given, or the one that gives ``fov_deg`` across the width."""
        if self.focal_length_mm is not None:
            return self.focal_length_mm
        return self.width * self.pixel_pitch_um * 1e-3 / 2.0 / math.tan(math.radians(self.fov_deg) / 2.0)


def limiting_electrons(snr: float, noise_var_px: float, area_px: float) -> float:
    """Electrons a star must deliver in one exposure to reach ``snr`` over ``area_px`` pixels each of noise
    variance ``noise_var_px`` (e-^2), its own shot noise included: the root of ``S / sqrt(S + A v) = snr``."""
    k2 = snr * snr
    return (k2 + math.sqrt(k2 * k2 + 4.0 * k2 * area_px * noise_var_px)) / 2.0


def stars_brighter(magnitude: float) -> float:
    """Hipparcos-2 stars on the whole sky brighter than ``magnitude`` (Hp), log-interpolated between whole
    magnitudes of :data:`starenv.scenario.HIP_COUNT_AT_MAG` (-2 .. 14)."""
    counts = scenario_mod.HIP_COUNT_AT_MAG  # counts[i]: stars with Hp <= i - 2
    m = min(max(magnitude, -2.0), 14.0)
    i = min(int(math.floor(m)) + 2, len(counts) - 2)
    if counts[i] == 0:  # below the brightest star's bin: no log to interpolate in
        return counts[i + 1] * (m - (i - 2))
    return counts[i] * (counts[i + 1] / counts[i]) ** (m - (i - 2))


def rectangle_solid_angle_sr(full_x_rad: float, full_y_rad: float) -> float:
    """Solid angle (sr) of a rectangular pyramid field of full angles ``full_x_rad`` x ``full_y_rad``."""
    return 4.0 * math.asin(math.sin(full_x_rad / 2.0) * math.sin(full_y_rad / 2.0))


def derived(sheet: SensorSheet) -> dict[str, tuple[float, str, str]]:
    """Every figure derived from the datasheet: key -> (value, unit, what it is), in the order the file shows them."""
    f_mm, p_mm = sheet.focal_mm, sheet.pixel_pitch_um * 1e-3
    t = sheet.exposure_ms * 1e-3
    f_px = f_mm / p_mm
    ifov_rad = p_mm / f_mm
    fov = {axis: 2.0 * math.atan(n * p_mm / 2.0 / f_mm) for axis, n in
           (("width", sheet.width), ("height", sheet.height), ("diagonal", math.hypot(sheet.width, sheet.height)))}
    head = Photometry(sheet.aperture_mm * 1e-3, sheet.transmission, sheet.quantum_efficiency)
    pupil = Photometry(sheet.aperture_mm * 1e-3, 1.0, 1.0)  # unit throughput: the photons at the pupil
    e0 = head.electrons_per_s_mag0
    sky = head.sky_electrons_per_px_s(sheet.sky_mag_per_arcsec2, (ifov_rad / ARCSEC) ** 2)
    noise_var = sheet.read_noise_e ** 2 + (sheet.dark_current_e_per_s + sky) * t
    area = 4.0 * math.pi * sheet.psf_sigma_px ** 2
    limit = -2.5 * math.log10(limiting_electrons(sheet.snr, noise_var, area) / (e0 * t))
    peak_share = math.erf(1.0 / (2.0 * math.sqrt(2.0) * sheet.psf_sigma_px)) ** 2
    saturation = -2.5 * math.log10(sheet.full_well_e / (peak_share * e0 * t))
    adc_e = (2 ** sheet.adc_bits - 1 - DEFAULT_DETECTOR.bias_dn) * sheet.gain_e_per_dn
    sky_share = rectangle_solid_angle_sr(fov["width"], fov["height"]) / (4.0 * math.pi)
    out = {
        "focal_length_mm": (f_mm, "mm", "focal length" + (" (from the field of view across the width)"
                                                          if sheet.focal_length_mm is None else "")),
        "focal_length_px": (f_px, "px", "focal length in pixels, f / p"),
        "f_number": (f_mm / sheet.aperture_mm, "", "f-number, f / D"),
        "fov_width_deg": (math.degrees(fov["width"]), "deg", "field of view across the width, edge to edge"),
        "fov_height_deg": (math.degrees(fov["height"]), "deg", "field of view across the height"),
        "fov_diagonal_deg": (math.degrees(fov["diagonal"]), "deg", "field of view along the diagonal"),
        "ifov_arcsec_per_px": (ifov_rad / ARCSEC, "arcsec/px", "IFOV: one pixel's angle, p / f"),
        "ifov_urad_per_px": (ifov_rad * 1e6, "urad/px", "the same in microradians"),
        "plate_scale_arcsec_per_mm": (1.0 / f_mm / ARCSEC, "arcsec/mm", "plate scale, 1 / f"),
        "airy_diameter_px": (2.44 * WAVELENGTH_M * f_mm / sheet.aperture_mm / (p_mm * 1e-3), "px",
                             "diffraction spot (first dark ring) at 550 nm, 2.44 lambda N / p"),
        "photons_per_s_mag0": (pupil.electrons_per_s_mag0, "photons/s", "a magnitude-0 star through the aperture"),
        "electrons_per_s_mag0": (e0, "e-/s", "the same after transmission and QE"),
        "electrons_mag0_per_exposure": (e0 * t, "e-", "a magnitude-0 star in one exposure"),
        "sky_e_per_px_s": (sky, "e-/px/s", f"sky background at {sheet.sky_mag_per_arcsec2:g} mag/arcsec^2"),
        "noise_e_per_px": (math.sqrt(noise_var), "e-", "noise per pixel in one exposure: read, dark and sky shot"),
        "noise_area_px": (area, "px", "noise-equivalent area of the Gaussian spot, 4 pi sigma^2"),
        "limiting_magnitude": (limit, "mag", f"faintest star at SNR {sheet.snr:g} over that area"),
        "saturation_magnitude": (saturation, "mag", "brightest star whose peak pixel stays under the full well"),
        "adc_full_scale_e": (adc_e, "e-", "electrons at the ADC's top code above its bias (clips before the full "
                                          "well)" if adc_e < sheet.full_well_e else "electrons at the ADC's top "
                                                                                  "code above its bias"),
        "smear_px_per_dps": (f_px * t * math.radians(1.0), "px", "trail length per deg/s across the boresight"),
        "stars_in_field": (stars_brighter(limit) * sky_share, "", "mean Hipparcos-2 stars in the field brighter "
                                                                  "than the limiting magnitude"),
        "frame_period_ms": (1e3 / sheet.frame_rate_hz, "ms", "frame period"),
    }
    return out


def _line(key: str, value, comment: str = "") -> str:
    text = f"{key} = {toml_value(value)}"
    return f"{text:36s} # {comment}" if comment else text


def scenario_text(sheet: SensorSheet, given: frozenset[str] | None = None) -> str:
    """The scenario TOML of ``sheet``: a constant pointing, the default gyro and pipeline, one head with the
    sheet's optics and detector, every derived figure in a comment; it loads with :func:`starenv.scenario.load`.
    ``given``: the fields taken from the datasheet (the rest are marked as defaults; None: those that differ from
    their defaults)."""
    defaults = {f.name: f.default for f in dataclasses.fields(SensorSheet)}
    if given is None:
        given = frozenset(k for k, v in defaults.items() if getattr(sheet, k) != v)

    def _given(sheet: SensorSheet, field: str) -> str:
        return "datasheet" if field in given else "default, not given"

    figures = derived(sheet)
    value = {k: v for k, (v, _, _) in figures.items()}
    mag_limit = round(min(12.0, max(-2.0, value["limiting_magnitude"] + 1.0)), 1)
    threshold = float(f"{value['ifov_arcsec_per_px']:.3g}")
    gyro = GyroSpec()
    head_desc = (f"{sheet.width}x{sheet.height} px of {sheet.pixel_pitch_um:g} um, f {value['focal_length_mm']:.4g} "
                 f"mm, D {sheet.aperture_mm:g} mm, {sheet.exposure_ms:g} ms at {sheet.frame_rate_hz:g} Hz")
    lines = [
        f"# {sheet.name}: a star sensor from its datasheet (starenv new).  Every key is documented in",
        "# starenv/scenario.py and in the bundled scenarios (starenv scenarios --show paper_000).  Derived from the",
        "# datasheet values (closed forms in starenv/sensor_sheet.py):",
        "#",
    ]
    lines += [f"#   {key:30s} {v:12.5g} {unit:10s} {what}" for key, (v, unit, what) in figures.items()]
    lines += [
        "",
        _line("name", sheet.name),
        _line("description", f"a star sensor from its datasheet: {head_desc}"),
        _line("seed", 0),
        _line("duration_s", float(sheet.duration_s), f"{math.floor(sheet.duration_s * sheet.frame_rate_hz + 1e-9)} "
                                                     "frames"),
        _line("frame_rate_hz", float(sheet.frame_rate_hz), "datasheet"),
        _line("exposure_s", sheet.exposure_ms * 1e-3, "datasheet"),
        _line("mag_limit", mag_limit, "stars rendered: the limiting magnitude + 1 (fainter clutter), at most 12"),
        _line("sky_mag_per_arcsec2", float(sheet.sky_mag_per_arcsec2), "dark sky (zodiacal + galactic)"),
        _line("availability_threshold_arcsec", threshold, "one pixel's IFOV: set your accuracy requirement"),
        "",
        "[motion]                             # inertial pointing: set a rate, a slew or a tumble for your mission",
        _line("kind", "constant_rate"),
        _line("rate_dps", [0.0, 0.0, 0.0], f"smear {value['smear_px_per_dps']:.3g} px per deg/s across the "
                                           "boresight"),
        _line("initial_ra_deg", 83.8, "Orion"),
        _line("initial_dec_deg", -5.4),
        _line("initial_roll_deg", 0.0),
        "",
        "[gyro]                               # the simulator's default gyro: set your gyro's datasheet values",
        _line("rate_hz", gyro.rate_hz),
        _line("arw_deg_rthr", gyro.arw_deg_rthr),
        _line("rrw_deg_hr_rthr", gyro.rrw_deg_hr_rthr),
        _line("bias_instability_deg_hr", gyro.bias_instability_deg_hr),
        "",
        "[drops]",
        _line("probability", 0.0, "no dropped frames"),
        "",
        "[[heads]]",
        _line("name", "main"),
        _line("focal_length_mm", float(f"{value['focal_length_mm']:.6g}"),
              _given(sheet, "focal_length_mm") if sheet.focal_length_mm is not None
              else f"from the {sheet.fov_deg:g} deg field across the width"),
        _line("pixel_pitch_um", float(sheet.pixel_pitch_um), "datasheet"),
        _line("width", int(sheet.width), "datasheet"),
        _line("height", int(sheet.height), "datasheet"),
        _line("f_number", float(f"{value['f_number']:.6g}"), f"focal length / the {sheet.aperture_mm:g} mm aperture"),
        _line("psf_sigma_px", float(sheet.psf_sigma_px), f"spot sigma ({_given(sheet, 'psf_sigma_px')})"),
        _line("transmission", float(sheet.transmission), f"optics ({_given(sheet, 'transmission')})"),
        _line("quantum_efficiency", float(sheet.quantum_efficiency), _given(sheet, "quantum_efficiency")),
        "",
        "[heads.detector]",
        _line("read_noise_e", float(sheet.read_noise_e), _given(sheet, "read_noise_e")),
        _line("dark_current_e_per_s", float(sheet.dark_current_e_per_s), _given(sheet, "dark_current_e_per_s")),
        _line("full_well_e", float(sheet.full_well_e), _given(sheet, "full_well_e")),
        _line("gain_e_per_dn", float(sheet.gain_e_per_dn), _given(sheet, "gain_e_per_dn")),
        _line("adc_bits", int(sheet.adc_bits), _given(sheet, "adc_bits")),
        _line("bias_dn", DEFAULT_DETECTOR.bias_dn, "default"),
        "",
    ]
    return "\n".join(lines)
