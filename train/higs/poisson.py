"""``poisson``: 8×8 cells of unit width (the reference's PhiFlow grid), zero Dirichlet, the
5-point Laplacian of ``poisson2d``. As in the reference: x* is PhiFlow's ``Noise`` (a periodic
field with a 1/k² spectrum, zero mean and unit standard deviation per sample), y = Δ x*; the
network 64 → 64 → 128 → 64 → 64 (tanh) maps y to x̂, loss ‖Δ x̂ − y‖², fresh samples every
step. Adam batch 64, lr 3e-4; HIG τ = 1e-5. The reference's HIG lr 0.01 acts on the gradient of
½ Σ_batch ‖Δ x̂ − y‖², b/2 times ours (the batch mean of ‖·‖²), so ours is 0.01 · b/2.
Deviation: HIG and GN use batch 4, not 64: at 64 one update takes 26 s on one core (nearly all
of it the eigendecomposition of the 4096 × 4096 Gram matrix), 23 updates in 600 s."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch

from adjointsim.nets.mlp import MLP
from adjointsim.solvers.poisson import Poisson2D

from ..hig import TorchPhysics
from . import DTYPE, PROBLEMS, Batch, HigProblem

#: the HIG and GN batch (the deviation above)
BATCH = 4


def five_point_laplacian(x: torch.Tensor, inv_h2: float, n: int) -> torch.Tensor:
    """The 5-point Δ_h with zero Dirichlet boundaries on flattened n × n fields (b, n²)."""
    u = torch.nn.functional.pad(x.reshape(-1, 1, n, n), (1, 1, 1, 1))
    c = u[..., 1:-1, 1:-1]
    lap = u[..., :-2, 1:-1] + u[..., 2:, 1:-1] + u[..., 1:-1, :-2] + u[..., 1:-1, 2:] - 4 * c
    return (inv_h2 * lap).reshape(x.shape[0], n * n)


def phiflow_noise(rng: np.random.Generator, count: int, n: int) -> np.ndarray:
    """``count`` fields like PhiFlow's ``Noise()`` on n × n unit cells, flattened (count, n²):
    complex white noise times 1/k² (k = 0 dropped), real part, unit std, zero mean."""
    k = np.fft.fftfreq(n) * n
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    weight = np.divide(1.0, k2, out=np.zeros_like(k2), where=k2 > 0)
    z = rng.standard_normal((count, n, n)) + 1j * rng.standard_normal((count, n, n))
    x = np.fft.ifft2(z * weight).real
    x /= x.std(axis=(1, 2), keepdims=True)
    x -= x.mean(axis=(1, 2), keepdims=True)
    return x.reshape(count, n * n)


@PROBLEMS.register
class PoissonInverse(HigProblem):
    """A network that inverts the Laplacian: y ↦ x̂ with Δ x̂ = y."""

    name = "poisson"
    SOLVER = Poisson2D
    # h = length / (n + 1) = 1: the reference's unit cells
    SCENE: ClassVar[dict[str, Any]] = {"n": 8, "length": 9.0}
    FIXED: ClassVar[dict[str, Any]] = {"bc": "dirichlet", "kappa": 0.0}
    SETTINGS: ClassVar = {"adam": {"batch": 64, "lr": 3e-4},
                          "hig": {"batch": BATCH, "lr": 0.01 * BATCH / 2, "tau": 1e-5},
                          "gn": {"batch": BATCH, "lr": 0.01 * BATCH / 2, "tau": 1e-5}}
    DATA: ClassVar = {"tiny": 64, "full": 1024}

    def __init__(self, seed: int, size: str = "full", scene: dict[str, Any] | None = None):
        super().__init__(seed, size, scene)
        n, inv_h2 = self.solver.n, self.solver.inv_h2
        self.physics = TorchPhysics(lambda f, _c: five_point_laplacian(f, inv_h2, n))
        test_y = self.fields(np.random.default_rng(seed), self.count)
        self.test = (test_y, torch.zeros(self.count, 0, dtype=DTYPE), test_y)
        self.pool: list[torch.Tensor] = []

    def fields(self, rng: np.random.Generator, count: int) -> torch.Tensor:
        """``count`` right-hand sides y = Δ x*, x* PhiFlow noise."""
        n = self.solver.n
        noise = torch.from_numpy(phiflow_noise(rng, count, n))
        return five_point_laplacian(noise, self.solver.inv_h2, n)

    def sample(self, gen: torch.Generator, batch: int) -> Batch:
        # Fresh fields every step, made 4096 at a time (one FFT batch, not one per step).
        if not self.pool or self.pool[0].shape[0] < batch:
            rng = np.random.default_rng(int(torch.randint(2**62, (1,), generator=gen)))
            self.pool[:] = [self.fields(rng, max(4096, batch))]
        y, self.pool[0] = self.pool[0][:batch], self.pool[0][batch:]
        return y, torch.zeros(batch, 0, dtype=DTYPE), y

    def state_dict(self) -> dict[str, Any]:
        return {"pool": list(self.pool)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.pool[:] = state["pool"]

    def model(self) -> torch.nn.Module:
        n = self.solver.n
        return MLP(n * n, n * n, widths=(64, 128, 64), activation="tanh").to(DTYPE)
