"""Paper 002's network (shapes, parameter count) and the training harness (toy task, determinism, resume)."""

import hashlib
import json
import math

import numpy as np
import pytest
import torch

from starenv.agents.identify.network_model import MainStarConfig, MainStarNet, parameter_count
from starenv.agents.identify.network_train import parse_config, train
from starenv.datasets.preprocess import network_input
from starenv.datasets.shards import record_shards, write_npz


def test_paper_architecture_shapes():
    net = MainStarNet(MainStarConfig())  # 4331 classes, 256 input, D 64, depth 8, 6 heads
    frames = torch.from_numpy(network_input(np.full((2, 1024, 1024), 100, dtype=np.uint16), 256))  # paper's sensor
    assert net.preprocess(frames).shape == (2, 1, 256, 256)
    assert net.features(frames).shape == (2, 64, 16, 16)  # four stride-2 stages: 256 tokens of 64
    assert net(frames).shape == (2, 4331)
    with pytest.raises(ValueError, match=r"expected inputs \(B, 256, 256\)"):
        net(torch.zeros(2, 1024, 1024))  # a raw frame must be preprocessed first
    assert len(net.encoder) == 8 and net.encoder[0].attn.heads == 6
    convs = [m for m in net.blocks.modules() if isinstance(m, torch.nn.Conv2d) and m.kernel_size == (3, 3)]
    assert len(convs) == 12  # 6 basic blocks / 12 conv layers


@pytest.mark.parametrize("config", [
    MainStarConfig(),
    MainStarConfig(n_classes=216, input_size=64, stem_width=8, widths=(8, 16, 16, 32, 32, 64), depth=4, mlp_dim=128),
    MainStarConfig(n_classes=10, input_size=32, widths=(4, 8, 8, 8, 16, 16), depth=1, heads=3, head_dim=5),
])
def test_parameter_count_closed_form(config):
    net = MainStarNet(config)
    assert sum(p.numel() for p in net.parameters()) == parameter_count(config)


def test_paper_configuration_size_against_the_paper():
    # The paper's model file is 47.1 MB; with the widths and MLP it does not give, ours has 1.54 M float32
    # parameters (6.1 MB): the same order only if the paper's file held more (e.g. optimiser state).
    n = parameter_count(MainStarConfig())
    assert n == 1_535_611
    assert 4 * n < 47.1e6


def test_bad_config_names_the_field():
    with pytest.raises(ValueError, match="input_size"):
        MainStarConfig(input_size=100)
    with pytest.raises(ValueError, match="--set 'depht=2'"):
        parse_config(["depht=2"], 5)


def _toy_dataset(folder, n, seed):
    """Four classes: a bright spot in one image quadrant on a noisy background (uint16 DN), stored preprocessed."""
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 4, n)
    images = rng.normal(100, 3, (n, 32, 32))
    for img, lab in zip(images, labels, strict=True):
        r, c = 4 + 16 * (lab // 2) + rng.integers(0, 8), 4 + 16 * (lab % 2) + rng.integers(0, 8)
        img[r - 1:r + 2, c - 1:c + 2] += 300
    folder.mkdir()
    shard = {"image": network_input(images.round().astype(np.uint16), 32), "label": labels.astype(np.int32),
             "meta": np.frombuffer(json.dumps({"spec_digest": "toy"}).encode(), dtype=np.uint8)}
    record_shards(folder, "toy", {"shard-00000.npz": write_npz(folder / "shard-00000.npz", shard)})
    info = {"name": "toy", "kind": "main_star", "spec_digest": "toy", "starenv_version": "test", "samples": n,
            "n_shards": 1, "spec": {"shard_size": n}}
    (folder / "dataset.json").write_text(json.dumps(info))


@pytest.fixture
def toy(tmp_path, monkeypatch):
    _toy_dataset(tmp_path / "train", 256, 0)
    _toy_dataset(tmp_path / "val", 128, 1)
    monkeypatch.setattr("starenv.agents.identify.network_train._class_hips", lambda spec: np.arange(1, 5))
    return tmp_path


TOY = ["input_size=32", "stem_width=4", "widths=[4,8,8,8,16,16]", "depth=1", "heads=2", "head_dim=8", "mlp_dim=16"]


def _run(toy, out, **kw):
    return train(toy / "train", toy / out, val=toy / "val", epochs=4, batch=32, lr=1e-2, seed=3, config_pairs=TOY,
                 progress=False, log=lambda *_: None, **kw)


def test_toy_task_trains_to_high_accuracy_deterministically(toy):
    manifest = _run(toy, "a")
    assert manifest["metrics"][-1]["val"]["top1"] >= 0.9  # chance is 0.25
    _run(toy, "b")
    a = torch.load(toy / "a" / "weights.pt", weights_only=True)
    b = torch.load(toy / "b" / "weights.pt", weights_only=True)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert manifest["dataset"]["spec_digest"] == "toy" and manifest["classes_hip"] == [1, 2, 3, 4]
    # the samples' own digest: the shard's bytes, independently hashed
    shard = (toy / "train" / "shard-00000.npz").read_bytes()
    assert manifest["dataset"]["content_digest"] == hashlib.sha256(shard).hexdigest()


def test_init_starts_from_another_runs_weights(toy):
    # the paper's second stage: a run started from the first one's weights.  With a vanishing learning rate one
    # epoch leaves the weights where they were (BatchNorm running statistics aside), so the accuracy is the first
    # run's from the start; a run started from scratch with the same rate stays at chance.
    first = _run(toy, "a")
    second = train(toy / "train", toy / "b", val=toy / "val", epochs=1, batch=32, lr=1e-12, seed=4, config_pairs=TOY,
                   progress=False, log=lambda *_: None, init=toy / "a")
    scratch = train(toy / "train", toy / "c", val=toy / "val", epochs=1, batch=32, lr=1e-12, seed=4, config_pairs=TOY,
                    progress=False, log=lambda *_: None)
    assert first["metrics"][-1]["val"]["top1"] >= 0.9 and second["metrics"][-1]["val"]["top1"] >= 0.9
    assert scratch["metrics"][-1]["val"]["top1"] < 0.5
    a = torch.load(toy / "a" / "weights.pt", weights_only=True)
    b = torch.load(toy / "b" / "weights.pt", weights_only=True)
    learned = [k for k in a if "running" not in k and "num_batches" not in k]
    assert all(torch.allclose(a[k], b[k], atol=1e-6) for k in learned)
    assert second["init"]["weights_sha256"] == hashlib.sha256((toy / "a" / "weights.pt").read_bytes()).hexdigest()
    with pytest.raises(ValueError, match="--init .*do not fit this model config"):
        train(toy / "train", toy / "d", epochs=1, batch=32, seed=4, config_pairs=[*TOY[:-1], "mlp_dim=8"],
              progress=False, log=lambda *_: None, init=toy / "a")


def test_resume_replays_the_interrupted_run(toy):
    _run(toy, "full")
    _run(toy, "cut", max_minutes=0.0)  # stops after the first batch, checkpoint written
    cut = json.loads((toy / "cut" / "manifest.json").read_text())
    assert cut["stopped_early"] and cut["epochs_done"] == 0
    _run(toy, "cut", resume=True)
    a = torch.load(toy / "full" / "weights.pt", weights_only=True)
    b = torch.load(toy / "cut" / "weights.pt", weights_only=True)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_training_has_no_median_and_its_workers_do_not_change_the_weights(toy, monkeypatch):
    """The code path `--device cuda` runs, on the CPU: no median anywhere in a training step (torch has no
    deterministic CUDA median), and batches read by DataLoader workers give the weights of batches read here."""
    def refuse(*args, **kwargs):
        raise AssertionError("median called in a training step")

    monkeypatch.setattr(torch, "median", refuse)
    monkeypatch.setattr(torch.Tensor, "median", refuse)
    monkeypatch.setattr(torch, "nanmedian", refuse)
    # three loader paths, with the rolls drawn per batch: shards read here, by two workers, and the set held in memory
    here = _run(toy, "here", preload="no", rot90=True)
    assert here["loader"] == {"in_memory": False, "workers": 0}
    a = torch.load(toy / "here" / "weights.pt", weights_only=True)
    same = ("epoch", "last_loss", "val")  # not the timings
    for out, kw in (("workers", {"preload": "no", "workers": 2}), ("memory", {"preload": "yes", "workers": 2})):
        other = _run(toy, out, rot90=True, **kw)
        b = torch.load(toy / out / "weights.pt", weights_only=True)
        assert all(torch.equal(a[k], b[k]) for k in a), out
        assert [{k: m[k] for k in same} for m in here["metrics"]] == [{k: m[k] for k in same}
                                                                       for m in other["metrics"]]
        assert other["loader"]["in_memory"] == (out == "memory")
        assert other["dataset"]["content_digest"] == here["dataset"]["content_digest"]


def test_batches_are_the_samples_of_their_indices_turned_as_drawn(toy):
    """Against an independent reading (``np.load`` of the shard, each image turned by ``np.rot90``): the batches
    of both sources, across a shard boundary, and the rolls drawn from (seed, epoch, batch)."""
    from starenv.agents.identify.network_data import InMemory, ShardDataset
    from starenv.agents.identify.network_train import batches

    with np.load(toy / "train" / "shard-00000.npz") as z:
        images, labels = z["image"], z["label"]
    for shard_size in (256, 100):  # one shard; then the same samples in shards of 100 (batches span two)
        folder = toy / f"shards_of_{shard_size}"
        folder.mkdir()
        hashes = {}
        for s in range(math.ceil(256 / shard_size)):
            part = slice(s * shard_size, (s + 1) * shard_size)
            hashes[f"shard-{s:05d}.npz"] = write_npz(folder / f"shard-{s:05d}.npz", {
                "image": images[part], "label": labels[part],
                "meta": np.frombuffer(json.dumps({"spec_digest": "toy"}).encode(), dtype=np.uint8)})
        record_shards(folder, "toy", hashes)
        info = json.loads((toy / "train" / "dataset.json").read_text())
        info.update(n_shards=len(hashes), spec={"shard_size": shard_size})
        (folder / "dataset.json").write_text(json.dumps(info))
        dataset = ShardDataset(folder)
        order = np.random.default_rng(5).permutation(256).tolist()
        for source in (dataset, InMemory(dataset)):
            for b, (x, y) in enumerate(batches(source, order, 96, turn=(7, 2))):
                g = torch.Generator().manual_seed((7 * 1_000_003 + 2) * 1_000_003 + b)
                turns = torch.randint(0, 4, (96,), generator=g).tolist()
                chosen = order[96 * b:96 * (b + 1)]
                expected = np.stack([np.rot90(images[i], q) for i, q in zip(chosen, turns, strict=True)])
                assert np.array_equal(x.numpy(), expected) and y.tolist() == labels[chosen].tolist()
            assert b == 1  # 256 // 96 whole batches


def test_turns_about_the_centre_block_keep_the_main_star_pixel_and_follow_the_index_formula():
    """A turn by 90 deg about pixel (c, c), c = S // 2, where a ``centre = "main_star"`` input holds its main star,
    moves pixel (r, col) to (c - (col - c), c + (r - c)) (``torch.rot90``'s sense), zero where that source lies
    outside the image; checked pixel by pixel for even and odd S.  A turn about the image centre (the frame-centred
    inputs' turn) would move the main star's pixel for an even S."""
    from starenv.agents.identify.network_train import rot90

    for size in (8, 9):
        c = size // 2
        images = torch.arange(1, 64 * size * size + 1, dtype=torch.float32).reshape(64, size, size)
        g = torch.Generator().manual_seed((3 * 1_000_003 + 1) * 1_000_003 + 0)
        turns = torch.randint(0, 4, (64,), generator=g).tolist()
        out = rot90(images, 3, 1, 0, about_block=True)
        assert set(turns) == {0, 1, 2, 3}
        for n, q in enumerate(turns):
            expected = torch.zeros(size, size)
            for i in range(size):
                for j in range(size):
                    r, col = i, j
                    for _ in range(q):  # the source of (r, col) under one more quarter turn
                        r, col = col, 2 * c - r
                    if 0 <= r < size and 0 <= col < size:
                        expected[i, j] = images[n, r, col]
            assert torch.equal(out[n], expected), (size, q)
            assert out[n, c, c] == images[n, c, c]
        frame_turn = rot90(images, 3, 1, 0)
        moved = [n for n, q in enumerate(turns) if q and frame_turn[n, c, c] != images[n, c, c]]
        assert bool(moved) == (size % 2 == 0)


def test_a_set_is_held_in_memory_only_when_it_fits(toy, monkeypatch):
    from starenv.agents.identify import network_data
    from starenv.agents.identify.network_data import ShardDataset, fits_in_memory

    dataset = ShardDataset(toy / "train")
    need = 256 * (32 * 32 * 4 + 8)  # float32 images and int64 labels
    monkeypatch.setattr(network_data, "_host_available_bytes", lambda: 2 * need)
    assert fits_in_memory(dataset, "cpu")
    monkeypatch.setattr(network_data, "_host_available_bytes", lambda: 2 * need - 1)
    assert not fits_in_memory(dataset, "cpu")


@pytest.mark.parametrize("before, after", [(None, ":4096:8"), (":0:0", ":4096:8"), (":16:8", ":16:8")])
def test_cuda_training_sets_a_deterministic_cublas_workspace(monkeypatch, before, after):
    from starenv.agents.identify.network_train import deterministic_cuda_environment

    if before is None:
        monkeypatch.delenv("CUBLAS_WORKSPACE_CONFIG", raising=False)
    else:
        monkeypatch.setenv("CUBLAS_WORKSPACE_CONFIG", before)
    deterministic_cuda_environment()
    import os

    assert os.environ["CUBLAS_WORKSPACE_CONFIG"] == after


def test_a_dataset_of_another_input_size_is_refused(toy):
    info = json.loads((toy / "train" / "dataset.json").read_text())
    info["spec"]["input_size"] = 64
    (toy / "train" / "dataset.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="--set input_size=32: the dataset's images are 64 px"):
        _run(toy, "other")


def test_a_dataset_centred_on_its_main_star_trains_a_network_that_says_so(toy):
    """The spec's ``centre`` reaches the manifest's config (the identifier reads it to recentre its input); a
    ``--set`` that contradicts the dataset is refused."""
    info = json.loads((toy / "train" / "dataset.json").read_text())
    info["spec"]["centre"] = "main_star"
    (toy / "train" / "dataset.json").write_text(json.dumps(info))
    manifest = train(toy / "train", toy / "c", epochs=1, batch=32, seed=3, config_pairs=TOY, progress=False,
                     log=lambda *_: None)
    assert manifest["config"]["centre"] == "main_star"
    with pytest.raises(ValueError, match="--set centre=frame: the dataset's images are centred on the main_star"):
        train(toy / "train", toy / "d", epochs=1, batch=32, seed=3, config_pairs=[*TOY, 'centre="frame"'],
              progress=False, log=lambda *_: None)


def test_the_gpu_run_takes_another_spec_a_config_and_initial_weights_on_the_cpu(tmp_path):
    """benchmarks/paper002_gpu.py, the GPU run's own code path, on the CPU at a tiny size with the real camera's twin
    spec: the run's manifest must record that spec's set and camera (1024 x 768 px), the --set config (not the
    paper-size default) and the --init weights, and the figures the sizes it was told (whole epochs, a fixed set)."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    spec = importlib.util.spec_from_file_location("paper002_gpu", root / "benchmarks" / "paper002_gpu.py")
    gpu = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gpu)
    small = ["stem_width=8", "widths=[8,16,16,32,32,64]", "depth=4", "heads=6", "head_dim=64", "mlp_dim=128",
             "scale_dn=450"]
    shipped = root / "starenv" / "agents" / "identify" / "weights" / "paper002_sky_small"
    args = ["--out", str(tmp_path / "out"), "--work", str(tmp_path / "work"), "--device", "cpu", "--jobs", "1",
            "--workers", "0", "--val", "16", "--samples", "64", "--epochs", "1", "--batch", "16",
            "--spec", str(root / "datasets" / "tetra3_twin_sky.toml"), "--init", str(shipped), "--lr", "1e-4",
            "--total-s", "600", "--limit-s", "900", "--preload", "yes"]
    for pair in small:
        args += ["--set", pair]
    assert gpu.main(args) == 0
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    figures = json.loads((tmp_path / "out" / "figures.json").read_text())
    assert manifest["dataset"]["name"] == "tetra3_twin_sky" and manifest["dataset"]["samples"] == 64
    assert manifest["camera"]["width"] == 1024 and manifest["camera"]["height"] == 768
    assert manifest["config"] == {**parse_config(small + ['centre="main_star"', "input_size=64"], 4559).to_dict()}
    assert manifest["init"]["run"] == str(shipped)
    assert manifest["epochs_done"] == 1 and figures["train"]["epochs_done"] == 1 and figures["input_size"] == 64
