"""Paper 000's EBPNN (Sec. 3.3, Eqs. 27-32): three 1-10-1 back-propagation networks, bagged, refined just in time.

Network: ``y = W2 . sigmoid(W1 x + b1) + b2`` (1 input, 10 sigmoid hidden units, linear output), in numpy.  The
input is ``ln SUMFC`` and the target the optimal iteration count, both scaled to [0, 1] by the training set's range
(the paper gives no scaling; the log spreads SUMFC's steep small-blur end).  Training minimises the (weighted) mean
squared error plus ``1e-7 |params|^2`` with scipy's L-BFGS from seeded normal initial weights: deterministic.

Improved bagging with just-in-time learning (decisions where the paper is silent):

* three bootstrap sets ``D_i`` drawn with replacement, each the size of ``D``; network ``i`` is trained on ``D_i``
  once (the global networks, shipped);
* for a query ``x_q``, each ``D_i``'s ``k`` samples most similar by Eq. 28, ``S = a exp(-d) + (1 - a) cos(theta)``
  (``a = 0.5``; ``d`` the distance of the scaled inputs; with one positive input ``cos(theta) = 1``, so ``S``
  ranks by distance), form ``D'_i``; network ``i`` is refitted from its global weights on ``D'_i`` with the squared
  errors weighted by ``S`` (Eq. 30) for at most ``JIT_STEPS`` L-BFGS steps;
* the outputs combine with weights ``1 / e_i``, ``e_i`` the mean absolute error of refitted network ``i`` on
  ``D'_i`` (Eq. 32).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from starenv import checks

HIDDEN = 10
N_NETS = 3
L2 = 1e-7
TRAIN_STEPS = 300
JIT_STEPS = 20
JIT_K = 40
JIT_ALPHA = 0.5
N_PARAMS = 3 * HIDDEN + 1  # W1 (10), b1 (10), W2 (10), b2 (1)


def forward(params: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Network output (n,) for scaled inputs ``x`` (n,)."""
    w1, b1, w2, b2 = params[:HIDDEN], params[HIDDEN : 2 * HIDDEN], params[2 * HIDDEN : 3 * HIDDEN], params[-1]
    return (1.0 / (1.0 + np.exp(-(np.outer(x, w1) + b1)))) @ w2 + b2


def _loss(params: np.ndarray, x: np.ndarray, y: np.ndarray, weight: np.ndarray) -> tuple[float, np.ndarray]:
    """Weighted mean squared error plus the L2 penalty, and its gradient (back-propagation)."""
    w1, b1, w2, b2 = params[:HIDDEN], params[HIDDEN : 2 * HIDDEN], params[2 * HIDDEN : 3 * HIDDEN], params[-1]
    hidden = 1.0 / (1.0 + np.exp(-(np.outer(x, w1) + b1)))  # (n, 10)
    resid = hidden @ w2 + b2 - y
    wsum = weight.sum()
    loss = float(weight @ resid**2 / wsum + L2 * params @ params)
    g_out = 2.0 * weight * resid / wsum  # (n,)
    g_hidden = np.outer(g_out, w2) * hidden * (1.0 - hidden)  # (n, 10)
    grad = np.concatenate([g_hidden.T @ x, g_hidden.sum(axis=0), hidden.T @ g_out, [g_out.sum()]])
    return loss, grad + 2.0 * L2 * params


def fit(x: np.ndarray, y: np.ndarray, start: np.ndarray, weight: np.ndarray | None = None,
        steps: int | None = None) -> np.ndarray:
    """Parameters (31,) fitted by at most ``steps`` (default ``TRAIN_STEPS``) L-BFGS steps from ``start`` to scaled
    samples ``x``, ``y`` (n,), optionally weighted."""
    weight = np.ones(len(x)) if weight is None else weight
    res = minimize(_loss, start, args=(x, y, weight), jac=True, method="L-BFGS-B",
                   options={"maxiter": TRAIN_STEPS if steps is None else steps, "gtol": 1e-10, "ftol": 1e-15})
    return res.x


@dataclass
class EnsembleNet:
    """The trained EBPNN: training samples (SUMFC, optimal iterations), scaling, bootstrap sets and global weights."""

    sumfc: np.ndarray  # (n,)
    iterations: np.ndarray  # (n,)
    bags: np.ndarray  # (3, n) sample indices of each bootstrap set
    params: np.ndarray  # (3, 31) global weights of each network
    x_range: np.ndarray  # (2,) ln SUMFC min, max
    y_range: np.ndarray  # (2,) iterations min, max
    seed: int

    @classmethod
    def train(cls, sumfc, iterations, seed: int = 0) -> EnsembleNet:
        """Bootstrap three sets from the samples and train one network on each (deterministic given ``seed``)."""
        s = checks.finite("sumfc", sumfc)
        it = checks.finite("iterations", iterations)
        if s.ndim != 1 or it.shape != s.shape or len(s) < 4 or np.any(s <= 0):
            raise ValueError(f"sumfc and iterations must be matching 1-D arrays of at least 4 samples with sumfc > 0, "
                             f"got shapes {s.shape} and {it.shape}")
        rng = np.random.default_rng(seed)
        lx = np.log(s)
        x_range = np.array([lx.min(), lx.max()])
        y_range = np.array([it.min(), it.max()])
        if np.ptp(x_range) == 0 or np.ptp(y_range) == 0:
            raise ValueError("sumfc and iterations must each take at least two distinct values")
        bags = rng.integers(0, len(s), (N_NETS, len(s)))
        starts = rng.normal(0.0, 1.0, (N_NETS, N_PARAMS))
        net = cls(s, it, bags, np.zeros((N_NETS, N_PARAMS)), x_range, y_range, int(seed))
        x, y = net._scale_x(s), net._scale_y(it)
        net.params = np.stack([fit(x[b], y[b], p0) for b, p0 in zip(bags, starts, strict=True)])
        return net

    def _scale_x(self, sumfc) -> np.ndarray:
        return (np.log(sumfc) - self.x_range[0]) / (self.x_range[1] - self.x_range[0])

    def _scale_y(self, iterations) -> np.ndarray:
        return (np.asarray(iterations, dtype=np.float64) - self.y_range[0]) / (self.y_range[1] - self.y_range[0])

    def global_predict(self, sumfc) -> np.ndarray:
        """The three global networks' mean prediction (iterations, float) for SUMFC values (n,), without JIT."""
        x = self._scale_x(np.atleast_1d(np.asarray(sumfc, dtype=np.float64)))
        y = np.mean([forward(p, x) for p in self.params], axis=0)
        return self.y_range[0] + y * (self.y_range[1] - self.y_range[0])

    def predict(self, sumfc: float) -> float:
        """Eqs. 27-32: the JIT-refined ensemble's iteration count (float) for one SUMFC value."""
        xq = float(self._scale_x(checks.positive("sumfc", sumfc)))
        x_all, y_all = self._scale_x(self.sumfc), self._scale_y(self.iterations)
        outs, weights = [], []
        for bag, p0 in zip(self.bags, self.params, strict=True):
            x, y = x_all[bag], y_all[bag]
            similarity = JIT_ALPHA * np.exp(-np.abs(x - xq)) + (1.0 - JIT_ALPHA)  # Eq. 28, cos(theta) = 1
            near = np.argsort(-similarity, kind="stable")[:JIT_K]
            p = fit(x[near], y[near], p0, similarity[near], JIT_STEPS)
            err = float(np.mean(np.abs(forward(p, x[near]) - y[near])))
            outs.append(float(forward(p, np.array([xq]))[0]))
            weights.append(1.0 / max(err, 1e-9))
        y = float(np.dot(weights, outs) / np.sum(weights))
        return float(self.y_range[0] + y * (self.y_range[1] - self.y_range[0]))

    def save(self, path) -> None:
        """Write the ensemble to an ``.npz`` file (a few KB)."""
        np.savez(path, sumfc=self.sumfc, iterations=self.iterations, bags=self.bags.astype(np.int32),
                 params=self.params, x_range=self.x_range, y_range=self.y_range, seed=np.int64(self.seed))

    @classmethod
    def load(cls, path) -> EnsembleNet:
        """Read an ensemble written by :meth:`save`."""
        with np.load(path) as z:
            missing = {"sumfc", "iterations", "bags", "params", "x_range", "y_range", "seed"} - set(z.files)
            if missing:
                raise ValueError(f"{path}: not an iteration-net file, missing {sorted(missing)}")
            return cls(z["sumfc"], z["iterations"], z["bags"].astype(np.int64), z["params"], z["x_range"],
                       z["y_range"], int(z["seed"]))
