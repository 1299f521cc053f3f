"""``poisson64``: the Poisson problem (:mod:`adjointsim.train.higs.poisson`: the same grid, data,
network and Adam) with HIG and GN at the paper's batch of 64 instead of 4, at the reference's
lr 0.01 on the gradient of ½ Σ_batch, 0.01 · 64/2 on our batch mean. An update is the
eigendecomposition of a 4096 × 4096 Gram matrix: about 12 s on one core (the tridiagonal route
of :class:`adjointsim.train.hig.GramEigen`), a few hundred updates in the paper's hour."""

from __future__ import annotations

from typing import ClassVar

from . import PROBLEMS
from .poisson import PoissonInverse

BATCH = 64


@PROBLEMS.register
class PoissonInverse64(PoissonInverse):
    """The Laplacian's inverse, HIG and GN at batch 64."""

    name = "poisson64"
    BUDGET: ClassVar[float] = 3600.0
    SETTINGS: ClassVar = {**PoissonInverse.SETTINGS,
                          "hig": {"batch": BATCH, "lr": 0.01 * BATCH / 2, "tau": 1e-5},
                          "gn": {"batch": BATCH, "lr": 0.01 * BATCH / 2, "tau": 1e-5}}
