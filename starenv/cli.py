"""Command line: ``starenv scenarios [--show NAME]``, ``starenv new`` (a scenario from a sensor's datasheet),
``starenv render SCENARIO``, ``starenv run SCENARIO``,
``starenv bench BENCH``, ``starenv solve FILE...``, ``starenv calibrate FILE...`` (a camera's twin from its frames),
``starenv compare FILE...`` (the frames beside the twin), ``starenv view FILE``, ``starenv export FILE``,
``starenv recover FILE.mcap.partial``, ``starenv dataset SPEC`` and ``starenv train`` (torch, imported only when a
command builds a learned agent or trains one)."""

from __future__ import annotations

import argparse
import json
import math
import os
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
    if args.show is not None:  # the file's text, comments included, to start a scenario from
        names = scenario_mod.bundled_names()
        if args.show not in names:
            raise ValueError(f"--show {args.show!r}: not a bundled scenario ({', '.join(names)})")
        sys.stdout.write((scenario_mod.SCENARIO_DIR / f"{args.show}.toml").read_text(encoding="utf-8"))
        return 0
    for name in scenario_mod.bundled_names():
        sc = scenario_mod.load(name)
        print(f"{name:24s} {sc.description}")
    return 0


def cmd_new(args) -> int:
    from starenv.config import parse_toml
    from starenv.files import atomic_file
    from starenv.sensor_sheet import SensorSheet, scenario_text

    given = {field: value for field, value in vars(args).items() if field in NEW_FIELDS and value is not None}
    if args.resolution is not None:
        given["width"], given["height"] = args.resolution
    missing = [flag for flag, field in (("--resolution", "width"), ("--pixel-um", "pixel_pitch_um"),
                                        ("--aperture-mm", "aperture_mm"), ("--exposure-ms", "exposure_ms"),
                                        ("--rate-hz", "frame_rate_hz")) if field not in given]
    if missing:
        raise ValueError(f"new: give {', '.join(missing)} (from the sensor's datasheet)")
    text = scenario_text(SensorSheet(**given), frozenset(given))
    try:
        scenario_mod.load(parse_toml(text, "<new>", scenario_mod.ScenarioError))
    except scenario_mod.ScenarioError as exc:  # values each in range whose scenario is not (e.g. the f-number)
        raise ValueError(f"new: these datasheet values give no valid scenario: {exc}") from exc
    if args.out is None:
        sys.stdout.write(text)
        return 0
    out = Path(args.out)
    if out.exists() and not out.is_symlink() and not args.force:
        raise FileExistsError(f"--out {out} exists; --force replaces it")
    with atomic_file(out, "w", encoding="utf-8", replace=args.force) as f:  # refuses a symbolic link, even forced
        f.write(text)
    print(printable(f"wrote {out}: run it with starenv run {out}"))
    return 0


# ``starenv new`` options -> SensorSheet fields (``--resolution W H`` gives width and height)
NEW_FIELDS = ("fov_deg", "focal_length_mm", "pixel_pitch_um", "aperture_mm", "exposure_ms", "frame_rate_hz",
              "read_noise_e", "dark_current_e_per_s", "full_well_e", "gain_e_per_dn", "quantum_efficiency",
              "transmission", "adc_bits", "psf_sigma_px", "snr", "sky_mag_per_arcsec2", "duration_s", "name")


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


def _finished(recording: Path, tmp: str) -> tuple[Path, int | None]:
    """A finished MCAP to read ``recording`` from: the file itself (and None), or, for an unfinished one (a killed
    run's ``.partial``), its complete steps recovered into the folder ``tmp`` (and their count)."""
    from starenv.record.mcap import is_finished, recover

    if not recording.name.endswith(".partial") and is_finished(recording):
        return recording, None
    finished = Path(tmp) / recording.name.removesuffix(".partial")
    return finished, recover(recording, finished)


def cmd_view(args) -> int:
    import shutil
    import subprocess
    import tempfile

    from starenv.record.mcap import read_metadata, reproduce_command, run_info
    from starenv.record.rerun import analytics_off, mcap_to_rrd

    analytics_off()
    recording = Path(args.recording)
    stem = recording.with_name(recording.name.removesuffix(".partial"))
    rrd = Path(args.rrd) if args.rrd else stem.with_suffix(".rrd")
    with tempfile.TemporaryDirectory() as tmp:
        mcap_path, steps = _finished(recording, tmp)
        if steps is not None:  # an unfinished recording (a killed run): review what reached the file
            print(printable(f"{recording} is unfinished: reviewing its {steps} complete steps, up to its last "
                            f"complete chunk (starenv recover {recording} writes them as a finished MCAP)"))
        info = run_info(read_metadata(mcap_path), recording)  # errors name the user's file, not the copy
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


def _export_aem(args) -> int:
    """``export --format aem``: the run's estimated attitude to ``--out``, its truth beside it
    (``starenv.record.aem``)."""
    import tempfile

    from starenv.files import atomic_file
    from starenv.record.aem import recording_aems, truth_path

    if not args.out:
        raise ValueError("export --format aem: name the estimate's file with --out FILE.aem (FILE.xml for XML)")
    out = Path(args.out)
    outputs = (out, truth_path(out))
    for path in outputs:
        if path.exists() and not path.is_symlink() and not args.force:
            raise FileExistsError(f"{path} exists; --force replaces it")
    with tempfile.TemporaryDirectory() as tmp:  # an unfinished recording: its complete steps
        estimate, truth, estimated, steps = recording_aems(_finished(Path(args.recording), tmp)[0],
                                                           "xml" if out.suffix.lower() == ".xml" else "kvn")
    for path, text in zip(outputs, (estimate, truth), strict=True):
        with atomic_file(path, "w", encoding="utf-8", replace=args.force) as f:  # refuses a symbolic link
            f.write(text)
    print(printable(f"wrote {outputs[0]} (the estimated attitude of {estimated} of {steps} steps, CCSDS AEM) and "
                    f"{outputs[1]} (the truth at every step)"))
    return 0


def cmd_export(args) -> int:
    import tempfile

    from starenv.files import atomic_file
    from starenv.record.mcap import read_metadata, reproduce_command, run_info

    if args.format == "aem":
        return _export_aem(args)
    with tempfile.TemporaryDirectory() as tmp:  # an unfinished recording: the metadata of its complete steps
        info = run_info(read_metadata(_finished(Path(args.recording), tmp)[0]), args.recording)
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


def _solved_field(solution) -> str:
    """The field a solved frame used (when the search found it) and the one fitted to its stars, for the log line."""
    found = f"field found {solution.fov_deg:.4f} deg, " if solution.fov_searched else ""
    if solution.fov_fitted_deg is None:
        return found
    return found + f"fitted {solution.fov_fitted_deg:.4f} +- {solution.fov_fitted_sigma_deg:.4f} deg, "


def cmd_solve(args) -> int:
    from starenv.agents.pipeline import Pipeline
    from starenv.files import atomic_file
    from starenv.real import FrameSolver, camera_from_fov, read_frame
    from starenv.real.solve import FOV_TOLERANCE, LOST_IN_SPACE, write_wcs_fits

    camera_file = None
    if args.camera is not None:
        camera_file = scenario_mod.load_camera(args.camera)
    elif not 0.0 < args.fov < 180.0:
        raise ValueError(f"--fov {args.fov}: expected the field across the image columns in degrees, in (0, 180)")
    fov_tolerance = FOV_TOLERANCE if args.fov_tolerance is None else args.fov_tolerance
    if not 0.0 <= fov_tolerance < 0.5:
        raise ValueError(f"--fov-tolerance {fov_tolerance}: expected a fraction in [0, 0.5)")
    if args.json and Path(args.json).exists() and not args.force:
        raise FileExistsError(f"--json {args.json} exists; --force replaces it")
    spec = scenario_mod.PipelineSpec(LOST_IN_SPACE)
    if args.pipeline is not None:
        spec = spec.replaced_by(scenario_mod.load_pipeline(args.pipeline))
    spec = spec.replaced_by(scenario_mod.PipelineSpec(_agents(args.agent)))
    Pipeline.from_spec(spec, tuple(args.trust))  # a bad agent or option fails here, before any file
    solvers: dict = {}
    results, failed = [], 0
    for name in args.files:
        try:
            image = read_frame(name)
            if camera_file is not None:
                camera, calibrated = camera_file.camera, camera_file.spot_calibrated
                if image.shape != (camera.height, camera.width):
                    raise ValueError(f"{name}: {image.shape[1]} x {image.shape[0]} px, but the camera in "
                                     f"{args.camera} is {camera.width} x {camera.height}")
            else:
                camera, calibrated = camera_from_fov(args.fov, image.shape), False
            if camera not in solvers:
                solvers[camera] = FrameSolver(camera, Pipeline.from_spec(spec, tuple(args.trust)),
                                              spot_calibrated=calibrated, epoch=args.epoch,
                                              fov_tolerance=fov_tolerance)
            solution = solvers[camera].solve(image, file=str(name))
            if solution.solved and args.wcs_fits:
                write_wcs_fits(image, solution, camera, Path(args.wcs_fits) / (Path(name).stem + ".fits"),
                               replace=args.force)
        except (ValueError, OSError) as exc:  # this file's problem: one line, then the next file
            print(f"starenv solve: error: {printable(exc)}", file=sys.stderr)
            results.append({"file": str(name), "error": str(exc)})
            failed += 1
            continue
        results.append(solution.to_dict())
        spot = f"spot {solution.spot_sigma_px:.2f} px{' (measured)' if solution.spot_measured else ''}"
        if solution.solved:
            print(printable(f"{name}: solved, RA {solution.ra_deg:.5f} Dec {solution.dec_deg:+.5f} roll "
                            f"{solution.roll_deg:.3f} deg, {solution.stars_identified}/{solution.stars_detected} stars "
                            f"identified, residual rms {solution.residual_rms_px:.3f} px, {spot}, "
                            f"{_solved_field(solution)}{solution.time_ms:.1f} ms"))
        else:
            print(printable(f"{name}: not solved ({solution.stars_identified} of {solution.stars_detected} stars "
                            f"identified), {spot}, {solution.time_ms:.1f} ms"))
    solved = sum(bool(r.get("solved")) for r in results)
    print(f"{solved}/{len(args.files)} frames solved" + (f", {failed} unreadable" if failed else ""))
    if args.json:
        with atomic_file(args.json, "w", encoding="utf-8", replace=args.force) as f:
            json.dump(results, f, indent=1)
        print(f"wrote {args.json}")
    return 2 if failed else 0


def _refuse_existing(paths: list[Path], force: bool) -> None:
    """Refuse to replace an existing output without ``--force``."""
    for path in paths:
        if path.exists() and not force:
            raise FileExistsError(f"{path} exists; --force replaces it")


def cmd_calibrate(args) -> int:
    from starenv.files import atomic_file
    from starenv.real.calibrate import calibrate_files, camera_toml, report_markdown, residual_table, scenario_toml

    if not 0.0 < args.fov < 180.0:
        raise ValueError(f"--fov {args.fov}: expected the field across the image columns in degrees, in (0, 180)")
    out = Path(args.out)
    twin = Path(args.scenario) if args.scenario else out.with_name(out.stem + "_scenario.toml")
    report = Path(args.report) if args.report else out.with_suffix(".md")
    _refuse_existing([out, twin, report], args.force)
    models = ("pinhole", "brown", "legendre")
    cal, solutions = calibrate_files(args.files, args.fov, epoch=args.epoch, exposure_s=args.exposure_s,
                                     choose=args.distortion, legendre_order=args.legendre_order,
                                     gain_e_per_dn=args.gain, bias_dn=args.bias_dn, models=models)
    for sol in solutions:
        state = f"{sol.stars_identified} stars identified" if sol.solved else "not solved, left out"
        print(printable(f"{sol.file}: {state}"))
    print(residual_table(cal))
    with atomic_file(out, "w", encoding="utf-8") as f:
        f.write(camera_toml(cal, args.pixel_pitch_um, args.f_number))
    with atomic_file(twin, "w", encoding="utf-8") as f:
        f.write(scenario_toml(cal, args.pixel_pitch_um, args.f_number, name=out.stem))
    with atomic_file(report, "w", encoding="utf-8") as f:
        f.write(report_markdown(cal))
    print(f"twin ({cal.chosen} distortion, spot {cal.spot.mean_px:.3f} px, zero point {cal.zero_point.zp_twin_mag:.3f} "
          f"mag for 1 DN/s, gain {cal.noise.gain_e_per_dn:.3g} e-/DN{'' if cal.noise.gain_measured else ' assumed'})")
    print(f"wrote {out} (camera), {twin} (scenario), {report} (report)")
    return 0


def cmd_compare(args) -> int:
    from starenv.files import atomic_file
    from starenv.real.compare import compare_files, markdown, plots, summary

    out = Path(args.out)
    table = out / "compare.md"
    _refuse_existing([table], args.force)
    comparisons, solutions = compare_files(args.files, args.camera, args.exposure_s, args.epoch, args.seed)
    for sol in solutions:
        if not sol.solved:
            print(printable(f"{sol.file}: not solved with the twin's camera, left out"))
    text = markdown(comparisons, summary(comparisons))
    try:
        figures = plots(comparisons, out)
    except ModuleNotFoundError as exc:  # matplotlib: the report extra
        figures = []
        print(f"no plots ({exc.name} missing: pip install 'starenv[report]')")
    text += "".join(f"\n![{Path(name).stem}]({name})\n" for name in figures)
    with atomic_file(table, "w", encoding="utf-8") as f:
        f.write(text)
    print(text.split("\n\n| frame")[0])
    print(f"wrote {table}" + (f" and {len(figures)} figures in {out}" if figures else ""))
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


def _as_typed(exc: BaseException, pairs: list[str]) -> BaseException:
    """``exc`` naming the ``--set KEY=VALUE`` it lies in, as typed, where a scenario error names an override."""
    key = getattr(exc, "override", None)
    for pair in pairs if key is not None else ():
        if pair.partition("=")[0] == key:
            return type(exc)(f"--set {pair}: {exc.detail}")
    return exc


def main(argv: list[str] | None = None) -> int:
    """The command line; its exit status.  A reader that stops reading (``starenv scenarios | head -1``) ends it
    quietly with status 0."""
    try:
        status = _main(argv)
        sys.stdout.flush()  # here, not at interpreter exit, so that a closed pipe is caught below
        return status
    except BrokenPipeError:
        # Python's documented handling: the rest of the output goes to devnull, so the final flush cannot fail again
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0


def _main(argv: list[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    if argv[:1] == ["train"]:  # its own parser, in a module that imports torch (as the learned agents' modules do)
        from starenv.agents.identify.network_train import main as train_main

        try:
            return train_main(argv[1:])
        except BrokenPipeError:
            raise
        except Exception as exc:  # noqa: BLE001  (one line; --debug shows the traceback)
            return _fail("starenv train", exc, debug)
    import starenv

    parser = argparse.ArgumentParser(prog="starenv", description="Star sensor simulator under dynamic conditions")
    parser.add_argument("--version", action="version", version=f"starenv {starenv.__version__}")
    parser.add_argument("--debug", action="store_true", help="on an error, print its traceback too (any position)")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("scenarios", help="list the bundled scenarios (--show NAME prints one's file)")
    p.add_argument("--show", default=None, metavar="NAME",
                   help="print the bundled scenario NAME's TOML, comments included, to start your own from")
    p.set_defaults(fn=cmd_scenarios)
    p = sub.add_parser("new", help="write a documented scenario from a star sensor's datasheet values, every derived "
                                   "figure (IFOV, photon flux, limiting magnitude, ...) in a comment")
    optics = p.add_mutually_exclusive_group(required=True)
    optics.add_argument("--fov", type=float, dest="fov_deg", metavar="DEG",
                        help="full field of view across the width, edge to edge (deg)")
    optics.add_argument("--focal-mm", type=float, dest="focal_length_mm", metavar="F", help="focal length (mm)")
    p.add_argument("--pixel-um", type=float, dest="pixel_pitch_um", metavar="P", help="pixel pitch (um)")
    p.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), help="pixels across and down")
    p.add_argument("--aperture-mm", type=float, metavar="D", help="entrance pupil diameter (mm)")
    p.add_argument("--exposure-ms", type=float, metavar="T", help="exposure time (ms)")
    p.add_argument("--rate-hz", type=float, dest="frame_rate_hz", metavar="R", help="frame rate (Hz)")
    p.add_argument("--read-noise-e", type=float, metavar="E", help="read noise (e- RMS)")
    p.add_argument("--dark-current-e-s", type=float, dest="dark_current_e_per_s", metavar="E",
                   help="dark current (e-/px/s)")
    p.add_argument("--full-well-e", type=float, metavar="E", help="full-well capacity (e-)")
    p.add_argument("--gain-e-dn", type=float, dest="gain_e_per_dn", metavar="G", help="conversion gain (e-/DN)")
    p.add_argument("--qe", type=float, dest="quantum_efficiency", metavar="QE", help="quantum efficiency (0-1)")
    p.add_argument("--transmission", type=float, metavar="T", help="optics transmission (0-1; default 0.8)")
    p.add_argument("--adc-bits", type=int, metavar="N", help="ADC bits (default 12)")
    p.add_argument("--psf-sigma-px", type=float, metavar="S", help="spot sigma (px; default 1)")
    p.add_argument("--snr", type=float, metavar="K", help="SNR the limiting magnitude is stated for (default 5)")
    p.add_argument("--sky-mag", type=float, dest="sky_mag_per_arcsec2", metavar="M",
                   help="sky background (mag/arcsec^2; default 22)")
    p.add_argument("--duration-s", type=float, metavar="S", help="episode length (s; default 10)")
    p.add_argument("--name", default=None, help="scenario name (default my_sensor)")
    p.add_argument("--out", default=None, metavar="FILE.toml", help="write here (default: print it)")
    p.add_argument("--force", action="store_true", help="replace an existing --out file")
    p.set_defaults(fn=cmd_new)
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
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument("--format", choices=("scenario", "aem"), default="scenario",
                   help="scenario: the scenario TOML (--scenario); aem: the estimated attitude as a CCSDS AEM to "
                        "--out (KVN, or XML for a .xml name) and the truth beside it as OUT.truth.aem "
                        "(the 'aem' extra: ccsds-ndm)")
    p.add_argument("--out", default=None, metavar="FILE.aem", help="--format aem: the estimate's file")
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
    p = sub.add_parser("solve", help="solve real frames (FITS, 8/16-bit PNG or TIFF) lost in space: attitude, "
                                     "RA/Dec/roll, identified stars")
    p.add_argument("files", nargs="+", metavar="FILE", help="grey frames: .fits (starenv[fits]), .png, .tif/.tiff")
    camera = p.add_mutually_exclusive_group(required=True)
    camera.add_argument("--camera", metavar="CAMERA.toml",
                        help="a camera file: a [camera] table with the keys of a scenario's [[heads]] (without "
                             "psf_sigma_px the spot size is measured on each frame)")
    camera.add_argument("--fov", type=float, metavar="DEG",
                        help="a pinhole camera with this field across the image columns (deg), centred, no "
                             "distortion; the spot size is measured on each frame")
    p.add_argument("--fov-tolerance", type=float, default=None, metavar="FRACTION",
                   help="a frame not solved with the camera's focal length is solved again with it scaled over "
                        "1 +- FRACTION (default 0.1, starenv.real.solve.FOV_TOLERANCE; 0: no search); the field "
                        "fitted to the identified stars is reported (fov_fitted_deg)")
    p.add_argument("--pipeline", default=None, metavar="FILE.toml",
                   help="the [pipeline] table of this file (a scenario's, or a file holding only it: agents, options, "
                        "catalog_mag_limit) over the lost-in-space pipeline (roles used: detector, identifier, "
                        "solver)")
    p.add_argument("--agent", action="append", default=[], metavar="ROLE=module:Class",
                   help="replace an agent of the pipeline (after --pipeline)")
    p.add_argument("--trust", action="append", default=[], metavar="MODULE_PREFIX", help=TRUST_HELP)
    p.add_argument("--epoch", type=float, default=None, metavar="YEAR",
                   help="Julian year of the catalogue positions (default 2026.0; the frames' date, for fast stars)")
    p.add_argument("--json", default=None, metavar="OUT.json", help="write every frame's solution here")
    p.add_argument("--wcs-fits", default=None, metavar="DIR",
                   help="write each solved frame to DIR/NAME.fits with its solved WCS (starenv[fits])")
    p.add_argument("--force", action="store_true", help="replace existing --json and --wcs-fits outputs")
    p.set_defaults(fn=cmd_solve)
    p = sub.add_parser("calibrate", help="fit a camera's digital twin from real frames: focal length, principal point, "
                                         "distortion, spot, background and noise, zero point")
    p.add_argument("files", nargs="+", metavar="FILE", help="grey frames of one camera (.fits, .png, .tif/.tiff)")
    p.add_argument("--fov", type=float, required=True, metavar="DEG",
                   help="the field across the image columns (deg), roughly: the frames are solved with it first")
    p.add_argument("--out", required=True, metavar="CAMERA.toml",
                   help="the twin as a camera file ([camera], for solve --camera and compare --camera)")
    p.add_argument("--scenario", default=None, metavar="TWIN.toml",
                   help="the twin as a scenario (default: OUT's name + _scenario.toml)")
    p.add_argument("--report", default=None, metavar="REPORT.md",
                   help="the fit's report: residual table per model, every value with its 1 sigma (default OUT.md)")
    p.add_argument("--distortion", choices=("auto", "pinhole", "brown", "legendre"), default="auto",
                   help="the twin's distortion model (default auto: the lowest BIC); all three are fitted and tabled")
    p.add_argument("--legendre-order", type=int, default=4, metavar="N",
                   help="total order of paper 003's Legendre field (2-8, default 4)")
    p.add_argument("--exposure-s", type=float, default=1.0, metavar="S",
                   help="the frames' exposure (s; default 1): the zero point and dark current are per second")
    p.add_argument("--epoch", type=float, default=2026.0, metavar="YEAR",
                   help="Julian year of the catalogue positions (default 2026.0)")
    p.add_argument("--gain", type=float, default=None, metavar="E_PER_DN",
                   help="known gain (e-/DN); default: measured from the frames' photon-transfer line where their "
                        "background levels spread enough, else 1 assumed")
    p.add_argument("--bias-dn", type=float, default=None, metavar="DN",
                   help="known bias (DN, e.g. from a dark frame): read noise is measured only with it")
    p.add_argument("--pixel-pitch-um", type=float, default=5.0, metavar="UM",
                   help="pixel pitch written to the twin (default 5; frames give focal length / pitch only)")
    p.add_argument("--f-number", type=float, default=2.0, metavar="N",
                   help="f-number written to the twin (default 2; lowered where the zero point needs a larger pupil)")
    p.add_argument("--force", action="store_true", help="replace existing outputs")
    p.set_defaults(fn=cmd_calibrate)
    p = sub.add_parser("compare", help="real frames beside their twin rendered at each solved attitude: star fluxes, "
                                       "spots, centroids, background, detections; a table and plots")
    p.add_argument("files", nargs="+", metavar="FILE", help="grey frames of the camera (.fits, .png, .tif/.tiff)")
    p.add_argument("--camera", required=True, metavar="TWIN.toml", help="the twin: a camera file (starenv calibrate)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for compare.md and the plots")
    p.add_argument("--exposure-s", type=float, default=1.0, metavar="S",
                   help="the frames' exposure (s; default 1, as starenv calibrate's)")
    p.add_argument("--epoch", type=float, default=2026.0, metavar="YEAR",
                   help="Julian year of the catalogue positions (default 2026.0)")
    p.add_argument("--seed", type=int, default=0, help="the twin's noise seed (frame k takes seed + k)")
    p.add_argument("--force", action="store_true", help="replace an existing DIR/compare.md")
    p.set_defaults(fn=cmd_compare)
    sub.add_parser("train", help="train paper 002's network on a dataset (options: starenv train --help)")
    args = parser.parse_args(argv)
    try:
        return args.fn(args)
    except BrokenPipeError:
        raise
    except Exception as exc:  # noqa: BLE001  (one line; --debug shows the traceback)
        return _fail("starenv", _as_typed(exc, getattr(args, "set", [])), debug)


if __name__ == "__main__":
    sys.exit(main())
