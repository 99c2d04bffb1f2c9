"""Paper 002's network on a held-out ``main_star`` dataset: top-1 and top-5 of the plain reading and of the readings
``NetworkIdentifier`` averages (1, 2 and 4 turns about the point the network reads its main star at, their
log-probabilities averaged), each with its exact 95 % interval.

The training run's per-epoch figures (``starenv train --val``) are the plain reading's; the identifier ranks with
its ``turns`` (default 4 for a network trained on centred inputs), so its held-out accuracy is the matching row.

    python benchmarks/paper002_heldout.py --data data/sky_small_val [--weights paper002_sky_small] [--threads 2]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from starenv.agents.identify.network import load_network, shipped_weights, turned
from starenv.agents.identify.network_data import InMemory, ShardDataset
from starenv.datasheet import binomial_interval


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="held-out dataset folder (starenv dataset, kind main_star)")
    parser.add_argument("--weights", default="paper002_sky_small", help="a run folder or a shipped name")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--batch", type=int, default=500)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    net, manifest = load_network(shipped_weights(args.weights))
    data = ShardDataset(args.data)
    if data.info["spec"].get("centre", "frame") != net.config.centre:
        raise SystemExit(f"{args.data}: its images are centred on the {data.info['spec'].get('centre', 'frame')}, the "
                         f"network's on the {net.config.centre}")
    held = InMemory(data)
    about_block = net.config.centre == "main_star"
    labels = held.labels.numpy()
    logs = []
    with torch.no_grad():
        for q in range(4):
            logs.append(torch.cat([torch.log_softmax(net(turned(held.images[i:i + args.batch], q, about_block)), 1)
                                   for i in range(0, len(labels), args.batch)]).numpy())
    print(f"{args.weights} on {args.data}: {len(labels)} samples, {net.config.n_classes} classes")
    print(f"{'readings':>9} {'top-1 % (95 % CI)':>22} {'top-5 % (95 % CI)':>22}")
    for turns in (1, 2, 4):
        mean = np.mean([logs[q] for q in range(0, 4, 4 // turns)], axis=0)
        top = np.argsort(-mean, axis=1, kind="stable")[:, :5]
        cells = []
        for k in (1, 5):
            hits = int(np.sum(np.any(top[:, :k] == labels[:, None], axis=1)))
            low, high = binomial_interval(hits, len(labels))
            cells.append(f"{100 * hits / len(labels):6.2f} ({100 * low:.2f}-{100 * high:.2f})")
        print(f"{turns:>9} {cells[0]:>22} {cells[1]:>22}")


if __name__ == "__main__":
    main()
