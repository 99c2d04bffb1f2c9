"""Attitude histories and gyro logs from files (starenv.sim.attitude_files): SLERP and its body rates against
independent computations, the gyro's exact interval means, CCSDS AEM conventions and round trips through the
ccsds-ndm library, line-numbered errors, and scenarios replaying a file."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from starenv import scenario as scenario_mod
from starenv.sim.attitude_files import (
    AemSegment,
    AttitudeHistory,
    AttitudeRecord,
    LagrangeHistory,
    aem_text,
    attitude_motion,
    format_epoch,
    read_aem,
    read_attitude_csv,
    read_gyro_csv,
)
from starenv.sim.gyro import Gyro, GyroSpec

EXAMPLES = Path(__file__).resolve().parent.parent / "examples" / "data"
QUIET_GYRO = dict(arw_deg_rthr=0.0, rrw_deg_hr_rthr=0.0, bias_instability_deg_hr=0.0)  # an ideal gyro


def history(times, rotations: Rotation) -> AttitudeHistory:
    return AttitudeHistory(AttitudeRecord(np.asarray(times, dtype=float), rotations, np.arange(len(times)) + 2,
                                          "test.csv"))


@st.composite
def histories(draw):
    n = draw(st.integers(2, 6))
    steps = draw(st.lists(st.floats(0.01, 5.0), min_size=n - 1, max_size=n - 1))
    t0 = draw(st.floats(-3.0, 0.0))
    seed = draw(st.integers(0, 2**32 - 1))
    rotations = Rotation.random(n, random_state=seed)
    return np.concatenate([[t0], t0 + np.cumsum(steps)]), rotations


@settings(max_examples=60, deadline=None)
@given(histories(), st.floats(0.0, 1.0))
def test_slerp_matches_scipy_and_hits_every_sample(sample, fraction):
    """Between samples the attitude is scipy's Slerp (an independent implementation of the geodesic, with the
    shorter arc: scipy's Slerp goes the shorter way too); at every sample it is the sample itself."""
    t, rotations = sample
    motion = history(t, rotations)
    assert (motion.attitude(t) * rotations.inv()).magnitude().max() < 1e-12
    times = t[:-1] + fraction * np.diff(t)
    reference = Slerp(t, rotations)(times)
    assert (motion.attitude(times) * reference.inv()).magnitude().max() < 1e-12


@settings(max_examples=60, deadline=None)
@given(histories(), st.floats(0.05, 0.95))
def test_body_rate_is_the_derivative_of_the_attitude(sample, fraction):
    """dA/dt = -[w x] A: over a small step h inside an interval the attitude turns by exactly -w h (the rate is
    constant there), so rotvec(A(t + h) A(t)^-1) / h = -w, to the rounding of two attitudes (~1e-16 rad) over h,
    whose smallest here is 1e-5 s: relative 1e-6 leaves room."""
    t, rotations = sample
    motion = history(t, rotations)
    mid = t[:-1] + fraction * np.diff(t)
    h = 1e-2 * np.diff(t) * min(fraction, 1.0 - fraction)
    turned = (motion.attitude(mid + h) * motion.attitude(mid).inv()).as_rotvec() / h[:, None]
    assert np.allclose(turned, -motion.body_rate(mid), rtol=1e-6, atol=1e-9)
    # and over a whole interval the rate carries one sample to the next: A_k+1 = exp(-[w_k x] dt_k) A_k
    carried = Rotation.from_rotvec(-motion.body_rate(t[:-1]) * np.diff(t)[:, None]) * rotations[:-1]
    assert (carried * rotations[1:].inv()).magnitude().max() < 1e-12


@settings(max_examples=40, deadline=None)
@given(histories(), st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_mean_body_rate_is_the_exact_integral(sample, a, b):
    """The mean rate over (t0, t1] times its length is the integral of the piecewise-constant rate, summed here
    interval by interval from each interval's overlap with (t0, t1]."""
    t, rotations = sample
    motion = history(t, rotations)
    t0, t1 = t[0] + min(a, b) * (t[-1] - t[0]), t[0] + max(a, b) * (t[-1] - t[0]) + 1e-6
    t1 = min(t1, t[-1])
    if t1 <= t0:
        return
    overlap = np.clip(np.minimum(t[1:], t1) - np.maximum(t[:-1], t0), 0.0, None)
    integral = overlap @ motion.body_rate(t[:-1])
    mean = motion.mean_body_rate(np.array([t0]), np.array([t1]))[0]
    assert np.allclose(mean * (t1 - t0), integral, rtol=0.0, atol=1e-12 * (1.0 + np.abs(integral).max()))


def test_ideal_gyro_integrates_to_the_interpolated_attitude_change():
    """With the samples on the gyro's grid every gyro interval lies inside one interval of constant rate, so an
    ideal gyro's delta angles, chained, reproduce the trajectory's attitude change exactly; off the grid the summed
    delta angles still equal the exact integral of the rate."""
    rotations = Rotation.random(11, random_state=3)
    t = np.linspace(0.0, 1.0, 11)  # every 0.1 s: on the 200 Hz gyro grid
    motion = history(t, rotations)
    gyro = Gyro(GyroSpec(rate_hz=200.0, **QUIET_GYRO), np.random.default_rng(0))
    samples = gyro.sample_until(motion.body_rate, 1.0, motion.mean_body_rate)
    chained = Rotation.identity()
    for rate in samples.rate:
        chained = Rotation.from_rotvec(-rate * samples.dt) * chained
    assert (chained * (motion.attitude(1.0) * motion.attitude(0.0).inv()).inv()).magnitude() < 1e-12

    shifted = history(t - 0.0123, rotations)  # samples off the grid: some gyro intervals straddle two
    gyro = Gyro(GyroSpec(rate_hz=200.0, **QUIET_GYRO), np.random.default_rng(0))
    samples = gyro.sample_until(shifted.body_rate, 0.985, shifted.mean_body_rate)
    overlap = np.clip(np.minimum(shifted.t[1:], 0.985) - np.maximum(shifted.t[:-1], 0.0), 0.0, None)
    integral = overlap @ shifted.body_rate(shifted.t[:-1])
    assert samples.t[-1] == pytest.approx(0.985)
    assert np.allclose(samples.rate.sum(axis=0) * samples.dt, integral, rtol=0.0, atol=1e-12)


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def one_line_at(exc: pytest.ExceptionInfo, path: Path, line: int) -> str:
    text = str(exc.value)
    assert "\n" not in text
    assert text.startswith(f"{path}:{line}:"), text
    return text


QUAT = "0,0,0,1"


@pytest.mark.parametrize("rows, line, words", [
    ([f"0,{QUAT}", f"1,{QUAT}", f"1,{QUAT}"], 4, "does not increase"),
    ([f"0,{QUAT}", f"1,{QUAT}", f"0.5,{QUAT}"], 4, "does not increase"),
    ([f"0,{QUAT}", "1,0,0,0,nan"], 3, "finite"),
    ([f"0,{QUAT}", "1,0,0,0.1,1"], 3, "unit quaternion"),
    ([f"0,{QUAT}", "1,0,0,x,1"], 3, "qz: expected a number"),
    ([f"0,{QUAT}", "1,0,0,1"], 3, "expected 5 fields"),
    ([f"0,{QUAT}", f"100,{QUAT}"], 3, "a gap of 100 s"),
])
def test_attitude_csv_errors_name_the_line(tmp_path, rows, line, words):
    path = write(tmp_path, "att.csv", "t,qx,qy,qz,qw\n" + "\n".join(rows) + "\n")
    with pytest.raises(ValueError) as exc:
        read_attitude_csv(path, max_step_s=10.0)
    assert words in one_line_at(exc, path, line)


def test_attitude_csv_header_and_comments(tmp_path):
    path = write(tmp_path, "att.csv", "# from the AOCS team\nt,qw,qx,qy,qz\n\n0,1,0,0,0\n2,0,0,0,1\n")
    record = read_attitude_csv(path)
    assert record.lines.tolist() == [4, 5]
    assert np.allclose(record.attitude.as_quat(canonical=True), [[0, 0, 0, 1], [0, 0, 1, 0]])
    bad = write(tmp_path, "bad.csv", "time,qx,qy,qz,qw\n0,0,0,0,1\n")
    with pytest.raises(ValueError) as exc:
        read_attitude_csv(bad)
    assert "header" in one_line_at(exc, bad, 1)


@pytest.mark.parametrize("rows, line, words", [
    (["0.005,0,0,0", "0.010,0,0,0", "0.020,0,0,0", "0.025,0,0,0"], 4, "a gap"),
    (["0.005,0,0,0", "0.010,0,0,0", "0.010,0,0,0"], 4, "does not increase"),
    (["0.005,0,0,0", "0.010,0,inf,0"], 3, "finite"),
    (["0.005,0,0,0", "0.010,0,100,0"], 3, "rates within"),
])
def test_gyro_csv_errors_name_the_line(tmp_path, rows, line, words):
    path = write(tmp_path, "gyro.csv", "t,wx,wy,wz\n" + "\n".join(rows) + "\n")
    with pytest.raises(ValueError) as exc:
        read_gyro_csv(path)
    assert words in one_line_at(exc, path, line)


def kvn(data_lines: list[str], frames=("EME2000", "SC_BODY_1"), direction="A2B", qtype="LAST", extra="") -> str:
    return "\n".join([
        "CCSDS_AEM_VERS = 1.0", "CREATION_DATE = 2026-01-01T00:00:00", "ORIGINATOR = TEST", "META_START",
        "OBJECT_NAME = SAT", "OBJECT_ID = 2026-001A", f"REF_FRAME_A = {frames[0]}", f"REF_FRAME_B = {frames[1]}",
        f"ATTITUDE_DIR = {direction}", "TIME_SYSTEM = UTC", "START_TIME = 2026-01-01T00:00:00",
        "STOP_TIME = 2026-01-01T00:00:10", "ATTITUDE_TYPE = QUATERNION", f"QUATERNION_TYPE = {qtype}", extra,
        "META_STOP", "DATA_START", *data_lines, "DATA_STOP", ""])


S45 = math.sqrt(0.5)


@pytest.mark.parametrize("frames, direction, qtype, quat", [
    (("EME2000", "SC_BODY_1"), "A2B", "LAST", f"0 0 {S45} {S45}"),
    (("EME2000", "SC_BODY_1"), "A2B", "FIRST", f"{S45} 0 0 {S45}"),
    (("SC_BODY_1", "ICRF"), "B2A", "LAST", f"0 0 {S45} {S45}"),
    (("SC_BODY_1", "ICRF"), "A2B", "LAST", f"0 0 {-S45} {S45}"),
])
def test_aem_convention(tmp_path, frames, direction, qtype, quat):
    """A body frame made by turning ICRF +90 deg about its Z axis (CCSDS: the rotation from ICRF to the body, QC =
    cos 45 deg, the axis +Z) has its +X axis along ICRS +Y: the attitude maps ICRS +Y to body +X, and ICRS +X to
    body -Y, however the file orders the scalar or names the direction."""
    path = write(tmp_path, "att.aem", kvn([f"2026-01-01T00:00:00 {quat}", f"2026-01-01T00:00:10 {quat}"],
                                          frames, direction, qtype))
    attitude = read_aem(path).attitude[0]
    assert np.allclose(attitude.apply([0.0, 1.0, 0.0]), [1.0, 0.0, 0.0], atol=1e-12)
    assert np.allclose(attitude.apply([1.0, 0.0, 0.0]), [0.0, -1.0, 0.0], atol=1e-12)


def test_aem_times_and_usable_span(tmp_path):
    path = write(tmp_path, "att.aem", kvn(["2026-001T00:00:00.5 0 0 0 1", "2026-01-01T00:00:02.5 0 0 0 1",
                                           "2026-01-01T00:01:00.5 0 0 0 1"],
                                          extra="USEABLE_START_TIME = 2026-01-01T00:00:01.5"))
    record = read_aem(path, start_s=0.25)
    assert record.t.tolist() == [-1.25, 0.75, 58.75]  # t = 0 at the usable start plus start_s
    assert record.span == (-0.25, 58.75)  # valid from the usable start on


@pytest.mark.parametrize("data, extra, line, words", [
    (["2026-01-01T00:00:00 0 0 0 1", "2026-01-01T00:00:00 0 0 0 1"], "", 19, "does not increase"),
    (["2026-01-01T00:00:00 0 0 0 1", "2026-01-01T00:00:01 0 0 0.2 1"], "", 19, "unit quaternion"),
    (["2026-01-01T00:00:00 0 0 0 1", "2026-01-01T00:00:01 0 0 0 nan"], "", 19, "finite"),
    (["2026-01-01T00:00:00 0 0 0 1", "2026-01-01T00:01:00 0 0 0 1"], "", 19, "a gap of 60 s"),
    (["2026-01-01T00:00:00 0 0 0 1", "2026-01-01T00:00:01 0 0 1"], "", 19, "four finite quaternion numbers"),
    (["2026-01-01T00:00:00 0 0 0 1", "2026-01-01T00:00:01 0 0 x 1"], "", 19, "four finite quaternion numbers"),
    (["2026-01-01T00:00:00 0 0 0 1", "2026-13-01T00:00:01 0 0 0 1"], "", 19, "expected a calendar date"),
])
def test_aem_errors_name_the_line(tmp_path, data, extra, line, words):
    path = write(tmp_path, "att.aem", kvn(data, extra=extra))
    with pytest.raises(ValueError) as exc:
        read_aem(path, max_step_s=10.0)
    assert words in one_line_at(exc, path, line)


def test_aem_refusals(tmp_path):
    data = ["2026-01-01T00:00:00 0 0 0 1", "2026-01-01T00:00:01 0 0 0 1"]
    hermite = write(tmp_path, "h.aem", kvn(data, extra="INTERPOLATION_METHOD = HERMITE"))
    with pytest.raises(ValueError, match=r"INTERPOLATION_METHOD HERMITE: SLERP \(LINEAR, SLERP\) or LAGRANGE"):
        read_aem(hermite)
    no_degree = write(tmp_path, "l.aem", kvn(data, extra="INTERPOLATION_METHOD = LAGRANGE"))
    with pytest.raises(ValueError, match="INTERPOLATION_DEGREE: an integer in"):
        read_aem(no_degree)
    orbit = write(tmp_path, "o.aem", kvn(data, frames=("LVLH", "SC_BODY_1")))
    with pytest.raises(ValueError, match="between an inertial frame"):
        read_aem(orbit)
    xml = aem_text([AemSegment(np.array([0, 10**9]), Rotation.identity(2), "SAT", "x")], "xml")
    entity = write(tmp_path, "e.xml", xml.replace("?>", '?>\n<!DOCTYPE aem [<!ENTITY x SYSTEM "file:///etc/passwd">]>',
                                                  1))
    with pytest.raises(ValueError, match="document type declaration"):
        read_aem(entity)
    no_type = write(tmp_path, "t.aem", kvn(data).replace("QUATERNION_TYPE = LAST\n", ""))
    with pytest.raises(ValueError, match="QUATERNION_TYPE .FIRST or LAST. expected"):
        read_aem(no_type)
    version_2 = write(tmp_path, "v2.aem", kvn(data).replace("CCSDS_AEM_VERS = 1.0", "CCSDS_AEM_VERS = 2.0"))
    with pytest.raises(ValueError, match="AEM 2.0 in KVN, which ccsds-ndm does not read back"):
        read_aem(version_2)
    garbage = write(tmp_path, "g.aem", "CCSDS_AEM_VERS = 1.0\nnot an aem\n")
    with pytest.raises(ValueError) as exc:
        read_aem(garbage)
    assert str(exc.value).startswith(f"{garbage}: ") and "\n" not in str(exc.value)


def test_aem_segments_must_meet(tmp_path):
    one = kvn(["2026-01-01T00:00:00 0 0 0 1", "2026-01-01T00:00:05 0 0 0 1"])
    second = one.split("META_START", 1)[1]
    meets = write(tmp_path, "m.aem", one + "META_START" + second)
    with pytest.raises(ValueError, match="segment 2 starts -5 s after the previous one ends: a gap"):
        read_aem(meets)
    joined = second.replace("00:00:05 0 0 0 1", "00:00:09 0 0 0 1").replace("00:00:00 0 0 0 1",
                                                                            "00:00:05 0 0 0 1")
    record = read_aem(write(tmp_path, "j.aem", one + "META_START" + joined))
    assert record.t.tolist() == [0.0, 5.0, 9.0]


def test_lagrange_aem_follows_the_sampled_motion(tmp_path):
    """An AEM stating LAGRANGE of degree 7, sampled every 0.5 s from a constant body rate w: between samples the
    attitude and rate are the motion's.  The quaternion's components are sinusoids of frequency |w| / 2, so the
    Lagrange remainder is at most (|w| h / 2)^(d + 1) / (4 (d + 1)), 2e-18 here: what is left is rounding, well
    under 1e-12."""
    rate = np.array([0.01, -0.02, 0.03])
    t = np.arange(21) * 0.5
    start = Rotation.random(random_state=4)
    attitude = Rotation.from_rotvec(-np.outer(t, rate)) * start
    text = aem_text([AemSegment(np.round(t * 1e9).astype(np.int64), attitude, "SAT", "x")], "kvn")
    text = text.replace("QUATERNION_TYPE          = LAST", "QUATERNION_TYPE = LAST\nINTERPOLATION_METHOD = LAGRANGE\n"
                                                          "INTERPOLATION_DEGREE = 7")
    motion = attitude_motion(read_aem(write(tmp_path, "lagrange.aem", text)))
    assert isinstance(motion, LagrangeHistory) and motion.mean_body_rate is None
    times = np.linspace(0.0, 10.0, 401)
    truth = Rotation.from_rotvec(-np.outer(times, rate)) * start
    assert (motion.attitude(times) * truth.inv()).magnitude().max() < 1e-12
    assert np.abs(motion.body_rate(times) - rate).max() < 1e-12
    assert motion.max_rate(0.0, 10.0) >= np.linalg.norm(rate)


@pytest.mark.parametrize("form", ["kvn", "xml"])
def test_aem_round_trip_through_the_library(form):
    """aem_text writes; ccsds-ndm reads it back on its own: the same epochs and quaternions (the inverse of each
    attitude, scalar last and non-negative) to 1e-12."""
    from ccsds_ndm.ndm_io import NdmIo

    attitude = Rotation.random(7, random_state=5)
    unix_ns = 1767225600 * 10**9 + np.arange(7) * 12_345_678
    text = aem_text([AemSegment(unix_ns, attitude, "SAT", "test")], form)
    states = NdmIo().from_string(text).body.segment[0].data.attitude_state
    quats = np.array([[s.quaternion_state.quaternion.q1, s.quaternion_state.quaternion.q2,
                       s.quaternion_state.quaternion.q3, s.quaternion_state.quaternion.qc] for s in states])
    assert np.abs(quats - attitude.inv().as_quat(canonical=True)).max() < 1e-12
    assert states[1].quaternion_state.epoch == "2026-01-01T00:00:00.012345678"


def small_scenario(motion: dict, **more) -> dict:
    return {"duration_s": 0.1, "motion": motion, **more}


def test_scenario_replaying_an_aem_has_the_files_attitude_at_frame_times():
    """The env's truth at each frame's mid-exposure time is the file's attitude there: scipy's Slerp of the file's
    records (read by ccsds-ndm through the reader) at that time, to 1e-12 rad."""
    from starenv.env import StarSensorEnv

    aem = EXAMPLES / "orion_pass.aem"
    env = StarSensorEnv("paper_000", small_scenario({"kind": "attitude_file", "file": str(aem)}))
    record = read_aem(aem)
    reference = Slerp(record.t, record.attitude)
    _, info = env.reset(seed=0)
    for _ in range(4):
        truth = info["truth"]
        expected = reference([truth["time_s"]])[0]
        assert (Rotation.from_quat(truth["attitude"]) * expected.inv()).magnitude() < 1e-12
        _, _, _, _, info = env.step(env.null_action())


def test_attitude_file_must_cover_the_episode(tmp_path):
    path = write(tmp_path, "att.csv", "t,qx,qy,qz,qw\n0,0,0,0,1\n0.05,0,0,0,1\n")
    with pytest.raises(scenario_mod.ScenarioError, match=r"covering \[0, 0.05\] s"):
        scenario_mod.load("paper_000", small_scenario({"kind": "attitude_file", "file": str(path)}))


def test_gyro_replay_delivers_the_log_and_keeps_the_truth(tmp_path):
    """The observation's gyro samples are the log's, sample for sample, while the truth follows the motion."""
    from starenv.env import StarSensorEnv

    t = np.arange(1, 41) * 0.005
    rates = np.column_stack([np.sin(t), np.cos(t), t])
    log = write(tmp_path, "gyro.csv", "t,wx,wy,wz\n" + "\n".join(
        ",".join(repr(float(v)) for v in (ti, *r)) for ti, r in zip(t, rates, strict=True)) + "\n")
    overrides = {"duration_s": 0.1, "gyro": {"replay_file": str(log)}}
    env = StarSensorEnv("paper_000", overrides)
    simulated = StarSensorEnv("paper_000", {"duration_s": 0.1})
    assert env.scenario.gyro.rate_hz == pytest.approx(200.0)
    obs, info = env.reset(seed=0)
    _, info_sim = simulated.reset(seed=0)
    delivered = [obs["gyro"]["t"][: obs["gyro"]["count"]]]
    assert np.array_equal(info["truth"]["attitude"], info_sim["truth"]["attitude"])
    for _ in range(3):
        obs, _, _, _, info = env.step(env.null_action())
        delivered.append(obs["gyro"]["t"][: obs["gyro"]["count"]])
    times = np.concatenate(delivered)
    rows = np.searchsorted(t, times)
    assert np.array_equal(t[rows], times) and np.array_equal(np.diff(rows), np.ones(len(rows) - 1))
    assert np.array_equal(obs["gyro"]["rate"][: obs["gyro"]["count"]], rates[rows[-obs["gyro"]["count"]:]])
    assert np.isnan(info["truth"]["gyro_bias"]).all()  # unknown for a recorded log


def test_gyro_replay_refusals(tmp_path):
    t = np.arange(1, 11) * 0.005
    short = write(tmp_path, "short.csv", "t,wx,wy,wz\n" + "\n".join(f"{float(v)!r},0,0,0" for v in t) + "\n")
    with pytest.raises(scenario_mod.ScenarioError, match="gyro.replay_file: expected samples"):
        scenario_mod.load("paper_000", {"duration_s": 0.1, "gyro": {"replay_file": str(short)}})
    with pytest.raises(scenario_mod.ScenarioError, match=r"gyro.rate_hz: expected the log's rate 200 Hz"):
        scenario_mod.load("paper_000", {"duration_s": 0.04, "gyro": {"replay_file": str(short), "rate_hz": 500.0}})


def test_export_aem_round_trips_through_the_library(tmp_path, capsys):
    """starenv export --format aem: ccsds-ndm reads back every step's estimated attitude of the recording (the
    inverse quaternion, scalar last) to 1e-12, at the step's mid-exposure time on the recording's origin; the truth
    file holds every step's truth the same way."""
    from ccsds_ndm.ndm_io import NdmIo

    from starenv.cli import main
    from starenv.record.mcap import read_metadata, read_steps, run_info

    recording = tmp_path / "run.mcap"
    assert main(["run", "paper_000", "--steps", "3", "--quiet", "--record", str(recording),
                 "--set", "duration_s=0.05"]) == 0
    out = tmp_path / "run.aem"
    assert main(["export", str(recording), "--format", "aem", "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    steps = [s for s in read_steps(recording) if s.attitude_true is not None]
    origin = run_info(read_metadata(recording), recording)["origin_ns"]
    for path, key in ((out, "attitude_estimate"), (tmp_path / "run.truth.aem", "attitude_true")):
        kept = [s for s in steps if getattr(s, key) is not None]
        assert kept
        segments = NdmIo().from_string(path.read_text()).body.segment
        states = [state.quaternion_state for segment in segments for state in segment.data.attitude_state]
        quats = np.array([[q.quaternion.q1, q.quaternion.q2, q.quaternion.q3, q.quaternion.qc] for q in states])
        expected = Rotation.from_quat(np.array([getattr(s, key) for s in kept])).inv().as_quat(canonical=True)
        assert np.abs(quats - expected).max() < 1e-12
        assert [q.epoch for q in states] == [format_epoch(origin + s.time_ns) for s in kept]
    assert main(["export", str(recording), "--format", "aem", "--out", str(out)]) == 2  # exists: --force replaces
    assert "exists; --force replaces it" in capsys.readouterr().err


def test_aem_2_xml_is_read(tmp_path):
    """An AEM 2.0 in XML (built with the library's own 2.0 model; 2.0 has no ATTITUDE_DIR, its quaternions go from
    REF_FRAME_A to REF_FRAME_B): the attitude is each quaternion's inverse, at the records' times."""
    from ccsds_ndm.mapping import NDMFileFormats
    from ccsds_ndm.models import ndmxml4 as adm
    from ccsds_ndm.ndm_io import NdmIo

    rotations = Rotation.random(3, random_state=6)
    quats = rotations.as_quat().tolist()
    states = [adm.AttitudeStateType(quaternion_ephemeris=adm.QuaternionEphemerisType(
        epoch=f"2026-01-01T00:00:0{i}.5", quaternion=adm.QuaternionType(q1=q[0], q2=q[1], q3=q[2], qc=q[3])))
        for i, q in enumerate(quats)]
    meta = adm.AemMetadata(object_name="SAT", object_id="2026-001A", ref_frame_a="ICRF", ref_frame_b="SC_BODY_1",
                           time_system="UTC", start_time="2026-01-01T00:00:00.5", stop_time="2026-01-01T00:00:02.5",
                           attitude_type=adm.AttitudeTypeType.QUATERNION_1)
    segment = adm.AemSegment(metadata=meta, data=adm.AemData(attitude_state=states))
    message = adm.Aem(header=adm.AdmHeader(creation_date="2026-01-01T00:00:00", originator="TEST"),
                      body=adm.AemBody(segment=[segment]))
    path = write(tmp_path, "v2.xml", NdmIo().to_string(message, NDMFileFormats.XML))
    record = read_aem(path)
    assert record.t.tolist() == [0.0, 1.0, 2.0]
    assert (record.attitude * rotations).magnitude().max() < 1e-12  # attitude = rotation^-1
