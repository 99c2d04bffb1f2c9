"""Paper 003's ground batch learning of the 2-D Legendre network, in torch as the paper trains it (its Sec. 3.2).

Stars pooled from frames over random sky (:func:`starenv.datasets.pairs.pooled_pairs`) are split 8:2 into training
and test sets at random; the network (:mod:`starenv.agents.correct.legendre`: offsets ``F = W^T b`` at the measured
positions, normalised units) is trained on mini-batches of 128 stars with the point-wise loss ``J_p = E^2 / 2``
(averaged over the batch, the two axes' losses summed; they share no weight), by Adam (lr 1e-4, beta 0.9 / 0.999,
eps 1e-8) followed, each step, by the forgetting factor ``W <- tau W`` (tau = 0.999): the paper's Eq. 25.
Deterministic on CPU for a given seed.  torch is imported inside :func:`train_ground` only.

    python -m starenv.agents.correct.ground SCENARIO --out ground.npz [--frames 200] [--method lstsq|torch]

writes ground weights for ``LegendreCorrector(weights="ground.npz")``.
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
    torch.set_num_threads(1)  # 128 x 21 products: far too small to repay the threads' synchronisation
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


def main(argv: list[str] | None = None) -> None:
    """Ground weights for a scenario's head 0 from random-sky pairs, written as a ``.npz`` that
    ``LegendreCorrector(weights=...)`` starts from."""
    import argparse

    from starenv import scenario as scenario_mod
    from starenv.agents.correct.legendre import fit_least_squares
    from starenv.datasets.pairs import pooled_pairs

    parser = argparse.ArgumentParser(prog="python -m starenv.agents.correct.ground", description=main.__doc__)
    parser.add_argument("scenario", help="bundled scenario name or TOML path")
    parser.add_argument("--out", required=True, help="output .npz")
    parser.add_argument("--frames", type=int, default=200, help="random-sky frames (default 200)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--method", choices=("lstsq", "torch"), default="lstsq",
                        help="closed-form least squares (default) or the paper's Adam training")
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--order", type=int, default=ORDER)
    args = parser.parse_args(argv)
    sc = scenario_mod.load(args.scenario)
    cam = sc.heads[0].calibrated
    pairs = pooled_pairs(sc, args.seed, args.frames)
    if args.method == "lstsq":
        model = LegendreModel(fit_least_squares(pairs.measured, pairs.reference, cam, args.order))
    else:
        model = train_ground(pairs.measured, pairs.reference, cam, args.order, args.epochs, seed=args.seed).model
    model.save(args.out)
    residual = np.abs(model.correct(pairs.distorted, cam) - pairs.reference).mean(axis=0)
    print(f"{args.out}: {len(pairs)} stars, residual on them {residual[0]:.4f} / {residual[1]:.4f} px (x / y)")


if __name__ == "__main__":
    main()
