"""The large Gram matrix's decomposition without its eigenvectors (``GramEigen``): the same
half-inverse direction as ``eigh`` and as the paper's SVD rule, to round-off."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

import adjointsim.train.hig as hig
from adjointsim.train.higs import make_problem


@pytest.mark.parametrize("rank", [300, 200])  # full rank, and a Gram matrix of rank 200
def test_eigenvalues_and_the_applied_eigenvectors_equal_eighs(rank):
    rng = np.random.default_rng(0)
    j = torch.from_numpy(rng.standard_normal((300, 400)) if rank == 300 else
                         rng.standard_normal((300, rank)) @ rng.standard_normal((rank, 400)))
    gram, g = j @ j.T, torch.from_numpy(rng.standard_normal(300))
    lam, u = torch.linalg.eigh(gram)
    eigen = hig.GramEigen(gram)
    assert torch.allclose(eigen.values, lam, rtol=0, atol=1e-13 * float(lam[-1]))
    # eigenvectors are defined up to sign (and within a null space up to rotation): compare
    # what the direction uses, U f(Λ) Uᵀ g over the kept eigenvalues
    keep = lam > 1e-8 * lam[-1]
    scale = torch.where(keep, lam.clamp(min=1e-300) ** -0.75, 0.0)
    ours = eigen.from_eigen(scale * eigen.to_eigen(g))
    theirs = u @ (scale * (u.T @ g))
    assert float((ours - theirs).norm() / theirs.norm()) < 1e-12
    # U is orthogonal: applied to a vector and back it returns the vector
    assert torch.allclose(eigen.to_eigen(eigen.from_eigen(g)), g, rtol=0, atol=1e-12)


@pytest.mark.parametrize("kappa", [0.5, 1.0])
def test_a_large_gram_matrix_gives_the_same_update_as_eigh_and_the_svd_rule(monkeypatch, kappa):
    """Poisson at batch 8 (512 rows of J), the tridiagonal route forced by a lower threshold:
    the same update as ``eigh`` and as the paper's rule (a dense SVD of J) to round-off."""
    problem = make_problem("poisson", 0, "tiny")
    torch.manual_seed(0)
    model = problem.model()
    x, c, t = problem.sample(torch.Generator().manual_seed(1), 8)

    def direction(rows_threshold: int, decomposition: str = "gram") -> torch.Tensor:
        monkeypatch.setattr(hig, "TRIDIAGONAL_ROWS", rows_threshold)
        net = copy.deepcopy(model)
        opt = hig.HalfInverseGradients(net, problem.physics, problem.loss, lr=1.0, kappa=kappa,
                                       tau=1e-5, decomposition=decomposition)
        before = torch.cat([p.detach().flatten() for p in net.parameters()])
        opt.step(x, c, t)
        return torch.cat([p.detach().flatten() for p in net.parameters()]) - before

    tridiagonal, eigh, svd = direction(1), direction(10**9), direction(10**9, "svd")
    assert float((tridiagonal - eigh).norm() / eigh.norm()) < 1e-10
    assert float((tridiagonal - svd).norm() / svd.norm()) < 1e-10
