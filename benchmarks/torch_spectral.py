"""Kuramoto–Sivashinsky ETDRK4 in pure PyTorch (torch.fft), differentiable by autograd: the
PyTorch baseline of ``benchmarks/spectral.py``.

Same discretisation as ``ks1d-etdrk4``, written independently of its kernels:
u_t + u u_x + α u_xx + β u_xxxx = 0 on [0, length), conservative form
N(v) = −½ i k ⊙ rfft(irfft(v)²) (derivative zero at the Nyquist mode; optional 2/3 mask on N),
L = α k² − β k⁴, Kassam–Trefethen ETDRK4 with the contour-integral coefficients of
:func:`adjointsim.spectral.etdrk.etdrk_coefficients`. States are tensors (..., N), any leading
batch axes; gradients come from torch autograd through the whole rollout.
"""

from __future__ import annotations

import numpy as np
import torch

from adjointsim.spectral.etdrk import etdrk_coefficients, reference_step


class TorchKS:
    """ETDRK4 stepper for KS on ``n`` points of [0, ``length``) with step ``dt``."""

    def __init__(
        self,
        n: int = 128,
        length: float = 64.0,
        dt: float = 0.25,
        anti_diffusion: float = 1.0,
        hyper_diffusion: float = 1.0,
        dealias: bool = False,
        dtype: torch.dtype = torch.float64,
    ):
        self.n = n
        k = 2 * np.pi * np.arange(n // 2 + 1) / length
        lin = anti_diffusion * k**2 - hyper_diffusion * k**4
        k_odd = k.copy()
        k_odd[-1] = 0.0  # an odd derivative of a real signal has no Nyquist mode
        g = -0.5j * k_odd * ((np.arange(n // 2 + 1) < n / 3) if dealias else 1.0)
        cdtype = torch.complex128 if dtype == torch.float64 else torch.complex64
        c = etdrk_coefficients(lin, dt, 4)
        self.coef = {key: torch.tensor(v, dtype=cdtype) for key, v in c.items()}
        self.g = torch.tensor(g, dtype=cdtype)

    def nonlinear(self, v: torch.Tensor) -> torch.Tensor:
        return self.g * torch.fft.rfft(torch.fft.irfft(v, self.n) ** 2)

    def step_spectral(self, v: torch.Tensor) -> torch.Tensor:
        return reference_step(v, self.coef, 4, self.nonlinear)

    def step(self, u: torch.Tensor) -> torch.Tensor:
        return torch.fft.irfft(self.step_spectral(torch.fft.rfft(u)), self.n)

    def rollout(self, u0: torch.Tensor, steps: int) -> torch.Tensor:
        """u_steps; the state stays spectral between steps (8 real FFTs per step)."""
        v = torch.fft.rfft(u0)
        for _ in range(steps):
            v = self.step_spectral(v)
        return torch.fft.irfft(v, self.n)


def forward_and_gradient(
    model: TorchKS, u0: np.ndarray, steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """u_steps and the gradient of the loss ½ Σ u_steps² with respect to u0, by autograd."""
    u = torch.tensor(u0, requires_grad=True)
    last = model.rollout(u, steps)
    (0.5 * (last**2).sum()).backward()
    return last.detach().numpy(), u.grad.numpy()
