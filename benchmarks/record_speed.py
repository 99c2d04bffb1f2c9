"""Recording cost: env steps/s of the 512 x 512 paper_000 scenario with the built-in pipeline, without recording,
with MCAP recording (zstd chunks) and with a live Rerun .rrd recording, measured in the same run; then what the MCAP
recorder's time goes to (encoding the messages, compressing the chunks, writing) and the zstd level / chunk size trade.

Goal: MCAP recording slows the loop by <= 1.3x.

    python benchmarks/record_speed.py [--steps N] [--rounds R]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import zstandard

from starenv.agents.pipeline import Pipeline
from starenv.env import StarSensorEnv
from starenv.episode import StepLog, run_episode
from starenv.record.mcap import McapRecorder, encode_step
from starenv.record.rerun import RerunRecorder, analytics_off
from starenv.record.step import from_step_log

SCENARIO = "paper_000"


def steps_per_s(steps: int, make_observer) -> float:
    env = StarSensorEnv(SCENARIO)
    pipeline = Pipeline.for_scenario(env.scenario)
    observers = [] if make_observer is None else [make_observer()]
    result = run_episode(env, pipeline, seed=0, steps=steps, observers=observers)
    return len(result.records) / result.wall_s


class Keep:
    """Keeps the step logs (frames copied) for the cost breakdown."""

    def start(self, env, seed, pipeline):
        self.logs: list[StepLog] = []

    def step(self, log):
        self.logs.append(log)

    def close(self, error=None):
        pass


def breakdown(steps: int, tmp: Path) -> None:
    env = StarSensorEnv(SCENARIO)
    keep = Keep()
    run_episode(env, Pipeline.for_scenario(env.scenario), seed=0, steps=steps, observers=[keep])
    sizes = [(h.camera.height, h.camera.width) for h in env.scenario.heads]
    t0 = time.perf_counter()
    data = [from_step_log(log, sizes) for log in keep.logs]
    t1 = time.perf_counter()
    payload = [b"".join(m.SerializeToString(deterministic=True) for _, m in encode_step(d)) for d in data]
    t2 = time.perf_counter()
    rec = McapRecorder(tmp / "breakdown.mcap")
    rec.start(env, 0, None)
    t3 = time.perf_counter()
    for d in data:
        rec.write(d)
    rec.close()
    t4 = time.perf_counter()
    n = len(data)
    print(f"\nMCAP recorder cost per step ({n} steps, {sum(map(len, payload)) / n / 1e3:.0f} kB encoded per step):")
    print(f"  StepLog -> StepData             {1e3 * (t1 - t0) / n:7.2f} ms")
    print(f"  protobuf encode + serialise     {1e3 * (t2 - t1) / n:7.2f} ms")
    print(f"  recorder.write (all of it)      {1e3 * (t4 - t3) / n:7.2f} ms")
    blob = b"".join(payload)
    chunk = blob[: 1 << 20]
    for level in (1, 3, 6):
        c = zstandard.ZstdCompressor(level=level)
        t = time.perf_counter()
        for _ in range(5):
            out = c.compress(chunk)
        dt = (time.perf_counter() - t) / 5
        print(f"  zstd level {level}: 1 MiB chunk in {1e3 * dt:6.2f} ms ({len(chunk) / dt / 1e6:6.0f} MB/s), "
              f"ratio {len(chunk) / len(out):.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    args = parser.parse_args()
    analytics_off()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        configs = {
            "no recording": None,
            "MCAP (zstd, 1 MiB chunks)": lambda: McapRecorder(tmp / "run.mcap"),
            "Rerun .rrd (live)": lambda: RerunRecorder(tmp / "run.rrd"),
        }
        steps_per_s(10, None)  # warm the catalog and pattern caches
        rates = {name: [] for name in configs}
        for _ in range(args.rounds):  # interleaved, and compared round by round: the machine's load drifts
            for name, make in configs.items():
                rates[name].append(steps_per_s(args.steps, make))
        base = np.array(rates["no recording"])
        print(f"{SCENARIO}, built-in pipeline, {args.steps} steps x {args.rounds} interleaved rounds "
              f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs):")
        for name, r in rates.items():
            ratio = base / np.array(r)
            goal = "   (goal <= 1.3x)" if name.startswith("MCAP") else ""
            print(f"  {name:28s} best {max(r):6.1f} steps/s   slowdown: median of rounds {np.median(ratio):5.2f}x "
                  f"(range {ratio.min():.2f}-{ratio.max():.2f}), best vs best {max(base) / max(r):5.2f}x{goal}")
        size = os.path.getsize(tmp / "run.mcap")
        print(f"  MCAP file: {size / 1e6:.1f} MB for {args.steps} steps ({size / args.steps / 1e3:.0f} kB/step; "
              f"raw frames {np.prod((512, 512)) * 2 / 1e3:.0f} kB/step)")
        breakdown(min(args.steps, 60), tmp)


if __name__ == "__main__":
    main()
