"""Paper 002's network on the whole sky, on the paper_002 sensor, within a fixed wall budget (run by
``benchmarks/paper002_gpu.sh``): a held-out set and a training set built from ``datasets/paper002_sky.toml``, the
paper-size configuration trained, top-1 / top-5 on the held-out set, and the figures written as JSON.

    python benchmarks/paper002_gpu.py --out OUT [--work DIR] [--device cuda] [--jobs 16] [--data-s 150]
                                      [--train-s 170] [--val 2000] [--input SIZE] [--samples N] [--epochs E]
                                      [--spec SPEC] [--set KEY=VALUE ...] [--init RUN] [--lr LR]

Sizes follow the measured rates: the held-out set (``--val`` samples, seed 1) is built first (its build rate, samples/s
on ``--jobs`` processes), then read the way training will read the training set (``--preload``: held in the device's
memory when it fits, else ``--workers`` DataLoader processes) and one epoch of its batches drawn without a model (the
loader's rate), and a short probe times forward + backward passes on the device (the network's rate).  Training runs
at the lower of the loader's rate and ``PROBE_SHARE`` of the network's; the training set (seed 0) is then as large
as ``--data-s`` + ``--train-s`` seconds allow for building it, reading it and ``--epochs`` passes at that rate, so a
slow loader shrinks the set rather than leaving epochs unrun (``--samples`` fixes the size instead).
Training: the paper-size :class:`~starenv.agents.identify.network_model.MainStarConfig` (``--set`` none but the
input; ``--set`` pairs as ``starenv train`` takes them make another, ``--init`` starts from a run's weights), Adam,
batch 160 (the paper's), one-cycle learning rate, random 90-degree rolls, ``--workers`` DataLoader processes.
``--spec`` trains on another ``main_star`` spec the same way (its centring kept, its input size unless ``--input``):
``datasets/tetra3_twin_sky.toml`` is the real camera's twin (sim to real).  Writes ``OUT/weights.pt`` and
``OUT/manifest.json`` (the run, as ``starenv train`` writes it) and ``OUT/figures.json`` (rates, wall times, epochs,
accuracy).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from starenv.datasets import build_dataset, load_spec, navigation_stars  # noqa: E402

SPEC = ROOT / "datasets" / "paper002_sky.toml"
BATCH = 160  # the paper's (--batch)
LR = 1e-3
PROBE_BATCHES = 8  # timed forward + backward passes, after as many warm-ups
PROBE_SHARE = 0.8  # of the measured rate the epochs are sized for (data loading, the per-epoch held-out pass)
RATE_CAP = 1.5
SHM_BYTES = 2**31  # shared memory the DataLoader workers' batches in flight need, with room
FINISH_S = 45.0  # kept for what follows the training (the dataset's digest, the files) and the probe


def spec_with(spec, samples: int, seed: int, name: str, shard_size: int = 100, input_size: int | None = None):
    """``spec`` (a validated spec) with another size, seed, name and shard size (and input size, when given)."""
    d = spec.to_dict()
    d.update(name=name, samples=samples, seed=seed, shard_size=shard_size)
    if input_size is not None:
        d.update(input_size=input_size)
    return load_spec(d)


def build(spec, folder: Path, jobs: int) -> float:
    """Build ``spec`` into ``folder``; its wall time (s)."""
    t0 = time.perf_counter()
    build_dataset(spec, folder, jobs=jobs, progress=False, log=print)
    return time.perf_counter() - t0


def probe(config, device: str, batch: int, steps: int = PROBE_BATCHES) -> float:
    """Forward + backward samples/s of the network of ``config`` (a MainStarConfig) on ``device`` (random inputs;
    ``steps`` timed Adam steps after as many warm-ups)."""
    import torch
    from torch.nn import functional as F

    from starenv.agents.identify.network_model import MainStarNet
    from starenv.agents.identify.network_train import deterministic_cuda_environment

    if device == "cuda":
        deterministic_cuda_environment()
    torch.use_deterministic_algorithms(True)
    net = MainStarNet(config).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=LR)  # the probe times steps; the rate does not matter
    x = torch.randn(batch, config.input_size, config.input_size, device=device)
    y = torch.randint(0, config.n_classes, (batch,), device=device)

    def step():
        loss = F.cross_entropy(net(x), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss.item()

    for _ in range(steps):
        step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return steps * batch / (time.perf_counter() - t0)


def loader_rates(folder: Path, device: str, preload: str, workers: int, batch: int) -> dict:
    """How training will read a set like the one in ``folder``: held in memory or not, the samples/s of that first
    read (the shards' bytes checked and parsed; for shards read while training, one untimed pass), and of one epoch
    of rolled batches drawn from it without a model."""
    from starenv.agents.identify.network_data import InMemory, ShardDataset, ShardSampler
    from starenv.agents.identify.network_train import batches, source_for

    dataset = ShardDataset(folder)
    t0 = time.perf_counter()
    source = source_for(dataset, device, preload, log=lambda *_: None)
    in_memory = isinstance(source, InMemory)
    order = ShardSampler(dataset, 0).order()
    if not in_memory:
        sum(1 for _ in batches(source, order, batch, workers=workers))
    read_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    drawn = sum(len(x) for x, _ in batches(source, order, batch, workers=workers, turn=(0, 0)))
    if device == "cuda":
        import torch

        torch.cuda.synchronize()
    return {"in_memory": in_memory, "workers": 0 if in_memory else workers,
            "read_samples_per_s": round(len(dataset) / read_s, 1),
            "batches_samples_per_s": round(drawn / (time.perf_counter() - t0), 1)}


def warn_only() -> None:
    """Make every later ``torch.use_deterministic_algorithms(True)`` warn instead of raise (this run only), so a one-off
    GPU run still trains and records which op had no deterministic kernel."""
    import torch

    strict = torch.use_deterministic_algorithms
    torch.use_deterministic_algorithms = lambda mode, **_: strict(mode, warn_only=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--work", default=None, help="folder for the datasets (default: a new temporary folder)")
    p.add_argument("--device", default="cuda")
    p.add_argument("--jobs", type=int, default=16)
    p.add_argument("--workers", type=int, default=8)
    p.add_argument("--data-s", type=float, default=150.0)
    p.add_argument("--train-s", type=float, default=170.0)
    p.add_argument("--total-s", type=float, default=400.0, help="the whole run's budget: training gets what is left")
    p.add_argument("--limit-s", type=float, default=450.0, help="the whole run's hard limit (training stops early)")
    p.add_argument("--val", type=int, default=3000)
    p.add_argument("--input", type=int, default=None, help="network input size (default: the spec's)")
    p.add_argument("--samples", type=int, default=None)
    p.add_argument("--epochs", type=int, default=3, help="passes over the training set the sizes are planned for")
    p.add_argument("--preload", default="auto", help="auto, yes or no (starenv train --preload)")
    p.add_argument("--batch", type=int, default=BATCH)
    p.add_argument("--spec", default=str(SPEC), help="the main_star dataset spec (default: paper002_sky.toml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="network config (starenv train)")
    p.add_argument("--init", default=None, help="a run folder or shipped weights' name to start from")
    p.add_argument("--lr", type=float, default=LR)
    args = p.parse_args(argv)
    t_start = time.perf_counter()
    out = Path(args.out)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="paper002_gpu-"))
    out.mkdir(parents=True, exist_ok=True)
    base = load_spec(args.spec)
    size, name = args.input, base.name
    val_spec = spec_with(base, args.val, 1, f"{name}_val", input_size=size)
    figures: dict = {"spec": Path(args.spec).name, "device": args.device, "jobs": args.jobs,
                     "input_size": val_spec.input_size, "batch": args.batch, "lr": args.lr, "set": args.set,
                     "init": args.init}
    figures["classes"] = n_classes = len(navigation_stars(val_spec)[0])  # the catalogue's disk cache, for the workers
    from starenv.agents.identify.network_train import parse_config

    config = parse_config([*args.set, f"input_size={val_spec.input_size}", f"centre={json.dumps(val_spec.centre)}"],
                          n_classes)
    # a build's start (processes spawned, imports, catalogue) measured apart: one sample on each process
    start_s = build(spec_with(base, args.jobs, 2, f"{name}_start", shard_size=1, input_size=size), work / "start",
                    args.jobs)
    val_s = build(val_spec, work / "val", args.jobs)
    # samples/s once the processes run; at most RATE_CAP x the plain rate, in case the start was timed long
    rate = min((args.val - args.jobs) / max(1e-3, val_s - start_s), RATE_CAP * args.val / val_s)
    figures["val"] = {"samples": args.val, "build_s": round(val_s, 1), "start_s": round(start_s, 1),
                      "samples_per_s": round(rate, 1)}
    print(json.dumps({"val": figures["val"]}), flush=True)

    workers = args.workers
    shm = shutil.disk_usage("/dev/shm").free if Path("/dev/shm").is_dir() else 0
    if shm < SHM_BYTES:  # DataLoader workers hand batches over in shared memory
        print(f"/dev/shm has {shm / 2**30:.1f} GiB free: reading the shards in the training process", flush=True)
        workers = 0
    figures["workers"] = workers
    figures["loader"] = loader = loader_rates(work / "val", args.device, args.preload, workers, args.batch)
    print(json.dumps({"loader": loader}), flush=True)
    try:
        probe_rate = probe(config, args.device, args.batch)
    except RuntimeError as exc:  # an op without a deterministic kernel: recorded, and the run goes on warning
        if "deterministic" not in str(exc):
            raise
        figures["nondeterministic_op"] = str(exc).splitlines()[0]
        print(f"not deterministic on {args.device}: {figures['nondeterministic_op']}", flush=True)
        warn_only()
        probe_rate = probe(config, args.device, args.batch)
    figures["probe_samples_per_s"] = round(probe_rate, 1)
    train_rate = min(PROBE_SHARE * probe_rate, loader["batches_samples_per_s"])
    figures["bottleneck"] = "loader" if loader["batches_samples_per_s"] < PROBE_SHARE * probe_rate else "network"

    # the budget left, shared between building the set, reading it and the epochs, each at its measured rate
    budget = min(args.data_s + args.train_s, args.total_s - FINISH_S - (time.perf_counter() - t_start))
    per_sample_s = 1 / rate + 1 / loader["read_samples_per_s"] + args.epochs / train_rate
    fitting = int(budget / per_sample_s)
    samples = args.samples or max(args.batch, fitting // 100 * 100 if fitting >= 100 else fitting)  # whole shards
    epochs = args.epochs
    figures["plan"] = {"budget_s": round(budget, 1), "train_samples_per_s": round(train_rate, 1),
                       "data_s": round(samples / rate, 1), "read_s": round(samples / loader["read_samples_per_s"], 1),
                       "train_s": round(epochs * samples / train_rate, 1)}
    print(json.dumps({"probe_samples_per_s": figures["probe_samples_per_s"], "bottleneck": figures["bottleneck"],
                      "train_samples": samples, "epochs": epochs, "plan": figures["plan"]}), flush=True)

    train_spec = spec_with(base, samples, 0, name, input_size=size)
    data_s = build(train_spec, work / "train", args.jobs)
    figures["train_data"] = {"samples": samples, "build_s": round(data_s, 1),
                             "samples_per_s": round(samples / data_s, 1),
                             "ms_per_sample_per_process": round(1e3 * data_s * args.jobs / samples, 1)}
    print(json.dumps({"train_data": figures["train_data"]}), flush=True)
    figures["epochs"] = epochs

    from starenv.agents.identify.network_train import train

    run = work / "run"
    # a hard stop that keeps the whole run inside its limit even if the epochs were sized too generously
    stop_min = max(0.25, (args.limit_s - FINISH_S - (time.perf_counter() - t_start) - figures["plan"]["read_s"]) / 60)
    extra = "".join(f" --set {pair}" for pair in args.set) + (f" --init {args.init}" if args.init else "")
    command = (f"starenv train --data {work / 'train'} --val {work / 'val'} --out {run} --epochs {epochs} "
               f"--batch {args.batch} --lr {args.lr} --seed 0 --rot90 --device {args.device} --workers {workers} "
               f"--max-minutes {stop_min:.2f} --preload {args.preload}{extra}")
    t0 = time.perf_counter()
    manifest = train(work / "train", run, val=work / "val", epochs=epochs, batch=args.batch, lr=args.lr, seed=0,
                     device=args.device, rot90=True, max_minutes=stop_min, checkpoint_every=10**6,
                     progress=False, command=command, workers=workers, preload=args.preload,
                     config_pairs=args.set, init=args.init)
    figures["train_wall_s"] = round(time.perf_counter() - t0, 1)
    history = manifest["metrics"]
    figures["train"] = {"epochs_done": manifest["epochs_done"], "stopped_early": manifest["stopped_early"],
                        "loader": manifest["loader"],
                        "train_seconds": manifest["train_seconds"],
                        "samples_per_s": [h["samples_per_s"] for h in history],
                        "val_top1": [round(h["val"]["top1"], 4) for h in history],
                        "val_top5": [round(h["val"]["top5"], 4) for h in history]}
    if manifest["stopped_early"] or not history:  # the weights written are past the last epoch's evaluation
        from starenv.agents.identify.network import load_network
        from starenv.agents.identify.network_data import ShardDataset
        from starenv.agents.identify.network_train import evaluate

        final = evaluate(load_network(run, args.device)[0], ShardDataset(work / "val"), args.device, workers=workers)
    else:
        final = history[-1]["val"]
    figures["top1"], figures["top5"] = final["top1"], final["top5"]
    try:
        import torch

        figures["torch"] = torch.__version__
        if args.device == "cuda":
            figures["gpu"] = torch.cuda.get_device_name(0)
    except ImportError:
        pass
    for name in ("weights.pt", "manifest.json"):
        shutil.copyfile(run / name, out / name)
    figures["total_wall_s"] = round(time.perf_counter() - t_start, 1)
    (out / "figures.json").write_text(json.dumps(figures, indent=1) + "\n")
    print(json.dumps(figures), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
