"""Seed 003's ground batch learning of the 2-D Legendre network, in torch as the paper trains it (its Sec. 3.2).

Stars pooled from frames over random sky (:func:`starenv.datasets.pairs.pooled_pairs`) are split 8:2 into training
and test sets at random; the network (:mod:`starenv.agents.correct.legendre`: offsets ``F = W^T b`` at the measured
positions, normalised units) is trained on mini-batches of 128 stars with the point-wise loss ``J_p = E^2 / 2``
(averaged over the batch, the two axes' losses summed; they share no weight), by Adam (lr 1e-4, beta 0.9 / 0.999,
eps 1e-8) followed, each step, by the forgetting factor ``W <- tau W`` (tau = 0.999): the paper's Eq. 25.
Deterministic on CPU for a given seed.  torch is imported inside :func:`train_ground` only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from starenv import checks
from starenv.agents.correct.legendre import ORDER, LegendreModel, design, labels
from starenv.sim.optics import Camera, legendre_mode_count


@dataclass
class GroundResult:
    """The trained model, the indices of the test stars, and the mean training loss of each epoch."""

    model: LegendreModel
    test: np.ndarray
    loss: list[float]


def train_ground(measured: np.ndarray, reference: np.ndarray, camera: Camera, order: int = ORDER,
                 epochs: int = 20, lr: float = 1e-4, batch: int = 128, tau: float = 0.999, train_fraction: float = 0.8,
                 seed: int = 0, initial: LegendreModel | None = None) -> GroundResult:
    """Train the network on pairs ``measured`` / ``reference`` (n, 2) px of ``camera`` (module docstring)."""
    import torch

    checks.integer("epochs", epochs, 1, 10**6)
    checks.integer("batch", batch, 1, 10**7)
    checks.in_range("lr", lr, 0.0, 1.0, low_open=True)
    checks.in_range("tau", tau, 0.0, 1.0, low_open=True)
    checks.in_range("train_fraction", train_fraction, 0.0, 1.0, low_open=True)
    b_all = design(measured, camera, order)
    f_all = labels(measured, reference, camera)
    rng = np.random.default_rng(seed)
    order_idx = rng.permutation(len(b_all))
    n_train = int(round(train_fraction * len(b_all)))
    train, test = order_idx[:n_train], order_idx[n_train:]
    torch.manual_seed(seed)
    b = torch.from_numpy(b_all[train])
    f = torch.from_numpy(f_all[train])
    start = np.zeros((legendre_mode_count(order), 2)) if initial is None else initial.weights
    w = torch.nn.Parameter(torch.from_numpy(np.array(start, dtype=np.float64)))
    opt = torch.optim.Adam([w], lr=lr, betas=(0.9, 0.999), eps=1e-8)
    gen = torch.Generator().manual_seed(seed)
    history = []
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # 128 x 21 products: more threads cost ~20x in synchronisation
    try:
        for _ in range(epochs):
            history.append(_epoch(torch, b, f, w, opt, gen, batch, tau))
    finally:
        torch.set_num_threads(threads)
    return GroundResult(LegendreModel(w.detach().numpy().copy()), test, history)


def _epoch(torch, b, f, w, opt, gen, batch: int, tau: float) -> float:
    """One pass over the training stars in random mini-batches of ``batch``; their mean loss."""
    total = 0.0
    for idx in torch.randperm(len(b), generator=gen).split(batch):
        e = f[idx] - b[idx] @ w
        loss = 0.5 * (e * e).mean(dim=0).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            w.mul_(tau)
        total += float(loss.detach()) * len(idx)
    return total / len(b)
