"""Command line: ``starenv scenarios``, ``starenv render SCENARIO``, ``starenv run SCENARIO``,
``starenv bench BENCH``, ``starenv view FILE``, ``starenv export FILE``, ``starenv recover FILE.mcap.partial``,
``starenv dataset SPEC`` and ``starenv train`` (torch, imported only when a command builds a learned agent or
trains one)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from starenv import metrics
from starenv import scenario as scenario_mod

TRUST_HELP = ("let agents ('module:Class' in the scenario, bench file or --agent) load from this module prefix outside "
              "starenv: its code will run (repeatable)")


MAX_SET_DEPTH = 16  # lists / tables nested in one --set value (a scenario's deepest value is a matrix: 2)


def _depth(value) -> int:
    """How deeply lists and dicts nest in a JSON value (0 for a scalar), found without recursion."""
    deepest, todo = 0, [(value, 0)]
    while todo:
        node, level = todo.pop()
        if isinstance(node, list | dict):
            deepest = max(deepest, level + 1)
            if deepest > MAX_SET_DEPTH:
                break
            todo.extend((child, level + 1) for child in (node.values() if isinstance(node, dict) else node))
    return deepest


def _overrides(pairs: list[str]) -> dict:
    """``key.path=VALUE`` pairs; VALUE is parsed as JSON when it can be (numbers, lists), else kept as a string."""
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise scenario_mod.ScenarioError(f"--set {pair!r}: expected KEY.PATH=VALUE, e.g. motion.rate_dps=[0,0,5]")
        too_deep = scenario_mod.ScenarioError(f"--set {key}: lists and tables nested more than {MAX_SET_DEPTH} deep")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
        except RecursionError:  # nested beyond the JSON parser's own limit
            raise too_deep from None
        if _depth(out[key]) > MAX_SET_DEPTH:
            raise too_deep
    return out


def printable(text, limit: int = 1000) -> str:
    """``text`` safe to print as one terminal line: control and format characters (escape sequences, line breaks,
    bidirectional overrides) shown as Python escapes, cut to ``limit`` characters.  For text read from files."""
    out = "".join(c if c.isprintable() else ascii(c)[1:-1] for c in str(text)[: limit + 1])
    return out if len(out) <= limit else out[:limit] + "..."


def cmd_scenarios(args) -> int:
    for name in scenario_mod.bundled_names():
        sc = scenario_mod.load(name)
        print(f"{name:24s} {sc.description}")
    return 0


def _bounded(name: str, value: int | None, low: int, high: int, why: str) -> None:
    """Refuse ``value`` outside ``[low, high]`` with a message naming the option and the reason for the bound."""
    if value is not None and not low <= value <= high:
        raise ValueError(f"{name} {value}: expected an integer in [{low}, {high}] ({why})")


def _header(sc, overrides: dict) -> None:
    """The scenario's name and description, and the overrides that change it (the description is the file's)."""
    print(printable(f"{sc.name}: {sc.description}"))
    if overrides:
        print("  overrides: " + ", ".join(f"{k}={json.dumps(v)}" for k, v in overrides.items())
              + " (the description above is the file's)")


def _progress(total: int, desc: str, quiet: bool):
    """A tqdm bar on stderr, shown on a terminal only (or never with ``--quiet``)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=True if quiet else None, leave=False)


def cmd_render(args) -> int:
    from starenv.sim.sensor import StarSensor

    overrides = _overrides(args.set)
    sc = scenario_mod.load(args.scenario, overrides)
    _bounded("--frame", args.frame, 0, sc.n_steps - 1, f"{sc.name} has {sc.n_steps} frames")
    _bounded("--seed", args.seed, 0, 2**63 - 1, "a non-negative seed")
    fmt = args.format
    out = Path(args.out or f"recordings/{sc.name}_frame{args.frame}.{fmt}")
    if out.suffix != f".{fmt}":
        raise ValueError(f"--out {str(out)!r}: expected a file name ending in .{fmt} for --format {fmt}")
    if fmt == "fits":
        from starenv.record.frames import _astropy

        _astropy()  # a missing extra fails before the frames are simulated
    sensor = StarSensor(sc)
    sensor.reset(sc.seed if args.seed is None else args.seed)
    with _progress(args.frame + 1, f"simulating to frame {args.frame}", args.quiet) as bar:
        for _ in range(args.frame + 1):
            frame = sensor.next_frame()
            bar.update()
    if fmt == "png":
        import cv2

        from starenv.view import mosaic, overlay

        images = [overlay(h.image, h.truth if args.truth else None, h.dropped) for h in frame.heads]
        out.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(out), cv2.cvtColor(mosaic(images), cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write {out}")
    else:
        from starenv.record.frames import write_fits, write_npz

        (write_fits if fmt == "fits" else write_npz)(frame, sc, out)
    stars = ", ".join(f"{hf.truth.catalog_id.size} stars" + (" (dropped)" if hf.dropped else "") for hf in frame.heads)
    rate_dps = math.degrees(float(np.linalg.norm(sc.trajectory.body_rate(frame.t_mid))))
    _header(sc, overrides)
    print(f"  frame {frame.index} at t = {frame.t_mid:.4f} s, |w| = {rate_dps:.3g} deg/s, {stars}")
    print(f"wrote {out}")
    return 0


def _agents(pairs: list[str]) -> dict[str, str]:
    out = {}
    for pair in pairs:
        role, sep, spec = pair.partition("=")
        if not sep:
            raise ValueError(f"--agent {pair!r}: expected ROLE=module:Class (or ROLE=none)")
        out[role] = None if spec.lower() == "none" else spec
    return out


class _Tick:
    """Episode observer that advances a progress bar once per step."""

    def __init__(self, bar):
        self.bar = bar

    def start(self, env, seed, pipeline) -> None:
        pass

    def step(self, log) -> None:
        self.bar.update()

    def close(self, error=None) -> None:
        pass


def cmd_run(args) -> int:
    from starenv.env import StarSensorEnv
    from starenv.episode import run_episode
    from starenv.scoring import summarize

    overrides = _overrides(args.set)
    env = StarSensorEnv(args.scenario, overrides)
    last = env.scenario.n_steps - 1
    _bounded("--steps", args.steps, 1, last, f"{env.scenario.name} has {env.scenario.n_steps} frames: "
             f"at most {last} scored steps")
    _bounded("--seed", args.seed, 0, 2**63 - 1, "a non-negative seed")
    pipeline = None
    if args.pipeline != "none":
        from starenv.agents.pipeline import Pipeline

        pipeline = Pipeline.for_scenario(env.scenario, _agents(args.agent), trust=tuple(args.trust))
    sc = env.scenario
    observers = []
    if args.record:
        from starenv.record.mcap import McapRecorder

        observers.append(McapRecorder(args.record))
    if args.rrd:
        from starenv.record.rerun import RerunRecorder, analytics_off

        analytics_off()

        observers.append(RerunRecorder(args.rrd))
    with _progress(last if args.steps is None else args.steps, sc.name, args.quiet) as bar:
        result = run_episode(env, pipeline, seed=args.seed, steps=args.steps, observers=[*observers, _Tick(bar)])
    for path in (args.record, args.rrd):
        if path:
            print(f"wrote {path}")
    records, wall, dropped, lost_at = result.records, result.wall_s, result.dropped, result.lost_at
    summary = summarize(records)
    _header(sc, overrides)
    print(f"  {len(records)} steps ({len(records) / sc.frame_rate_hz:.2f} s simulated) in {wall:.2f} s wall; "
          f"frames dropped per head: {dropped.tolist()}; lost rule fired at step: {lost_at}")
    if pipeline is None:
        print("  pipeline: none (every step unavailable)")
        return 0
    print("  pipeline: " + ", ".join(f"{r}={a}" for r, a in pipeline.describe().items() if a))
    _print_datasheet(sc, records)
    cross = [f"head{h}_cross_boresight_error_arcsec" for h in range(len(sc.heads))]
    for key in ("attitude_error_arcsec", *cross, "centroid_error_px_mean", "id_rate", "false_id_rate", "solved",
                "prediction_error_px_mean", "restoration_centroid_error_blurred_px", "restoration_centroid_error_px",
                "restoration_stars_before", "restoration_stars_after", "restoration_psnr_gain_db",
                "restoration_iterations"):
        if key in summary:
            v = summary[key]
            print(f"  {key:38s} median {v['median']:10.4g}  p95 {v['p95']:10.4g}  mean {v['mean']:10.4g} "
                  f"{metrics.lookup(key).unit}")
    for key in sorted(k for k in summary if k.startswith("latency_")):
        v = summary[key]
        print(f"  {key:38s} median {v['median']:10.3f}  p95 {v['p95']:10.3f} {metrics.lookup(key).unit}")
    return 0


def _axis_rows(n_heads: int) -> list[tuple[str, str]]:
    """(row label, record key) of the run summary's per-axis table: each head's camera axes, then the body's."""
    heads = [(f"head{h} {axis}", f"head{h}_error_{axis}_arcsec") for h in range(n_heads) for axis in ("x", "y", "roll")]
    return heads + [(f"body {axis}", f"body_error_{axis}_arcsec") for axis in ("x", "y", "z")]


def _print_datasheet(sc, records: list[dict]) -> None:
    """One episode's figures in a star-tracker datasheet's terms (``starenv.datasheet``): availability with its
    exact 95 % interval, acquisition and re-acquisition times, and per head (camera axes) and for the body the
    bias, NEA and total 3 sigma of each axis's signed error."""
    from starenv.datasheet import LEVEL, acquisition_times, binomial_interval, error_split

    within = sum(r.get("within_threshold") == 1.0 for r in records)
    low, high = binomial_interval(within, len(records))
    print(f"  availability ({sc.availability_threshold_arcsec.describe()}): {within / len(records):.3f} "
          f"({LEVEL:.0%} interval {low:.3f}-{high:.3f}, Clopper-Pearson over {len(records)} steps)")
    times = acquisition_times([r.get("fixed") == 1.0 for r in records], [r["time_s"] for r in records])
    reacquired = times["reacquisition"]
    first = f"{times['first'][0]:.3g} s after the first frame" if times["first"] else "never (no fix in the episode)"
    again = (f"{len(reacquired)}, median {np.median(reacquired):.3g} s, longest {max(reacquired):.3g} s" if reacquired
             else "none")
    print(f"  acquisition (to the first fix: solved and within the threshold): {first}; re-acquisitions after a "
          f"loss of fix: {again}")
    unit = metrics.lookup("body_error_x_arcsec").unit
    estimated = sum(r.get("body_error_x_arcsec") is not None for r in records)
    print(f"  per-axis error, {unit}, signed, over the {estimated} steps with an estimate (the ECSS-E-ST-60-20C split "
          "of starenv.datasheet):")
    print("    bias = mean; NEA = deviation of frame-to-frame differences / sqrt(2); total 3 sigma = 3 x RMS; a head's "
          "camera x, y (across its boresight) and roll, the body's x, y, z")
    print(f"    {'axis':12s}{'bias':>12s}{'NEA':>12s}{'total 3 sigma':>15s}")
    for label, key in _axis_rows(len(sc.heads)):
        split = error_split(np.array([math.nan if r.get(key) is None else r[key] for r in records]))
        print(f"    {label:12s}{split['bias']:12.4g}{split['nea']:12.4g}{split['total_3s']:15.4g}")


def cmd_view(args) -> int:
    import os
    import shutil
    import subprocess
    import tempfile

    from starenv.record.mcap import is_finished, read_metadata, recover, reproduce_command, run_info
    from starenv.record.rerun import analytics_off, mcap_to_rrd

    analytics_off()
    mcap_path = Path(args.recording)
    partial = mcap_path.name.endswith(".partial") or not is_finished(mcap_path)
    stem = mcap_path.with_name(mcap_path.name.removesuffix(".partial"))
    rrd = Path(args.rrd) if args.rrd else stem.with_suffix(".rrd")
    with tempfile.TemporaryDirectory() as tmp:
        if partial:  # an unfinished recording (a killed run): review what reached the file
            finished = Path(tmp) / stem.name
            steps = recover(mcap_path, finished)
            print(f"{mcap_path} is unfinished: reviewing its {steps} complete steps, up to its last complete chunk "
                  f"(starenv recover {mcap_path} writes them as a finished MCAP)")
            mcap_path = finished
        info = run_info(read_metadata(mcap_path), mcap_path)
        with _progress(info.get("steps"), "building the review", args.quiet) as bar:
            mcap_to_rrd(mcap_path, rrd, on_step=bar.update)
    # the file's text made printable; the reproduce command rebuilt from its checked numbers and agent names, never
    # the file's own text
    print(printable(f"{info['name']}, seed {info['seed']}: {info.get('steps', '?')} steps, "
                    f"{info.get('status', 'unfinished')}{': ' + info['error'] if info.get('error') else ''}"))
    if "steps" in info:
        command = reproduce_command("scenario.toml", info["seed"], info["steps"], info["agents"])
        print(printable(f"  reproduce: {command}  (starenv export {args.recording} --scenario scenario.toml writes "
                        f"it)"))
    print(printable(f"wrote {rrd}"))
    if not args.rrd and (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        viewer = shutil.which("rerun")
        if viewer is None:
            print("no `rerun` viewer on PATH (rerun-sdk installs it); open the .rrd with any Rerun 0.41 viewer")
        else:
            subprocess.Popen([viewer, str(rrd)])  # the viewer outlives this command
            print(f"opened the Rerun viewer on {rrd}")
    return 0


def cmd_export(args) -> int:
    from starenv.files import atomic_file
    from starenv.record.mcap import read_metadata, reproduce_command, run_info

    info = run_info(read_metadata(args.recording), args.recording)
    out = Path(args.scenario)
    if out.exists() and not out.is_symlink() and not args.force:
        raise FileExistsError(f"--scenario {out} exists; --force replaces it")
    with atomic_file(out, "w", encoding="utf-8", replace=args.force) as f:  # refuses a symbolic link, even forced
        f.write(info["toml"])
    print(printable(f"wrote {out} (the scenario of {args.recording}, overrides applied)"))
    if "steps" in info:  # rebuilt from the checked metadata, never the file's own text
        print(printable(f"  reproduce: {reproduce_command(str(out), info['seed'], info['steps'], info['agents'])}"))
    return 0


def cmd_recover(args) -> int:
    from starenv.record.mcap import recover

    partial = Path(args.partial)
    if not partial.name.endswith(".partial"):
        raise ValueError(f"recover: expected an unfinished recording FILE.mcap.partial, got {str(partial)!r}")
    out = Path(args.out) if args.out else partial.with_name(partial.name.removesuffix(".partial"))
    if (out.exists() or out.is_symlink()) and not args.force:
        raise ValueError(f"recover: {out} exists; name another output with --out, or replace it with --force")
    steps = recover(partial, out, replace=args.force)
    print(printable(f"wrote {out}: {steps} complete steps recovered from {partial}"))
    return 0


def cmd_bench(args) -> int:
    import importlib.util

    from starenv.bench.report import write_report
    from starenv.bench.runner import check_writable, run_bench
    from starenv.bench.spec import load_bench

    for module in ("tqdm", "matplotlib"):
        if importlib.util.find_spec(module) is None:  # fail before the runs, not at the report after them
            raise ValueError(f"starenv bench needs {module} (the 'report' extra: pip install 'starenv[report]')")
    bench = load_bench(args.bench, trust=tuple(args.trust), seeds=args.seeds)
    check_writable(Path(args.out))
    if args.jobs is not None and args.jobs < 1:
        raise ValueError(f"--jobs: expected an integer >= 1, got {args.jobs}")
    print(f"{bench.name}: {len(bench.runs)} runs, {sum(r.steps for r in bench.runs)} steps, from {bench.source}")
    files = run_bench(bench, args.out, jobs=args.jobs, use_ray=args.ray is not None, ray_address=args.ray or None,
                      progress=not args.quiet)
    # the report's figures fork processes: not from a driver whose Ray threads are running
    report = write_report(bench, files, Path(args.out), jobs=1 if args.ray is not None else args.jobs)
    print(f"report: {report}")
    return 0


def cmd_dataset(args) -> int:
    from starenv.datasets import build_dataset, load_spec

    if args.jobs is not None and args.jobs < 1:
        raise ValueError(f"--jobs: expected an integer >= 1, got {args.jobs}")
    spec = load_spec(args.spec)
    print(f"{spec.name}: {spec.kind}, {spec.samples} samples in {spec.n_shards} shards, spec {spec.digest[:12]}")
    build_dataset(spec, args.out, jobs=args.jobs, use_ray=args.ray is not None, ray_address=args.ray or None,
                  progress=not args.quiet)
    print(f"dataset: {args.out}")
    return 0


# Errors that an input (a file, an option, a folder) causes: one line, exit status 2.
INPUT_ERRORS = (scenario_mod.ScenarioError, ValueError, OSError, ModuleNotFoundError, RecursionError, MemoryError)


def _fail(prog: str, exc: BaseException, debug: bool) -> int:
    """Report ``exc`` on one line (the traceback first with ``--debug``); the exit status."""
    if debug:
        import traceback

        traceback.print_exception(exc)
    if isinstance(exc, INPUT_ERRORS):
        text = f"nested too deeply ({exc})" if isinstance(exc, RecursionError) else str(exc)
        print(f"{prog}: error: {printable(text)}", file=sys.stderr)
        return 2
    hint = "" if debug else " (starenv --debug ... shows the traceback)"
    print(f"{prog}: error: unexpected {type(exc).__name__}: {printable(exc, 300)}{hint}", file=sys.stderr)
    return 1


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    if argv[:1] == ["train"]:  # its own parser, in a module that imports torch (as the learned agents' modules do)
        from starenv.agents.identify.network_train import main as train_main

        try:
            return train_main(argv[1:])
        except Exception as exc:  # noqa: BLE001  (one line; --debug shows the traceback)
            return _fail("starenv train", exc, debug)
    import starenv

    parser = argparse.ArgumentParser(prog="starenv", description="Star sensor simulator under dynamic conditions")
    parser.add_argument("--version", action="version", version=f"starenv {starenv.__version__}")
    parser.add_argument("--debug", action="store_true", help="on an error, print its traceback too (any position)")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("scenarios", help="list the bundled scenarios").set_defaults(fn=cmd_scenarios)
    p = sub.add_parser("render", help="render one frame of a scenario: a PNG with truth, 16-bit FITS or npz")
    p.add_argument("scenario", help="bundled scenario name or path to a .toml file")
    p.add_argument("--frame", type=int, default=0, help="frame index (default 0)")
    p.add_argument("--seed", type=int, default=None, help="seed (default: the scenario's)")
    p.add_argument("--out", default=None, help="output file (default recordings/NAME_frameN.FORMAT)")
    p.add_argument("--no-truth", dest="truth", action="store_false", help="do not draw the true star trails (png)")
    p.add_argument("--format", choices=("png", "fits", "npz"), default="png",
                   help="png: 8-bit display stretch with truth; fits: raw 16-bit counts per head with a truth WCS "
                        "(starenv[fits]); npz: raw frames with their truth")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE", help="override a scenario key")
    p.set_defaults(fn=cmd_render)
    p = sub.add_parser("run", help="run an episode of a scenario and print a summary")
    p.add_argument("scenario", help="bundled scenario name or path to a .toml file")
    p.add_argument("--steps", type=int, default=None, help="steps to run (default: the whole scenario)")
    p.add_argument("--seed", type=int, default=None, help="seed (default: the scenario's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE", help="override a scenario key")
    p.add_argument("--pipeline", choices=("default", "none"), default="default",
                   help="the built-in classical pipeline (default) or none")
    p.add_argument("--agent", action="append", default=[], metavar="ROLE=module:Class",
                   help="replace one agent of the pipeline (roles: predictor, deblurrer, detector, corrector, "
                        "identifier, solver; ROLE=none empties an optional role)")
    p.add_argument("--trust", action="append", default=[], metavar="MODULE_PREFIX", help=TRUST_HELP)
    p.add_argument("--record", default=None, metavar="FILE.mcap",
                   help="record the episode to an MCAP file (Foxglove schemas; open with Foxglove or starenv view)")
    p.add_argument("--rrd", default=None, metavar="FILE.rrd", help="record the episode to a Rerun .rrd file")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(fn=cmd_run)
    p = sub.add_parser("export", help="write the scenario a recording was made from (what its reproduce command runs)")
    p.add_argument("recording", help="an MCAP file written by starenv run --record")
    p.add_argument("--scenario", default="scenario.toml", metavar="FILE.toml",
                   help="where to write the scenario (default scenario.toml, the name the reproduce command uses)")
    p.add_argument("--force", action="store_true", help="replace an existing --scenario file")
    p.set_defaults(fn=cmd_export)
    p = sub.add_parser("view", help="review an MCAP recording in Rerun (opens the viewer when a display exists)")
    p.add_argument("recording", help="an MCAP file written by starenv run --record (or the FILE.mcap.partial of a "
                                     "killed run: its complete steps are reviewed)")
    p.add_argument("--rrd", default=None, metavar="FILE.rrd",
                   help="write the Rerun recording here and do not open the viewer (default: next to the MCAP file)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(fn=cmd_view)
    p = sub.add_parser("recover", help="turn the .mcap.partial of a killed run into a finished MCAP of its complete "
                                       "steps")
    p.add_argument("partial", help="FILE.mcap.partial")
    p.add_argument("--out", default=None, metavar="FILE.mcap", help="output (default: FILE.mcap, if it does not exist)")
    p.add_argument("--force", action="store_true", help="replace an existing output")
    p.set_defaults(fn=cmd_recover)
    p = sub.add_parser("bench", help="run a benchmark (scenarios x pipelines x seeds, sweeps) and write a report")
    p.add_argument("bench", help="bench file (.toml) or bundled bench name (e.g. bundled)")
    p.add_argument("--out", required=True,
                   help="output folder (runs/, summary tables, datasheet.csv, plots/, report.md)")
    p.add_argument("--jobs", type=int, default=None,
                   help="local worker processes for the runs and the report's figures (default: the CPU count)")
    p.add_argument("--seeds", type=int, default=None, metavar="N",
                   help="run every group with the seeds 0 .. N-1 (N >= 1), replacing the file's seeds: more runs per "
                        "case, narrower 95 %% intervals")
    p.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run on a Ray cluster at ADDRESS (no ADDRESS: a local Ray instance)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--trust", action="append", default=[], metavar="MODULE_PREFIX", help=TRUST_HELP)
    p.set_defaults(fn=cmd_bench)
    p = sub.add_parser("dataset", help="generate a learning dataset (shards of simulated samples) from a spec")
    p.add_argument("spec", help="dataset spec (.toml), see starenv/datasets/spec.py")
    p.add_argument("--out", required=True, help="output folder (dataset.json and shard-NNNNN.npz)")
    p.add_argument("--jobs", type=int, default=None, help="local worker processes (default: the CPU count)")
    p.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="build on a Ray cluster at ADDRESS (no ADDRESS: a local Ray instance)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(fn=cmd_dataset)
    sub.add_parser("train", help="train paper 002's network on a dataset (options: starenv train --help)")
    args = parser.parse_args(argv)
    try:
        return args.fn(args)
    except Exception as exc:  # noqa: BLE001  (one line; --debug shows the traceback)
        return _fail("starenv", exc, debug)


if __name__ == "__main__":
    sys.exit(main())
