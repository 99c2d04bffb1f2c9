"""Dataset specs: a scenario, the randomised overrides each sample draws, the kind of sample and the sizes.

A spec is a TOML file (or dict), validated on load by the project's config engine (:mod:`starenv.config`); a bad
value raises :class:`DatasetError` (a ``ConfigError``) naming the file and the dotted key.  Layout (every table but
the top level is optional)::

    name = "paper002_orion"
    kind = "main_star"            # "main_star": raw image + boresight star label (paper 002)
                                  # "centroids": truth centroids with HIP ids, false stars id -1 (paper 004)
                                  # "position_pairs": measured / reference star positions (paper 003)
                                  # "smear_pairs": smeared / still patches around each star (restoration)
    scenario = "paper_002"        # bundled name or path (relative paths: from the spec file's folder)
    samples = 16000               # sample indices 0 .. samples-1
    shard_size = 500              # samples per shard file (the last shard may be shorter)
    seed = 0                      # sample i draws from np.random.SeedSequence([seed, i])
    input_size = 256              # main_star: the image stored is the frame area-resized to input_size^2 px with its
                                  # background (median) subtracted, the network's input (datasets/preprocess.py);
                                  # default: the largest multiple of 16 up to 256 the frame resizes to in whole
                                  # square blocks (max(width, height) / input_size px, dividing both sides)
    readout = "frame"             # main_star: "frame" reads the whole frame out and resizes it; "binned" draws its
                                  # block means directly (equal in distribution, far cheaper: Detector.read_out_binned)
    centre = "frame"              # main_star: what sits at the input's centre: the frame's ("frame", the paper's
                                  # resize) or the main star's block ("main_star": the input shifted, zeros shifted in)

    [overrides]                   # fixed scenario overrides, dotted key paths (as `starenv run --set`)
    "heads.0.width" = 128

    [randomize]                   # per-sample scenario overrides drawn uniformly in [low, high]
    "heads.0.detector.read_noise_e" = [5.0, 15.0]

    [pointing]
    mode = "main_star"            # "main_star": head 0's boresight on a navigation star at mid-exposure (paper 002)
                                  # "uniform": attitude uniform on the rotation group (roll included)
    mag_limit = 6.0               # navigation stars (the classes): Hp <= mag_limit ...
    center_ra_deg = 83.8          # ... within radius_deg of this direction (radius 180: the whole sky)
    center_dec_deg = -5.4
    radius_deg = 180.0
    roll_step_deg = 0.0           # 0: roll uniform in [0, 360); > 0: a multiple of the step (paper 002: 30)
    offset_deg = 0.0              # main_star: the boresight uniform within offset_deg of the main star, among the
                                  # directions whose nearest navigation star (Hp <= mag_limit, whole sky) it is
                                  # (the label: the navigation star nearest the image centre); 0: on the star

    [rates]                       # head 0's camera frame: two-axis (in-plane) magnitude, its direction, roll rate
    two_axis_dps = [0.0, 2.0, 4.0, 6.0, 8.0]    # resultant |(wx, wy)| drawn from this list ...
    two_axis_range_dps = [0.0, 10.0]            # ... or uniformly in this range (give one of the two)
    directions = 8                # smear directions at 360/n deg (0: uniform)
    roll_dps = [0.0, 6.0, -6.0]   # wz drawn from this list

    [stars]
    variants = ["clean", "false", "missing"]    # one drawn per sample (paper 002's three training sets)
    max_changed = 2               # 1 .. max_changed false stars added / field stars removed
    false_mag_range = [3.0, 6.0]  # magnitude of a false star (uniform)
    position_sigma_px = 0.0       # Gaussian shift of every star's direction, px on head 0 (whole trail)
    magnitude_sigma = 0.0         # Gaussian magnitude noise, mag

    [pairs]                       # kind = "position_pairs" (no image is rendered: the frame's geometry)
    centroid_noise_px = 0.05      # Gaussian noise of each measured position, px per axis

    [patches]                     # kind = "smear_pairs"
    size_px = 32                  # square patches centred on each detectable star's mid-exposure pixel

The spec's identity (:attr:`DatasetSpec.digest`) is the SHA-256 of its validated contents, the scenario's text and
the format version; it travels in every shard and in trained weights' manifests.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from starenv import scenario as scenario_mod
from starenv.config import REQUIRED, ConfigError, Table, parse_toml
from starenv.datasets.preprocess import square_block

FORMAT_VERSION = 1
KINDS = ("main_star", "centroids", "position_pairs", "smear_pairs")
VARIANTS = ("clean", "false", "missing")


class DatasetError(ConfigError):
    """A dataset spec that does not describe a valid dataset."""


@dataclass(frozen=True)
class PointingSpec:
    mode: str = "main_star"
    mag_limit: float = 6.0
    center_ra_deg: float = 0.0
    center_dec_deg: float = 0.0
    radius_deg: float = 180.0
    roll_step_deg: float = 0.0
    offset_deg: float = 0.0


@dataclass(frozen=True)
class RateSpec:
    two_axis_dps: tuple[float, ...] | None = (0.0,)
    two_axis_range_dps: tuple[float, float] | None = None
    directions: int = 8
    roll_dps: tuple[float, ...] = (0.0,)


@dataclass(frozen=True)
class StarsSpec:
    variants: tuple[str, ...] = ("clean",)
    max_changed: int = 2
    false_mag_range: tuple[float, float] = (3.0, 6.0)
    position_sigma_px: float = 0.0
    magnitude_sigma: float = 0.0


@dataclass(frozen=True)
class PairsSpec:
    centroid_noise_px: float = 0.05


@dataclass(frozen=True)
class PatchSpec:
    size_px: int = 32


@dataclass(frozen=True)
class DatasetSpec:
    """A validated dataset spec (see the module docstring); ``scenario_text`` is the scenario file's text."""

    name: str
    kind: str
    scenario: str
    scenario_text: str
    samples: int
    shard_size: int
    seed: int
    overrides: dict[str, Any] = field(default_factory=dict)
    randomize: dict[str, tuple[float, float]] = field(default_factory=dict)
    pointing: PointingSpec = PointingSpec()
    rates: RateSpec = RateSpec()
    stars: StarsSpec = StarsSpec()
    pairs: PairsSpec = PairsSpec()
    patches: PatchSpec = PatchSpec()
    source: str = "<dataset>"
    input_size: int | None = None
    readout: str = "frame"
    centre: str = "frame"

    @property
    def n_shards(self) -> int:
        return math.ceil(self.samples / self.shard_size)

    def shard_range(self, shard: int) -> range:
        """Sample indices of shard ``shard``."""
        return range(shard * self.shard_size, min(self.samples, (shard + 1) * self.shard_size))

    def identity(self) -> dict:
        """Everything that decides the samples' bytes (not the file it came from; not the tables of other kinds)."""
        d = self.to_dict()
        if self.pointing.offset_deg == 0.0:
            d["pointing"].pop("offset_deg")
        for table, kind in (("pairs", "position_pairs"), ("patches", "smear_pairs")):
            if self.kind != kind:
                d.pop(table)
        d["format_version"] = FORMAT_VERSION
        return d

    @functools.cached_property
    def digest(self) -> str:  # cached: every sample's context is looked up by it
        text = json.dumps(self.identity(), sort_keys=True, default=list)
        return hashlib.sha256(text.encode()).hexdigest()

    def to_dict(self) -> dict:
        """A dict that :func:`load_spec` turns back into this spec (the scenario inlined as its text)."""
        d = asdict(self)
        d.pop("source")
        if self.input_size is None:
            d.pop("input_size")
        for key in ("readout", "centre"):  # defaults left out: specs written before these keys keep their digests
            if d[key] == "frame":
                d.pop(key)
        return d

    def load_scenario(self, extra: dict[str, Any] | None = None) -> scenario_mod.Scenario:
        """The scenario with the spec's fixed overrides and ``extra`` (per-sample) ones applied."""
        data = tomllib.loads(self.scenario_text)
        data.setdefault("name", Path(self.scenario).stem)
        return scenario_mod.load(data, {**self.overrides, **(extra or {})})


OPTION_TABLES = ("pointing", "rates", "stars", "pairs", "patches")


def _table(parent: Table, key: str) -> Table:
    """The sub-table ``key`` of ``parent`` (an empty one when absent: every option has a default)."""
    return parent.table(key) or Table({}, parent.where(key), parent.source, parent.error)


def _unset_dropped(data: dict) -> dict:
    """``data`` without the ``None`` values :meth:`DatasetSpec.to_dict` writes in the option tables for unset options
    (a spec read back from ``dataset.json``); a ``None`` anywhere else stays, to be refused."""
    out = dict(data)
    for key in OPTION_TABLES:
        if isinstance(out.get(key), dict):
            out[key] = {k: v for k, v in out[key].items() if v is not None}
    return out


def default_input_size(width: int, height: int) -> int:
    """The largest multiple of 16 up to 256 that a ``width`` x ``height`` px frame area-resizes to in whole square
    blocks (:func:`~starenv.datasets.preprocess.square_block`; the network input of a ``main_star`` spec that names
    none); the frame's longer side over the greatest common divisor of its sides when none does."""
    fits = [d for d in range(16, 257, 16) if square_block(width, height, d)]
    return fits[-1] if fits else max(width, height) // math.gcd(width, height)


def load_spec(spec: str | Path | dict, source: str | None = None) -> DatasetSpec:
    """Load and validate a dataset spec from a TOML file or a dict (as :meth:`DatasetSpec.to_dict` gives)."""
    base = Path.cwd()
    if isinstance(spec, dict):
        data, source = _unset_dropped(spec), source or "<dataset>"
    else:
        path = Path(spec)
        source = str(path)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{source}: cannot read a TOML dataset spec: {exc}") from exc
        data = parse_toml(text, source, DatasetError)
        base = path.resolve().parent
    top = Table(data, "", source, DatasetError)
    name = top.string("name", "dataset")
    kind = top.string("kind", REQUIRED, KINDS)
    scenario = top.string("scenario")
    scenario_text = top.get("scenario_text", None)
    if scenario_text is None:
        candidate = base / scenario
        try:
            path = candidate if candidate.suffix == ".toml" and candidate.is_file() else scenario_mod.resolve(scenario)
            scenario_text = path.read_text(encoding="utf-8")
        except (scenario_mod.ScenarioError, OSError) as exc:
            top.fail("scenario", f"a bundled scenario name or a .toml file ({exc})", scenario)
    elif not isinstance(scenario_text, str):
        top.fail("scenario_text", "the scenario's TOML text", scenario_text)
    samples = top.number("samples", REQUIRED, 1, 10**9, integer=True)
    shard_size = top.number("shard_size", 1000, 1, 10**6, integer=True)
    seed = top.number("seed", 0, 0, 2**63 - 1, integer=True)
    input_size = top.number("input_size", None, 1, 1024, integer=True) if kind == "main_star" else None
    readout = top.string("readout", "frame", ("frame", "binned")) if kind == "main_star" else "frame"
    centre = top.string("centre", "frame", ("frame", "main_star")) if kind == "main_star" else "frame"
    overrides = top.get("overrides", {})
    if not isinstance(overrides, dict):
        top.fail("overrides", "a table of dotted scenario keys", overrides)
    rnd = _table(top, "randomize")
    randomize = {key: rnd.vector(key, 2, REQUIRED, -1e12, 1e12) for key in sorted(rnd.data)}
    for key, (low, high) in randomize.items():
        if low > high:
            rnd.fail(key, "[low, high] with low <= high", [low, high])
    rnd.finish()

    pt = _table(top, "pointing")
    pointing = PointingSpec(
        mode=pt.string("mode", "main_star" if kind == "main_star" else "uniform", ("main_star", "uniform")),
        mag_limit=pt.number("mag_limit", 6.0, -2.0, 14.0),
        center_ra_deg=pt.number("center_ra_deg", 0.0, -360.0, 360.0),
        center_dec_deg=pt.number("center_dec_deg", 0.0, -90.0, 90.0),
        radius_deg=pt.number("radius_deg", 180.0, 0.1, 180.0),
        roll_step_deg=pt.number("roll_step_deg", 0.0, 0.0, 360.0),
        offset_deg=pt.number("offset_deg", 0.0, 0.0, 90.0),
    )
    pt.finish()
    if kind == "main_star" and pointing.mode != "main_star":
        pt.fail("mode", "'main_star' for kind = 'main_star' (the label is the boresight star)", pointing.mode)

    rt = _table(top, "rates")
    listed = rt.vector("two_axis_dps", None, None, 0.0, 1000.0)
    ranged = rt.vector("two_axis_range_dps", 2, None, 0.0, 1000.0)
    if listed is not None and ranged is not None:
        rt.fail("two_axis_range_dps", "either two_axis_dps or two_axis_range_dps, not both", list(ranged))
    if ranged is not None and ranged[0] > ranged[1]:
        rt.fail("two_axis_range_dps", "[low, high] with low <= high", list(ranged))
    rates = RateSpec(
        two_axis_dps=listed if listed is not None or ranged is not None else (0.0,),
        two_axis_range_dps=ranged,
        directions=rt.number("directions", 8, 0, 3600, integer=True),
        roll_dps=rt.vector("roll_dps", None, [0.0], -1000.0, 1000.0),
    )
    rt.finish()

    st = _table(top, "stars")
    variants = st.get("variants", ["clean"])
    if not (isinstance(variants, list | tuple) and variants and all(v in VARIANTS for v in variants)):
        st.fail("variants", f"a non-empty list of {', '.join(map(repr, VARIANTS))}", variants)
    false_range = st.vector("false_mag_range", 2, [3.0, 6.0], -2.0, 14.0)
    if false_range[0] > false_range[1]:
        st.fail("false_mag_range", "[low, high] with low <= high", list(false_range))
    stars = StarsSpec(
        variants=tuple(variants),
        max_changed=st.number("max_changed", 2, 1, 100, integer=True),
        false_mag_range=false_range,
        position_sigma_px=st.number("position_sigma_px", 0.0, 0.0, 1000.0),
        magnitude_sigma=st.number("magnitude_sigma", 0.0, 0.0, 10.0),
    )
    st.finish()
    pr = _table(top, "pairs")
    pairs = PairsSpec(centroid_noise_px=pr.number("centroid_noise_px", 0.05, 0.0, 100.0))
    pr.finish()
    pa = _table(top, "patches")
    patches = PatchSpec(size_px=pa.number("size_px", 32, 4, 1024, integer=True))
    pa.finish()
    top.finish()
    spec = DatasetSpec(name, kind, scenario, scenario_text, samples, shard_size, seed, dict(overrides), randomize,
                       pointing, rates, stars, pairs, patches, source, input_size, readout, centre)
    try:  # the scenario with its fixed overrides and the per-sample ones at their low ends must load
        camera = spec.load_scenario({k: lo for k, (lo, _) in randomize.items()}).heads[0].camera
    except scenario_mod.ScenarioError as exc:
        raise DatasetError(f"{source}: scenario/overrides/randomize: {exc}") from exc
    if kind == "main_star" and input_size is None:
        input_size = default_input_size(camera.width, camera.height)
        spec = dataclasses.replace(spec, input_size=input_size)
    if input_size is not None and square_block(camera.width, camera.height, input_size) is None:
        top.fail("input_size", f"a size that head 0's {camera.width} x {camera.height} px frame area-resizes to in "
                 f"whole square blocks (its longer side over the size, dividing both sides)", input_size)
    return spec
