"""``starenv train``: train paper 002's network on a ``main_star`` dataset, seeded, checkpointed and resumable.

    starenv train --data DATA --out RUN [--val VAL] [--epochs N] [--batch B] [--lr LR] [--seed S]
                  [--device cpu|cuda] [--workers N] [--preload auto|yes|no] [--set key=value ...] [--rot90]
                  [--max-minutes M] [--resume] [--init RUN]

* Deterministic: ``torch.manual_seed(seed)``, ``torch.use_deterministic_algorithms(True)``, batches in an order that
  depends only on (seed, epoch) (:class:`~starenv.agents.identify.network_data.ShardSampler`), read by ``--workers``
  ``DataLoader`` processes (0: this process) or gathered from the whole set held in memory (``--preload``), and
  consumed in that order whatever the path; the same command gives bit-identical weights on one machine.  On CUDA,
  ``CUBLAS_WORKSPACE_CONFIG=:4096:8`` is set before CUDA starts (cuBLAS needs it to be deterministic) and the
  network has no op without a deterministic CUDA kernel (the background median is taken in numpy when the data is
  made); CUDA results are repeatable on one GPU model, driver and torch build, but differ from the CPU's and between
  GPU models (other kernels, other summation orders).  ``--rot90`` turns each image by a multiple of 90 deg, drawn
  from (seed, epoch, batch), about the point the network reads its main star at, which keeps the label: for
  ``centre = "frame"`` the image centre, a roll of the sensor (exact for a square sensor whose principal point is the
  image centre); for ``centre = "main_star"`` the centre of block (S // 2, S // 2), which holds the main star, a
  turn of the sky about that star (the boresight's offset from it turned with the roll; exact but for the
  projection's scale change over the field).
* ``RUN/checkpoint.pt`` (model, optimiser, epoch, batch, metrics so far, and the arguments that decide the result:
  seed, batch, learning rate, epochs, rot90, device, validation set, initial weights) is written after every epoch
  and every ``--checkpoint-every`` batches, whole and then moved into place; ``--resume`` continues from it and
  replays the remaining batches exactly, from whatever instant the run was killed at, and refuses, naming the
  option, a command whose arguments differ from the checkpoint's.
* ``RUN/weights.pt`` holds the state dict only (``torch.save``; load with ``torch.load(..., weights_only=True)``)
  and ``RUN/manifest.json`` the model config, the class list (HIP numbers, label order), the dataset's identity
  (name, spec digest, project version), the git commit, the command, the metrics per epoch and the hashes
  :func:`~starenv.agents.identify.network.load_network` checks (``weights_sha256``, ``identity_sha256``).
* ``--set key=value`` sets a :class:`~starenv.agents.identify.network_model.MainStarConfig` field (``depth=4``,
  ``widths=[8,16,16,32,32,64]``); ``n_classes`` comes from the dataset.
* ``--init RUN`` starts from another run's weights (same config and classes; a fresh optimiser and schedule): the
  paper's two stages, pre-training on the clean set and then training on the full one, are two runs.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from starenv.agents.identify.network import load_network, manifest_hashes, turned
from starenv.agents.identify.network_data import InMemory, ShardDataset, ShardSampler, fits_in_memory
from starenv.agents.identify.network_model import MainStarConfig, MainStarNet
from starenv.files import atomic_file

# The arguments that change the weights a run ends with: a resume must give the checkpoint's.
RESULT_ARGS = ("seed", "batch", "lr", "epochs", "rot90", "device", "val", "init")
CUBLAS_DETERMINISTIC = (":4096:8", ":16:8")  # the workspace settings cuBLAS is deterministic with (CUDA docs)
PRELOAD = ("auto", "yes", "no")  # --preload: the training and validation sets held in memory, or read from disk


def deterministic_cuda_environment() -> None:
    """Set ``CUBLAS_WORKSPACE_CONFIG`` to a deterministic workspace unless it holds one; effective only before
    cuBLAS starts (the first matrix product on the GPU), so :func:`train` calls it before touching CUDA."""
    if os.environ.get("CUBLAS_WORKSPACE_CONFIG") not in CUBLAS_DETERMINISTIC:
        os.environ["CUBLAS_WORKSPACE_CONFIG"] = CUBLAS_DETERMINISTIC[0]


class _Batches(torch.utils.data.Dataset):
    """Batch ``b`` of one epoch's order as an item, so ``DataLoader`` workers read whole batches (in order), each
    turned as :func:`rot90` draws when ``turn`` is (seed, epoch), about the centre block when ``about_block``."""

    def __init__(self, source: ShardDataset | InMemory, order: list[int], batch: int,
                 turn: tuple[int, int] | None = None, about_block: bool = False):
        self.source, self.order, self.batch, self.turn, self.about_block = source, order, batch, turn, about_block

    def __len__(self) -> int:
        return len(self.order) // self.batch

    def __getitem__(self, b: int) -> tuple[torch.Tensor, torch.Tensor]:
        images, labels = self.source.batch(self.order[b * self.batch:(b + 1) * self.batch])
        if self.turn is not None:
            images = rot90(images, *self.turn, b, about_block=self.about_block)
        return images, labels


def batches(source: ShardDataset | InMemory, order: list[int], batch: int, first: int = 0, workers: int = 0,
            pin: bool = False, turn: tuple[int, int] | None = None, about_block: bool = False):
    """Batches ``first ..`` of ``order`` (the last partial one dropped), in order: gathered here from an
    :class:`InMemory` source, read by ``workers`` processes (0: this one) from a :class:`ShardDataset`; turned
    as :func:`rot90` draws when ``turn`` is (seed, epoch)."""
    items = _Batches(source, order, batch, turn, about_block)
    if isinstance(source, InMemory):
        return (items[b] for b in range(first, len(items)))
    return torch.utils.data.DataLoader(items, batch_size=None, sampler=range(first, len(items)), num_workers=workers,
                                       pin_memory=pin, prefetch_factor=4 if workers else None,
                                       persistent_workers=False)


def source_for(dataset: ShardDataset, device: str, preload: str, log=print) -> ShardDataset | InMemory:
    """``dataset`` itself (read from its shards while training) or all of it in ``device``'s memory: ``preload``
    ``yes``, ``no``, or ``auto`` (in memory when it takes at most half of what is free there)."""
    if preload not in PRELOAD:
        raise ValueError(f"--preload: expected one of {', '.join(PRELOAD)}, got {preload!r}")
    if preload == "no" or (preload == "auto" and not fits_in_memory(dataset, device)):
        return dataset
    t0 = time.perf_counter()
    held = InMemory(dataset, device)
    seconds = time.perf_counter() - t0
    log(f"{dataset.folder}: {len(held)} samples read into {device} memory in {seconds:.1f} s "
        f"({held.images.numel() * 4 / 2**30:.2f} GiB)")
    return held


def _atomic_save(obj, path: Path) -> None:
    with atomic_file(path) as f:
        torch.save(obj, f)


def _git_commit() -> str | None:
    try:
        root = Path(__file__).resolve().parents[3]
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def parse_config(pairs: list[str], n_classes: int) -> MainStarConfig:
    """A config from ``key=value`` pairs (values in JSON) over the defaults, with the dataset's class count."""
    names = {f.name for f in fields(MainStarConfig)}
    values: dict = {}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        if not sep or key not in names or key == "n_classes":
            raise ValueError(f"--set {pair!r}: expected KEY=VALUE with KEY one of "
                             f"{', '.join(sorted(names - {'n_classes'}))}")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--set {pair!r}: VALUE must be JSON ({exc})") from exc
        values[key] = tuple(value) if isinstance(value, list) else value
    return MainStarConfig(n_classes=n_classes, **values)


def rot90(images: torch.Tensor, seed: int, epoch: int, batch: int, about_block: bool = False) -> torch.Tensor:
    """Each image of ``images`` (B, S, S) turned by its own multiple of 90 deg, drawn from (seed, epoch, batch) on
    the CPU, about the image's centre or with ``about_block`` about pixel (S // 2, S // 2) (:func:`turned`); a
    permutation of pixels, so the same numbers on any device."""
    g = torch.Generator().manual_seed((seed * 1_000_003 + epoch) * 1_000_003 + batch)
    k = torch.randint(0, 4, (len(images),), generator=g)
    out = images.clone()
    for q in range(1, 4):
        chosen = (k == q).nonzero().flatten()
        if len(chosen):
            chosen = chosen.to(images.device)
            out[chosen] = turned(images[chosen], q, about_block)
    return out


@torch.no_grad()
def evaluate(model: MainStarNet, source: ShardDataset | InMemory, device: str, batch: int = 256,
             workers: int = 0) -> dict:
    """Top-1 and top-5 accuracy and mean cross-entropy of ``model`` on every sample of ``source``."""
    model.eval()
    dataset = source.dataset if isinstance(source, InMemory) else source
    order = ShardSampler(dataset, 0, shuffle=False).order()
    order += [order[i % len(order)] for i in range(-len(order) % batch)]  # whole batches; the padding is cut below
    correct1 = correct5 = 0
    loss = 0.0
    n = len(dataset)
    for k, (x, y) in enumerate(batches(source, order, batch, workers=workers, pin=device == "cuda")):
        keep = max(0, min(batch, n - k * batch))
        x, y = x[:keep], y[:keep]
        logits = model(x.to(device))
        y = y.to(device)
        loss += float(F.cross_entropy(logits, y, reduction="sum"))
        top = logits.topk(min(5, logits.shape[1]), dim=1).indices
        correct1 += int((top[:, 0] == y).sum())
        correct5 += int((top == y[:, None]).any(dim=1).sum())
    return {"top1": correct1 / n, "top5": correct5 / n, "loss": loss / n, "samples": n}


def _initial_weights(run: str | Path, model: MainStarNet, classes, device: str) -> dict:
    """Load ``run``/weights.pt into ``model`` (checked as :func:`~starenv.agents.identify.network.load_network`
    checks it; its manifest's classes must be ``classes``); the manifest's record of it (path and SHA-256)."""
    run = Path(run)
    try:
        net, manifest = load_network(run, device)
    except ValueError as exc:
        raise ValueError(f"--init {run}: {exc}") from exc
    if manifest["classes_hip"] != [int(h) for h in classes]:
        raise ValueError(f"--init {run}: its classes are not this dataset's")
    try:
        model.load_state_dict(net.state_dict())
    except RuntimeError as exc:
        raise ValueError(f"--init {run}: its weights do not fit this model config ({exc})") from exc
    return {"run": str(run), "weights_sha256": manifest["weights_sha256"]}


def train(data: str | Path, out: str | Path, *, val: str | Path | None = None, epochs: int = 10, batch: int = 64,
          lr: float = 1e-3, seed: int = 0, device: str = "cpu", config_pairs: list[str] | None = None,
          rot90: bool = False, max_minutes: float | None = None, resume: bool = False,
          checkpoint_every: int = 100, progress: bool = True, command: str | None = None,
          init: str | Path | None = None, workers: int = 0, preload: str = "auto", log=print) -> dict:
    """Train and write ``out``/weights.pt and manifest.json; returns the manifest.  ``preload``: the sets held in
    the device's memory (``yes``, ``no``, ``auto``: when they fit, :func:`source_for`); ``workers``:
    ``DataLoader`` processes reading the shards when they are not (0: this process).  The weights depend on
    neither."""
    from tqdm import tqdm

    if device not in ("cpu", "cuda"):
        raise ValueError(f"--device: expected 'cpu' or 'cuda', got {device!r}")
    if not isinstance(workers, int) or workers < 0:
        raise ValueError(f"--workers: expected an integer >= 0, got {workers!r}")
    if device == "cuda":
        deterministic_cuda_environment()
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device is available to this torch build")
    for name, value, low in (("--epochs", epochs, 1), ("--batch", batch, 1), ("--checkpoint-every", checkpoint_every,
                                                                                1)):
        if not isinstance(value, int) or value < low:
            raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
    if not lr > 0:
        raise ValueError(f"--lr: expected a positive number, got {lr!r}")
    torch.manual_seed(seed)
    torch.use_deterministic_algorithms(True)
    dataset = ShardDataset(data)
    val_set = ShardDataset(val) if val is not None else None
    if preload not in PRELOAD:
        raise ValueError(f"--preload: expected one of {', '.join(PRELOAD)}, got {preload!r}")
    spec = dataset.info["spec"]
    classes = _class_hips(spec)
    input_size = spec.get("input_size")  # the size of the dataset's images (absent: a dataset not made by starenv)
    pairs = list(config_pairs or [])
    if input_size is not None and not any(p.startswith("input_size=") for p in pairs):
        pairs.append(f"input_size={input_size}")
    centre = spec.get("centre", "frame")  # where the dataset's images are centred
    if not any(p.startswith("centre=") for p in pairs):
        pairs.append(f"centre={json.dumps(centre)}")
    config = parse_config(pairs, len(classes))
    if input_size is not None and config.input_size != input_size:
        raise ValueError(f"--set input_size={config.input_size}: the dataset's images are {input_size} px "
                         f"(its spec's input_size)")
    if config.centre != centre:
        raise ValueError(f"--set centre={config.centre}: the dataset's images are centred on the {centre} (its spec's "
                         f"centre)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = MainStarNet(config).to(device)
    start = None if init is None else _initial_weights(init, model, classes, device)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sampler = ShardSampler(dataset, seed)
    n_batches = len(dataset) // batch  # the last partial batch of an epoch is dropped (BatchNorm statistics)
    if n_batches == 0:
        raise ValueError(f"--batch {batch}: more than the dataset's {len(dataset)} samples")
    total = epochs * n_batches
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=total, pct_start=0.15)
    state = {"epoch": 0, "batch": 0, "history": [], "train_seconds": 0.0, "last_loss": None}
    args = {"seed": seed, "batch": batch, "lr": lr, "epochs": epochs, "rot90": rot90, "device": device,
            "val": None if val_set is None else val_set.spec_digest,
            "init": None if start is None else start["weights_sha256"]}
    ckpt = out / "checkpoint.pt"
    if resume and ckpt.is_file():
        state = _resume(ckpt, model, opt, sched, dataset.spec_digest, config, args, device)
        log(f"resuming at epoch {state['epoch']}, batch {state['batch']}")

    def checkpoint():
        _atomic_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                      "state": state, "spec_digest": dataset.spec_digest, "config": config.to_dict(),
                      "args": args}, ckpt)

    train_source = source_for(dataset, device, preload, log)
    val_source = None if val_set is None else source_for(val_set, device, preload, log)
    in_memory = isinstance(train_source, InMemory)
    loader_record = {"in_memory": in_memory, "workers": 0 if in_memory else workers}
    t0 = time.perf_counter() - state["train_seconds"]
    stopped = False
    bar = tqdm(total=total, initial=state["epoch"] * n_batches + state["batch"], unit="batch", disable=not progress,
               file=sys.stderr, desc="train")
    try:
        while state["epoch"] < epochs and not stopped:
            epoch = state["epoch"]
            sampler.set_epoch(epoch)
            order = sampler.order()
            model.train()
            first, t_epoch = state["batch"], time.perf_counter()
            loader = batches(train_source, order, batch, first, workers, pin=device == "cuda" and not in_memory,
                             turn=(seed, epoch) if rot90 else None, about_block=config.centre == "main_star")
            for b, (x, y) in enumerate(loader, start=first):
                loss = F.cross_entropy(model(x.to(device, non_blocking=True)), y.to(device, non_blocking=True))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                sched.step()
                state["batch"], state["last_loss"] = b + 1, loss.item()
                state["train_seconds"] = time.perf_counter() - t0
                bar.update(1)
                bar.set_postfix(epoch=epoch, loss=f"{loss.item():.3f}")
                if max_minutes is not None and state["train_seconds"] > 60.0 * max_minutes:
                    stopped = True
                    break
                if state["batch"] % checkpoint_every == 0:
                    checkpoint()
            if stopped:
                break
            # from the state, not the loop: a run resumed after its epoch's last batch runs no batch here
            record = {"epoch": epoch, "last_loss": state["last_loss"],
                      "train_seconds": round(state["train_seconds"], 1),
                      # the batches this process ran of the epoch (None: resumed after its last)
                      "samples_per_s": None if first == n_batches else round(
                          (n_batches - first) * batch / (time.perf_counter() - t_epoch), 1)}
            if val_set is not None:
                record["val"] = evaluate(model, val_source, device, workers=workers)
            state["history"].append(record)
            state["epoch"], state["batch"] = epoch + 1, 0
            checkpoint()
            log(json.dumps(record))
    finally:
        bar.close()
    checkpoint()
    weights = io.BytesIO()
    torch.save(model.cpu().state_dict(), weights)  # CPU tensors wherever it trained: the weights load anywhere
    with atomic_file(out / "weights.pt") as f:
        f.write(weights.getvalue())
    manifest = {
        "model": "starenv.agents.identify.network_model:MainStarNet",
        "config": config.to_dict(),
        "classes_hip": [int(h) for h in classes],
        "camera": _camera(spec),
        "dataset": {"name": dataset.info["name"], "spec_digest": dataset.spec_digest,
                    "content_digest": dataset.content_digest(), "starenv_version": dataset.info["starenv_version"],
                    "samples": len(dataset)},
        "val_dataset": None if val_set is None else {"name": val_set.info["name"],
                                                     "spec_digest": val_set.spec_digest},
        "init": start,
        "git_commit": _git_commit(),
        "command": command,
        "seed": seed, "epochs": epochs, "batch": batch, "lr": lr, "rot90": rot90, "device": device,
        "epochs_done": state["epoch"], "stopped_early": stopped, "loader": loader_record,
        "train_seconds": round(state["train_seconds"], 1),
        "metrics": state["history"],
    }
    manifest.update(manifest_hashes(manifest, weights.getvalue()))
    with atomic_file(out / "manifest.json", "w", encoding="utf-8") as f:
        f.write(json.dumps(manifest, indent=1) + "\n")
    return manifest


def _resume(ckpt: Path, model, opt, sched, spec_digest: str, config: MainStarConfig, args: dict,
            device: str) -> dict:
    """Load ``ckpt`` into the model, optimiser and schedule; its training state.  A checkpoint of another dataset,
    config or result-changing argument (:data:`RESULT_ARGS`), or one that cannot be read, is refused."""
    try:
        saved = torch.load(ckpt, weights_only=True, map_location=device)
    except Exception as exc:  # noqa: BLE001  (torch raises many types for a damaged zip or pickle)
        raise ValueError(f"--resume: {ckpt} cannot be read ({type(exc).__name__}); delete it to start the run "
                         f"again") from exc
    if not isinstance(saved, dict) or not {"model", "optimizer", "scheduler", "state", "args"} <= set(saved):
        raise ValueError(f"--resume: {ckpt} is not a checkpoint of this starenv (keys missing); delete it to start "
                         f"the run again")
    if saved.get("spec_digest") != spec_digest or saved.get("config") != config.to_dict():
        raise ValueError(f"--resume: {ckpt} is from another dataset or model config")
    for key in RESULT_ARGS:
        if saved["args"].get(key) != args[key]:
            raise ValueError(f"--resume: {ckpt} was written with --{key.replace('_', '-')} "
                             f"{saved['args'].get(key)!r}, this command gives {args[key]!r}; resume with the same "
                             f"arguments or train into another --out")
    try:
        model.load_state_dict(saved["model"])
        opt.load_state_dict(saved["optimizer"])
        sched.load_state_dict(saved["scheduler"])
    except (RuntimeError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"--resume: {ckpt} does not fit this model ({type(exc).__name__}); delete it to start the "
                         f"run again") from exc
    state = saved["state"]
    if not (isinstance(state, dict) and isinstance(state.get("epoch"), int) and isinstance(state.get("batch"), int)
            and isinstance(state.get("history"), list)):
        raise ValueError(f"--resume: {ckpt} holds no valid training state; delete it to start the run again")
    state.setdefault("last_loss", None)
    return state


def _class_hips(spec: dict) -> np.ndarray:
    """The dataset's classes (HIP numbers in label order), recomputed from its spec."""
    from starenv.datasets import load_spec, navigation_stars

    return navigation_stars(load_spec(spec))[0]


def _camera(spec: dict) -> dict | None:
    """Head 0's resolution and field of view (deg) in the dataset's scenario, for the agent's check."""
    from starenv.datasets import load_spec

    try:
        cam = load_spec(spec).load_scenario().heads[0].camera
    except ValueError:
        return None
    return {"width": cam.width, "height": cam.height, "fov_deg": [math.degrees(a) for a in cam.fov]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="starenv train", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="training dataset folder (starenv dataset, kind main_star)")
    p.add_argument("--val", default=None, help="validation dataset folder, evaluated after every epoch")
    p.add_argument("--out", required=True, help="run folder: checkpoint.pt, weights.pt, manifest.json")
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--lr", type=float, default=1e-3, help="peak learning rate of the one-cycle schedule (Adam)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--workers", type=int, default=0, help="DataLoader processes reading the shards when they are "
                   "not held in memory (0: this one); the weights do not depend on it")
    p.add_argument("--preload", choices=PRELOAD, default="auto", help="hold the training and validation sets in the "
                   "device's memory (auto: when they take at most half of what is free); the weights do not depend "
                   "on it")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a MainStarConfig field")
    p.add_argument("--rot90", action="store_true", help="augment with rolls by multiples of 90 deg")
    p.add_argument("--max-minutes", type=float, default=None, help="stop (and save) after this much training")
    p.add_argument("--checkpoint-every", type=int, default=100, help="batches between checkpoints")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    p.add_argument("--init", default=None, metavar="RUN", help="start from RUN/weights.pt (same config and classes)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    command = "starenv train " + " ".join(argv if argv is not None else sys.argv[1:])
    manifest = train(args.data, args.out, val=args.val, epochs=args.epochs, batch=args.batch, lr=args.lr,
                     seed=args.seed, device=args.device, config_pairs=args.set, rot90=args.rot90,
                     max_minutes=args.max_minutes, resume=args.resume, checkpoint_every=args.checkpoint_every,
                     progress=not args.quiet, command=command, init=args.init, workers=args.workers,
                     preload=args.preload)
    print(json.dumps(manifest["metrics"][-1] if manifest["metrics"] else {}, indent=None))
    print(f"weights: {Path(args.out) / 'weights.pt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
