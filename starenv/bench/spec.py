"""Benchmark files: scenarios x agent pipelines x seeds, with one scenario key swept per run group.

A bench file is TOML (bundled ones are package data in ``scenarios/benches/``, named without ``.toml``)::

    name = "my-bench"                 # optional, defaults to the file's stem
    description = "..."               # optional
    seeds = [0, 1]                    # default seeds of every group (default: each scenario's own seed); a count
                                      # N >= 1 is the seeds 0 .. N-1 (seeds = 8: [0, 1, ..., 7])
    steps = 30                        # default scored steps per run (default: the whole scenario)
    recordings = false                # true: one MCAP per run (starenv.record.mcap:McapRecorder); a list of seeds:
                                      # only the runs of those seeds (recordings = [0])

    [pipelines.svd]                   # a named pipeline: the scenario's own [pipeline] with these roles replaced
    solver = "starenv.agents.solve:SvdSolver"          # role = "module:Class" or "none"
    catalog_mag_limit = 7.0                            # optional onboard catalog limit
    [pipelines.svd.options.solver]                     # optional constructor options per role

    [[runs]]                          # a run group: one scenario, its pipelines, seeds and an optional sweep
    scenario = "paper_002"            # bundled name, or a path (relative to the bench file or the working folder)
    pipelines = ["scenario", "lost_in_space", "svd"]   # names from [pipelines] or the built-in presets
    set = { "gyro.arw_deg_rthr" = 0.02 }              # optional fixed overrides (dotted scenario keys)
    sweep = { key = "motion.rate_dps", axis = [1, 1, 1], start = 0, stop = 30, step = 5 }
    # or  sweep = { key = "motion.rate_dps", axis = [1, 0, 0], values = [0, 5, 10] }
    # or  sweep = { key = "drops.probability", values = [0.0, 0.1, 0.3] }   (no axis: each value used as is)
    seeds = [3]                       # optional, replaces the default seeds (a list, or a count N: 0 .. N-1)
    steps = 50                        # optional, replaces the default steps
    recordings = false                # optional: do not record this group's runs (default: as the bench says)

With ``axis``, a swept value is a magnitude along the unit vector of ``axis`` (a rate of 10 deg/s about [1, 1, 1]
overrides ``motion.rate_dps`` with ``10 / sqrt(3) * [1, 1, 1]``); ranges include ``stop``.

``seeds`` scales the Monte Carlo: every figure of the report carries a 95 % interval over a case's runs (its seeds;
``starenv.datasheet``), so more seeds give narrower intervals.  ``parse_bench(..., seeds=N)`` (``starenv bench
--seeds N``) replaces every ``seeds`` of the file, the top level's and each group's, with 0 .. N-1.

Built-in pipelines (``PRESETS``): ``scenario`` (the scenario's own ``[pipeline]``), ``lost_in_space`` (the same
with the lost-in-space identifier, no tracking) and ``tracking`` (the same with the tracking identifier).

A bench file is data: it names scenarios, keys and agent classes, and nothing else is imported or called.  Agents
named by a ``"module:Class"`` string load only from ``starenv`` or from module prefixes the caller trusts (``trust=``
here, ``--trust`` on the command line; a file cannot grant trust itself), and only classes that implement their
role's protocol are constructed (:func:`starenv.agents.pipeline.load_agent`).

Loading validates everything before any run starts: unknown keys, missing scenarios, every scenario x sweep value
loaded with its overrides, every pipeline built once per scenario.  Errors are :class:`BenchError` naming the file,
the key path and the expected form.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from starenv import scenario as scenario_mod
from starenv.config import ConfigError, Table, is_number, parse_toml

BENCH_DIR = Path(str(resources.files("starenv.scenarios").joinpath("benches")))  # package data: scenarios/benches/
MCAP_RECORDER = "starenv.record.mcap:McapRecorder"
PRESETS: dict[str, dict[str, str]] = {
    "scenario": {},
    "lost_in_space": {"identifier": "starenv.agents.identify:LostInSpaceIdentifier"},
    "tracking": {"identifier": "starenv.agents.identify:TrackingIdentifier"},
}
MAX_STEPS = 10**7  # steps of one run: a bench's scenarios may not run longer than their own frames anyway
FORMAT = 1  # bumps when the meaning of a run's identity changes


class BenchError(ConfigError):
    """A bench file that does not describe a valid benchmark."""


@dataclass(frozen=True)
class NamedPipeline(scenario_mod.PipelineSpec):
    """A bench pipeline: the scenario's pipeline record (agents, options, catalogue limit replacing the scenario's
    own) plus the name the bench file gives it."""

    name: str = field(kw_only=True)

    def as_dict(self) -> dict:
        return {"name": self.name, "agents": self.agents, "options": self.options,
                "catalog_mag_limit": self.catalog_mag_limit}

    def build(self, scenario, trust: tuple[str, ...] = ()):
        """The ``Pipeline`` for a loaded scenario (raises ValueError for an unloadable, untrusted agent or a wrong
        protocol; ``trust``: module prefixes outside ``starenv`` agents may come from)."""
        from starenv.agents.pipeline import Pipeline

        return Pipeline.from_spec(scenario.pipeline.replaced_by(self), trust)


@dataclass(frozen=True)
class Sweep:
    """One swept scenario key: ``values`` (magnitudes along the unit ``axis`` when given, else used as is)."""

    key: str
    values: tuple
    axis: tuple[float, ...] | None = None

    def override(self, value: Any) -> Any:
        if self.axis is None:
            return value
        norm = math.sqrt(sum(a * a for a in self.axis))
        return [value * a / norm for a in self.axis]


@dataclass(frozen=True)
class RunSpec:
    """One run: a pure function of the scenario file's text, the overrides, the pipeline, the seed and the steps."""

    scenario: str  # the scenario's name
    scenario_file: str
    scenario_text: str
    overrides: dict
    sweep_key: str | None
    sweep_value: Any
    sweep_axis: tuple[float, ...] | None
    pipeline: NamedPipeline
    seed: int
    steps: int
    record: bool = True  # whether the bench's recorder (if any) records this run; not part of its identity
    trust: tuple[str, ...] = ()  # module prefixes its agents may come from (the caller's, never the file's)
    files_sha256: tuple[tuple[str, str], ...] = ()  # (dotted key, SHA-256) of each data file the scenario names

    def identity(self) -> dict:
        """What the run's results depend on (the scenario by the SHA-256 of its text and of each data file it
        names: editing a star catalogue or attitude file makes a new run, never a stale resumed one)."""
        files = {"files_sha256": dict(self.files_sha256)} if self.files_sha256 else {}
        return {**files,
            "format": FORMAT,
            "scenario": self.scenario,
            "scenario_sha256": hashlib.sha256(self.scenario_text.encode()).hexdigest(),
            "overrides": self.overrides,
            "sweep": None if self.sweep_key is None else {"key": self.sweep_key, "value": self.sweep_value,
                                                          "axis": self.sweep_axis},
            "pipeline": self.pipeline.as_dict(),
            "seed": self.seed,
            "steps": self.steps,
        }

    @property
    def digest(self) -> str:
        text = json.dumps(self.identity(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()

    @property
    def run_id(self) -> str:
        """File-name-safe id: scenario, pipeline, seed and the first 16 hex digits of the identity's hash."""
        return f"{self.scenario}-{self.pipeline.name}-s{self.seed}-{self.digest[:16]}"

    def scenario_data(self) -> dict:
        data = tomllib.loads(self.scenario_text)
        data.setdefault("name", self.scenario)
        return data

    def load_scenario(self):
        """The run's scenario, its data files read from the scenario file's folder; a data file whose bytes changed
        since the bench was loaded is refused (the run's identity names the bytes it was loaded with)."""
        scenario = scenario_mod.load(self.scenario_data(), self.overrides, base=Path(self.scenario_file).parent)
        if self.files_sha256:
            now, paths = scenario_mod.file_digests(scenario), scenario_mod.named_files(scenario.data)
            for key, digest in self.files_sha256:
                if now.get(key) != digest:
                    raise BenchError(f"{self.scenario_file}: {key}: the file {paths.get(key)} changed since the bench "
                                     "was loaded; load the bench again")
        return scenario


@dataclass
class Bench:
    """A validated benchmark: its runs in file order and the recorder (``MCAP_RECORDER``) or None."""

    name: str
    description: str
    source: str
    runs: list[RunSpec]
    recorder: str | None = None
    recorded_seeds: tuple[int, ...] | None = None  # the seeds whose runs are recorded (None: every seed)


def resolve_bench(bench: str | Path) -> Path:
    """Path of a bench file given by path or by the name of a bundled one (``bundled``)."""
    path = Path(bench)
    if path.suffix != ".toml" and (BENCH_DIR / f"{bench}.toml").is_file():
        return BENCH_DIR / f"{bench}.toml"
    if path.is_file():
        return path
    names = ", ".join(sorted(p.stem for p in BENCH_DIR.glob("*.toml"))) or "none"
    raise BenchError(f"bench {str(bench)!r} is neither a file nor a bundled bench (bundled: {names})")


def _sweep(tbl: Table) -> Sweep:
    key = tbl.get("key")
    if not isinstance(key, str) or not key or not all(key.split(".")):
        tbl.fail("key", "a dotted scenario key path like 'motion.rate_dps'", key)
    axis = tbl.get("axis")
    if axis is not None:
        if not (isinstance(axis, list) and axis and all(is_number(a) for a in axis) and any(a != 0 for a in axis)):
            tbl.fail("axis", "a non-zero list of numbers, e.g. [1, 0, 0]", axis)
        axis = tuple(float(a) for a in axis)
    values = tbl.get("values")
    start, stop, step = tbl.get("start"), tbl.get("stop"), tbl.get("step")
    if values is not None and (start, stop, step) != (None, None, None):
        tbl.fail("values", "either values = [...] or start / stop / step, not both", values)
    if values is None:
        for k, v in (("start", start), ("stop", stop), ("step", step)):
            if not is_number(v):
                tbl.fail(k, "a number (or give values = [...] instead)", v)
        if step <= 0 or stop < start:
            tbl.fail("step", f"a step > 0 with stop >= start (start = {start}, stop = {stop})", step)
        n = int(math.floor((stop - start) / step + 1e-9)) + 1
        if n > 10000:
            tbl.fail("step", "at most 10000 values between start and stop", step)
        values = [round(start + i * step, 12) for i in range(n)]
    elif not isinstance(values, list) or not values:
        tbl.fail("values", "a non-empty list of values", values)
    if axis is not None and not all(is_number(v) for v in values):
        tbl.fail("values", "numbers (magnitudes along axis)", values)
    if len({json.dumps(v, sort_keys=True) for v in values}) != len(values):
        tbl.fail("values", "distinct values", values)
    tbl.finish()
    return Sweep(key, tuple(values), axis)


def _named_pipeline(name: str, tbl: Table) -> NamedPipeline:
    spec = scenario_mod.parse_pipeline(tbl)
    return NamedPipeline(spec.agents, spec.options, spec.catalog_mag_limit, name=name)


SEEDS_EXPECTED = "a non-empty list of integers >= 0, or a count N >= 1 (the seeds 0 .. N-1)"


def seed_count(n: Any, what: str) -> list[int]:
    """The seeds 0 .. n-1 of a count ``n`` (an integer >= 1); BenchError naming ``what`` otherwise."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise BenchError(f"{what}: expected a count N >= 1 (the seeds 0 .. N-1), got {n!r}")
    return list(range(n))


def _seeds(tbl: Table, default: Any) -> list[int] | None:
    """A table's ``seeds``: a list of integers >= 0 or a count (``default`` when absent)."""
    v = tbl.get("seeds", default)
    if v is default:
        return v
    if isinstance(v, int) and not isinstance(v, bool):
        if v < 1:
            tbl.fail("seeds", SEEDS_EXPECTED, v)
        return list(range(v))
    if not (isinstance(v, list) and v and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in v)):
        tbl.fail("seeds", SEEDS_EXPECTED, v)
    return v


def _recorder(value: Any, source: str) -> tuple[str | None, tuple[int, ...] | None]:
    """The recorder and the seeds it records (None: all) of the top level's ``recordings``."""
    if isinstance(value, bool):
        return (MCAP_RECORDER if value else None), None
    if isinstance(value, list) and value and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0
                                                 for x in value):
        return MCAP_RECORDER, tuple(value)
    raise BenchError(f"{source}: recordings: expected true, false or a non-empty list of seeds (only their runs "
                     f"recorded), got {value!r}")


def _scenario_path(name: Any, bench_dir: Path, where: str, source: str) -> Path:
    if not isinstance(name, str) or not name:
        raise BenchError(f"{source}: {where}: expected a bundled scenario name or a .toml path, got {name!r}")
    for candidate in (name, bench_dir / name):
        try:
            return scenario_mod.resolve(candidate)
        except scenario_mod.ScenarioError:
            continue
    names = ", ".join(scenario_mod.bundled_names())
    raise BenchError(f"{source}: {where}: scenario {name!r} is neither a file nor a bundled scenario ({names})")


def parse_bench(text: str, source: str = "<bench>", bench_dir: Path | None = None, check: bool = True,
                trust: tuple[str, ...] = (), seeds: int | None = None) -> Bench:
    """Parse and validate bench TOML ``text``; with ``check`` every scenario x sweep value is loaded with its
    overrides and every pipeline is built once per scenario (an agent that does not load fails here).  ``trust``:
    module prefixes outside ``starenv`` whose agent classes the file may name (checked whatever ``check`` says).
    ``seeds``: a count N >= 1 whose seeds 0 .. N-1 replace every ``seeds`` of the file (``--seeds``)."""
    from starenv.agents.pipeline import check_trust

    bench_dir = Path(".") if bench_dir is None else bench_dir
    trust = check_trust(trust)
    forced_seeds = None if seeds is None else seed_count(seeds, "--seeds")
    data = parse_toml(text, source, BenchError)
    top = Table(data, "", source, BenchError)
    name = top.get("name", Path(source).stem)
    description = top.get("description", "")
    for k, v in (("name", name), ("description", description)):
        if not isinstance(v, str):
            top.fail(k, "a string", v)
    default_seeds = _seeds(top, None)
    default_steps = top.number("steps", None, low=1, high=MAX_STEPS, integer=True)
    recorder, recorded_seeds = _recorder(top.get("recordings", False), source)
    pipelines = {}
    ptbl = top.get("pipelines", {})
    pt = Table(ptbl, "pipelines", source, BenchError)
    for pname in ptbl:
        if pname in PRESETS:
            raise BenchError(f"{source}: pipelines.{pname}: {pname!r} is a built-in preset name; pick another name")
        if not pname.replace("_", "").replace("-", "").isalnum():
            raise BenchError(f"{source}: pipelines.{pname}: expected a name of letters, digits, '_' or '-'")
        pipelines[pname] = _named_pipeline(pname, Table(pt.get(pname), f"pipelines.{pname}", source, BenchError))
    for pname, agents in PRESETS.items():
        pipelines[pname] = NamedPipeline(dict(agents), name=pname)
    groups = top.get("runs")
    if not isinstance(groups, list) or not groups:
        top.fail("runs", "a non-empty array of tables ([[runs]])", groups)
    top.finish()

    runs: list[RunSpec] = []
    for gi, group in enumerate(groups):
        g = Table(group, f"runs.{gi}", source, BenchError)
        path = _scenario_path(g.get("scenario"), bench_dir, g.where("scenario"), source)
        text_sc = path.read_text(encoding="utf-8")
        sc_data = parse_toml(text_sc, f"{source}: {g.where('scenario')}: {path}", BenchError)
        sc_name = sc_data.get("name", path.stem)
        if not isinstance(sc_name, str) or not sc_name.replace("_", "").replace("-", "").isalnum():
            raise BenchError(f"{source}: {g.where('scenario')}: {path}: name must be letters, digits, '_' or '-'")
        names = g.get("pipelines", ["scenario"])
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            g.fail("pipelines", "a non-empty list of pipeline names", names)
        for n in names:
            if n not in pipelines:
                g.fail("pipelines", f"names from [pipelines] or the presets ({', '.join(pipelines)})", n)
        fixed = g.get("set", {})
        if not isinstance(fixed, dict):
            g.fail("set", "a table of dotted scenario keys, e.g. { \"motion.rate_dps\" = [0, 0, 5] }", fixed)
        sweep_tbl = g.get("sweep")
        sweep = None if sweep_tbl is None else _sweep(Table(sweep_tbl, g.where("sweep"), source, BenchError))
        seeds = _seeds(g, default_seeds)  # read and checked even where --seeds replaces it
        if forced_seeds is not None:
            seeds = forced_seeds
        steps = g.number("steps", default_steps, low=1, high=MAX_STEPS, integer=True)
        record = g.get("recordings", True)
        if not isinstance(record, bool):
            g.fail("recordings", "true or false (false: this group's runs are not recorded)", record)
        g.finish()
        for value in sweep.values if sweep else (None,):
            overrides = dict(fixed)
            if sweep is not None:
                overrides[sweep.key] = sweep.override(value)
            where = g.where("sweep") if sweep is not None else g.where("set")
            scenario = None
            if check or seeds is None or steps is None or _names_files(text_sc, overrides):
                try:
                    scenario = scenario_mod.load(path, overrides)
                    digests = tuple(scenario_mod.file_digests(scenario).items())
                except scenario_mod.ScenarioError as exc:
                    shown = f" = {value!r}" if sweep is not None else ""
                    raise BenchError(f"{source}: {where}{shown}: {exc}") from exc
            if scenario is not None and steps is not None and steps > scenario.n_steps - 1:
                g.fail("steps", f"at most {scenario.n_steps - 1} (the frames of {sc_name} less one)", steps)
            if check and value == (sweep.values[0] if sweep else None):
                for n in dict.fromkeys(names):
                    try:
                        pipelines[n].build(scenario, trust)
                    except ValueError as exc:
                        origin = f"pipelines.{n}" if n not in PRESETS else f"{g.where('pipelines')} ({n})"
                        raise BenchError(f"{source}: {origin}: {exc}") from exc
            for n in names:
                for seed in (seeds if seeds is not None else [scenario.seed]):
                    runs.append(RunSpec(
                        sc_name, str(path), text_sc, overrides, sweep.key if sweep else None, value,
                        sweep.axis if sweep else None, pipelines[n], int(seed),
                        int(steps if steps is not None else scenario.n_steps - 1),
                        record and (recorded_seeds is None or int(seed) in recorded_seeds), trust,
                        digests if scenario is not None else (),
                    ))
    ids = {}
    for r in runs:
        if r.run_id in ids:
            raise BenchError(f"{source}: runs: the same run is listed twice ({r.scenario}, pipeline {r.pipeline.name},"
                             f" seed {r.seed}, overrides {r.overrides})")
        ids[r.run_id] = r
    return Bench(name, description, source, runs, recorder, recorded_seeds)


def _names_files(text: str, overrides: dict) -> bool:
    """Whether a scenario's text or overrides may name a data file (then it is loaded to hash them)."""
    keys = "|".join(scenario_mod.FILE_KEYS)
    return bool(re.search(rf"(^|[{{,\s])({keys})\s*=", text, re.MULTILINE)) or any(
        str(k).rsplit(".", 1)[-1] in scenario_mod.FILE_KEYS for k in overrides)


def load_bench(bench: str | Path, check: bool = True, trust: tuple[str, ...] = (), seeds: int | None = None) -> Bench:
    """Load a bench file by path or bundled name (see :func:`parse_bench`)."""
    path = resolve_bench(bench)
    return parse_bench(path.read_text(encoding="utf-8"), str(path), path.parent, check, trust, seeds)
