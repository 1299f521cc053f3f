"""Balancing a loss of several named terms: weights λ_k of L = Σ_k λ_k L_k, or an update
direction combined from the terms' gradients.

``Weighting(names, rule=...)`` holds the weights and the history of one run; ``rule`` names one
scheme of :data:`SCHEMES` (one class each below, whose docstring gives its rule, its constants
and its paper). A scheme refreshes from what it :attr:`Scheme.needs`:

* nothing: ``uniform``, ``epsilon-optimal`` (constant weights);
* the terms' loss values: ``softadapt``, ``relobralo``;
* each term's full parameter gradient: ``inverse-dirichlet``, ``max-avg``, ``mgda``,
  ``gradnorm`` (which reads only its output layer's part), and the direction schemes
  ``pcgrad`` and ``config``, which return an update direction instead of weights (their λ
  stay 1);
* each term's per-sample residuals: ``ntk``.

Per-term gradients come from one batched reverse pass over the stacked terms
(:func:`term_gradients`, ``torch.autograd.grad(..., is_grads_batched=True)``), and the update
Σ_k λ_k g_k is combined from them, with no further reverse pass. A graph with an
operation that has no batching rule (the forward-Laplacian route of
:mod:`adjointsim.nets.taylor`, whose reverse pass is hand-written in NumPy) cannot be batched;
for it the gradients are taken one term after another, which costs no more than one pass of
their sum where the terms' graphs are disjoint (the Poisson residual and boundary terms).

Weights refresh every ``every`` steps (steps 0, every, 2·every, ...); ``mgda``, ``gradnorm``,
``softadapt``, ``relobralo`` and the direction schemes at every step, since their rules act on
consecutive steps or on the step's own gradients. A refresh acts on the step that triggers it.

Guard: a term whose gradient or loss gives a zero or non-finite statistic keeps its weight, and
a failed reference leaves every weight as it is; no weight becomes inf or NaN.

Terms may join one after another (sequential training): :meth:`Weighting.backward` and
:meth:`Weighting.update` take the *active* terms only, and an absent term keeps its weight.

:attr:`Weighting.history` holds ``{"step": s, "<name>": λ, ...}`` at every refresh on a
multiple of ``every`` (ID and max/avg add each term's gradient spread ``spread/<name>``). The
class serves any multi-term loss: :meth:`Weighting.backward` takes the named terms and the
parameters they act on and leaves the combined gradient in ``p.grad``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import ClassVar

import numpy as np
import torch


def term_gradients(outputs: torch.Tensor, params: Sequence[torch.Tensor],
                   retain_graph: bool = False) -> torch.Tensor:
    """The gradient of each entry of the 1-D ``outputs`` with respect to ``params``, as the
    rows of an (M, P) matrix (the parameters flattened and concatenated in order, zero where an
    output does not reach a parameter): one batched reverse pass with the identity's rows as
    cotangents."""
    eye = torch.eye(len(outputs), dtype=outputs.dtype, device=outputs.device)
    grads = torch.autograd.grad(outputs, params, eye, retain_graph=retain_graph,
                                allow_unused=True, is_grads_batched=True)
    return torch.cat([torch.zeros(len(outputs), p.numel(), dtype=p.dtype, device=p.device)
                      if g is None else g.reshape(len(outputs), -1)
                      for g, p in zip(grads, params)], dim=1)


def _flat(grads: torch.Tensor | Sequence[torch.Tensor | None]) -> torch.Tensor:
    if isinstance(grads, torch.Tensor):
        return grads.reshape(-1)
    parts = [g.reshape(-1) for g in grads if g is not None]
    return torch.cat(parts) if parts else torch.zeros(0)


def _last_layer(params: Sequence[torch.Tensor]) -> slice:
    """Where the last parameter of two or more dimensions lies in the flattened parameters."""
    sizes = [p.numel() for p in params]
    last = max((i for i, p in enumerate(params) if p.ndim >= 2), default=len(params) - 1)
    return slice(sum(sizes[:last]), sum(sizes[:last + 1]))


def _usable(x: float) -> bool:
    return math.isfinite(x) and x > 0.0


def _softmax(x: Sequence[float]) -> list[float]:
    top = max(x)
    e = [math.exp(v - top) for v in x]
    return [v / sum(e) for v in e]


# ----------------------------------------------------------------------------- the schemes
class Scheme:
    """One rule. A refresh sets ``self.w.weights`` of the active terms (the keys of ``losses``)
    and returns extra history columns; a direction scheme's :meth:`combine` maps the (K, P)
    per-term gradients to the update instead."""

    name: ClassVar[str]
    #: what a refresh needs: "" (never refreshed), "losses", "grads" or "residuals"
    needs: ClassVar[str] = ""
    #: refreshed from the output layer's part of each gradient only: the last parameter of
    #: two or more dimensions
    layer: ClassVar[bool] = False
    #: refreshed at every step rather than every ``every`` steps
    each_step: ClassVar[bool] = False
    direction: ClassVar[bool] = False

    def __init__(self, w: Weighting) -> None:
        self.w = w

    def refresh(self, step: int, losses: dict[str, float],
                grads: dict[str, torch.Tensor]) -> dict[str, float]:
        return {}

    def combine(self, grads: torch.Tensor, step: int) -> torch.Tensor:
        raise NotImplementedError

    def state(self) -> dict:
        """What the scheme remembers between steps (kept in checkpoints)."""
        return {}

    def load(self, state: Mapping) -> None:
        pass


#: every scheme by name
SCHEMES: dict[str, type[Scheme]] = {}


def _scheme(cls: type[Scheme]) -> type[Scheme]:
    SCHEMES[cls.name] = cls
    return cls


@_scheme
class Uniform(Scheme):
    """``uniform``: every λ_k = 1."""

    name = "uniform"


@_scheme
class EpsilonOptimal(Scheme):
    """``epsilon-optimal``: the constant weights given as ``fixed``, e.g. the Poisson
    problem's analytic ε-optimal λ_res = 1/(1 + ω⁴), λ_bc = 1 − λ_res (Maddu et al., MLST 2022);
    a term without one gets 1. Also spelled ``fixed`` (the name earlier runs were recorded
    under) and ``analytic``."""

    name = "epsilon-optimal"


@_scheme
class InverseDirichlet(Scheme):
    """``inverse-dirichlet`` (ID, Maddu, Sturm, Müller & Sbalzarini, MLST 2022): g_k = ∇_θ L_k
    over every parameter, concatenated; its spread s_k = std(g_k). Every ``every`` steps the
    target is λ̂_k = s_ref / s_k and λ_k ← (1 − α) λ_k + α λ̂_k (α = 0.5, all λ start at 1).
    ``reference`` names the reference term, which keeps λ = 1 (the authors' code: the PDE
    residual); ``reference=None`` takes the active term with the largest spread at each update
    (s_ref = max_k s_k), as several later implementations do, and so does a named reference
    while it is absent. Both equalise λ_k² Var(g_k)."""

    name = "inverse-dirichlet"
    needs = "grads"

    def refresh(self, step: int, losses: dict[str, float],
                grads: dict[str, torch.Tensor]) -> dict[str, float]:
        spread = _spreads(grads)
        ref = self.w.reference if self.w.reference in grads else None
        if ref is None:
            ref = max((n for n in grads if _usable(spread[n])), key=spread.get, default=None)
        if ref is not None and _usable(spread[ref]):
            for n in grads:
                if n != self.w.reference and _usable(spread[n]):
                    self.w.blend(n, spread[ref] / spread[n])
        return {f"spread/{n}": s for n, s in spread.items()}


def _spreads(grads: Mapping[str, torch.Tensor]) -> dict[str, float]:
    return {n: float(g.std(unbiased=False)) if g.numel() else 0.0 for n, g in grads.items()}


@_scheme
class MaxAvg(Scheme):
    """``max-avg``: learning-rate annealing (Wang, Teng & Perdikaris, SIAM J. Sci. Comput.
    2021), as in the authors' reference code: λ̂_k = max|g_ref| / mean|λ_k g_k| with the
    *current* λ_k inside the mean, and ID's moving average every ``every`` steps. Needs a named
    reference term (the PDE residual); nothing changes while it is absent."""

    name = "max-avg"
    needs = "grads"

    def refresh(self, step: int, losses: dict[str, float],
                grads: dict[str, torch.Tensor]) -> dict[str, float]:
        spread = _spreads(grads)
        ref = self.w.reference
        if ref in grads:
            top = float(grads[ref].abs().max()) if grads[ref].numel() else 0.0
            if _usable(top):
                for n, g in grads.items():
                    if n == ref or not _usable(spread[n]):
                        continue
                    avg = float((self.w.weights[n] * g).abs().mean())
                    if _usable(avg):
                        self.w.blend(n, top / avg)
        return {f"spread/{n}": s for n, s in spread.items()}


@_scheme
class MGDA(Scheme):
    """``mgda``: the multiple-gradient descent algorithm (Désidéri, C. R. Math. 2012; Sener &
    Koltun, NeurIPS 2018). The update is the min-norm point of the convex hull of the per-term
    gradients, Σ_k α_k g_k with α = argmin {‖Σ_k α_k g_k‖² : α ≥ 0, Σ_k α_k = 1}; the weights
    are α. Solved exactly on the K × K Gram matrix (:func:`min_norm`) rather than by Sener &
    Koltun's Frank–Wolfe iterations, which approximate the same point; the gradients are not
    normalised (their optional scaling left out). Every step."""

    name = "mgda"
    needs = "grads"
    each_step = True

    def refresh(self, step: int, losses: dict[str, float],
                grads: dict[str, torch.Tensor]) -> dict[str, float]:
        g = torch.stack(list(grads.values())).double()
        gram = (g @ g.T).numpy()
        if np.isfinite(gram).all():
            self.w.weights.update(zip(grads, map(float, min_norm(gram))))
        return {}


def min_norm(gram: np.ndarray) -> np.ndarray:
    """α on the simplex minimising αᵀ M α for the Gram matrix M: on every face S the stationary
    point of the KKT system `[M_SS 1; 1ᵀ 0] [α; μ] = [0; 1]` (least squares where M_SS is
    singular); the feasible one of least value. Exact, 2^K − 1 small solves."""
    k = len(gram)
    best, value = np.eye(k)[0], math.inf
    for size in range(1, k + 1):
        for face in itertools.combinations(range(k), size):
            kkt = np.ones((size + 1, size + 1))
            kkt[:size, :size] = gram[np.ix_(face, face)]
            kkt[size, size] = 0.0
            rhs = np.zeros(size + 1)
            rhs[size] = 1.0
            a = np.linalg.lstsq(kkt, rhs, rcond=None)[0][:size]
            if (a < -1e-12).any() or abs(a.sum() - 1.0) > 1e-9:
                continue
            alpha = np.zeros(k)
            alpha[list(face)] = np.clip(a, 0.0, None) / np.clip(a, 0.0, None).sum()
            v = alpha @ gram @ alpha
            if v < value:
                best, value = alpha, v
    return best


@_scheme
class GradNorm(Scheme):
    """``gradnorm`` (Chen, Badrinarayanan, Lee & Rabinovich, ICML 2018). On the last shared
    layer W (here: the output layer, the last parameter of two or more dimensions given)
    G_k = λ_k ‖∇_W L_k‖, Ḡ = mean_k G_k; the relative inverse training rate is
    r_k = L̃_k / mean_j L̃_j with L̃_k = L_k(t) / L_k(0) (L_k(0): the loss when the term first
    takes part). The weights take a gradient step on L_grad = Σ_k |G_k − Ḡ r_k^a| with the
    targets Ḡ r_k^a held constant, as in the paper:
    λ_k ← λ_k − η sign(G_k − Ḡ r_k^a) ‖∇_W L_k‖, clipped at 0 and renormalised to
    Σ_k λ_k = K. Constants (choices: the paper tunes both per problem and steps λ with the
    network's optimiser): a = 1.5, η = 0.025, plain gradient steps. Every step, on the
    terms' full gradients, so that the update costs no further reverse pass."""

    name = "gradnorm"
    needs = "grads"
    layer = True
    each_step = True
    asymmetry = 1.5
    rate = 0.025

    def __init__(self, w: Weighting) -> None:
        super().__init__(w)
        self.initial: dict[str, float] = {}

    def refresh(self, step: int, losses: dict[str, float],
                grads: dict[str, torch.Tensor]) -> dict[str, float]:
        for n, v in losses.items():
            if n not in self.initial and _usable(v):
                self.initial[n] = v
        names = [n for n in grads if n in self.initial]
        norms = {n: float(torch.linalg.vector_norm(grads[n].double())) for n in names}
        ratio = {n: losses[n] / self.initial[n] for n in names}
        if len(names) < 2 or not all(math.isfinite(norms[n]) and _usable(ratio[n])
                                     for n in names):
            return {}
        lam = self.w.weights
        g = {n: lam[n] * norms[n] for n in names}
        mean_g, mean_r = sum(g.values()) / len(names), sum(ratio.values()) / len(names)
        new = {}
        for n in names:
            target = mean_g * (ratio[n] / mean_r) ** self.asymmetry
            sign = (g[n] > target) - (g[n] < target)
            new[n] = max(lam[n] - self.rate * sign * norms[n], 0.0)
        total = sum(new.values())
        if _usable(total):
            lam.update({n: len(names) * v / total for n, v in new.items()})
        return {}

    def state(self) -> dict:
        return {"initial": dict(self.initial)}

    def load(self, state: Mapping) -> None:
        self.initial = dict(state.get("initial", {}))


@_scheme
class SoftAdapt(Scheme):
    """``softadapt`` (Heydari, Thompson & Mehmood, arXiv:1912.12355, 2019): from each loss's
    rate of change between consecutive steps s_k = L_k(t) − L_k(t − 1),
    λ_k = K exp(β s_k) / Σ_j exp(β s_j) with β = 0.1. Choices: the paper's basic variant
    (neither normalised rates nor loss-weighted); its weights sum to 1, here to K, so that
    equal rates give uniform's λ = 1. Every step; a term keeps its weight until it has a
    previous loss."""

    name = "softadapt"
    needs = "losses"
    each_step = True
    beta = 0.1

    def __init__(self, w: Weighting) -> None:
        super().__init__(w)
        self.previous: dict[str, float] = {}

    def refresh(self, step: int, losses: dict[str, float],
                grads: dict[str, torch.Tensor]) -> dict[str, float]:
        names = [n for n in losses if n in self.previous]
        rates = [self.beta * (losses[n] - self.previous[n]) for n in names]
        self.previous = dict(losses)
        if names and all(math.isfinite(r) for r in rates):
            self.w.weights.update(zip(names, (len(names) * p for p in _softmax(rates))))
        return {}

    def state(self) -> dict:
        return {"previous": dict(self.previous)}

    def load(self, state: Mapping) -> None:
        self.previous = dict(state.get("previous", {}))


@_scheme
class ReLoBRaLo(Scheme):
    """``relobralo``: relative loss balancing with random lookback (Bischof & Kraus,
    arXiv:2110.09813, 2021). With bal_k(t, t') = K softmax_k(L_k(t) / (T L_k(t'))),
    λ_k(t) = α [ρ λ_k(t − 1) + (1 − ρ) bal_k(t, 0)] + (1 − α) bal_k(t, t − 1), where ρ is a
    Bernoulli draw of mean E[ρ] per step and t = 0 is the term's first step. Constants (a
    choice within the ranges the paper explores): α = 0.999, E[ρ] = 0.999, T = 0.1. ρ is drawn
    from (seed, step), so a resumed run draws alike. Every step; a term keeps its weight until
    it has a previous loss."""

    name = "relobralo"
    needs = "losses"
    each_step = True
    alpha, expected_rho, temperature = 0.999, 0.999, 0.1

    def __init__(self, w: Weighting) -> None:
        super().__init__(w)
        self.initial: dict[str, float] = {}
        self.previous: dict[str, float] = {}

    def balance(self, losses: Mapping[str, float], ref: Mapping[str, float]) -> list[float]:
        bal = _softmax([losses[n] / (self.temperature * ref[n]) for n in losses])
        return [len(losses) * b for b in bal]

    def refresh(self, step: int, losses: dict[str, float],
                grads: dict[str, torch.Tensor]) -> dict[str, float]:
        now = {n: losses[n] for n in losses if n in self.previous}
        fine = all(_usable(v) for v in (*now.values(), *(self.previous[n] for n in now)))
        if now and fine:
            rho = float(np.random.default_rng([self.w.seed, step]).random() < self.expected_rho)
            first = self.balance(now, self.initial)
            last = self.balance(now, self.previous)
            for n, b0, b1 in zip(now, first, last):
                hist = rho * self.w.weights[n] + (1.0 - rho) * b0
                self.w.weights[n] = self.alpha * hist + (1.0 - self.alpha) * b1
        for n, v in losses.items():
            if _usable(v):
                self.initial.setdefault(n, v)
                self.previous[n] = v
        return {}

    def state(self) -> dict:
        return {"initial": dict(self.initial), "previous": dict(self.previous)}

    def load(self, state: Mapping) -> None:
        self.initial = dict(state.get("initial", {}))
        self.previous = dict(state.get("previous", {}))


@_scheme
class NTK(Scheme):
    """``ntk`` (Wang, Yu & Perdikaris, J. Comput. Phys. 2022): from the neural tangent kernel
    of each term's per-sample residuals r_k (given to :meth:`Weighting.backward` as
    ``residuals``), t_k = Tr(J_k J_kᵀ) / N_k = mean_i ‖∇_θ r_{k,i}‖², the target is
    λ̂_k = Σ_j t_j / t_k and λ_k ← (1 − α) λ_k + α λ̂_k every ``every`` steps (α = 1: the
    paper's rule). Choice: the trace per sample rather than the paper's sum, so that the weights
    do not follow how many points each term has or is sampled with."""

    name = "ntk"
    needs = "residuals"

    def refresh(self, step: int, losses: dict[str, float],
                grads: dict[str, torch.Tensor]) -> dict[str, float]:
        trace = {n: float(j.double().square().sum(dim=1).mean()) for n, j in grads.items()}
        total = sum(trace.values())
        if _usable(total):
            for n, t in trace.items():
                if _usable(t):
                    self.w.blend(n, total / t)
        return {}


@_scheme
class PCGrad(Scheme):
    """``pcgrad``: projecting conflicting gradients (Yu, Kumar, Gupta, Levine, Hausman & Finn,
    NeurIPS 2020). Each g_i, against every other term's original g_j in a random order, loses
    its component along g_j where they conflict (g_i · g_j < 0):
    g_i ← g_i − (g_i · g_j / ‖g_j‖²) g_j; the update is the sum of the projected gradients. The
    order is drawn from (seed, step), so a resumed run draws alike. Every step."""

    name = "pcgrad"
    needs = "grads"
    each_step = True
    direction = True

    def combine(self, grads: torch.Tensor, step: int) -> torch.Tensor:
        rng = np.random.default_rng([self.w.seed, step])
        norms2 = (grads * grads).sum(dim=1)
        out = grads.clone()
        for i in range(len(grads)):
            for j in rng.permutation(len(grads)):
                dot = out[i] @ grads[j]
                if j != i and dot < 0 and norms2[j] > 0:
                    out[i] -= dot / norms2[j] * grads[j]
        return out.sum(dim=0)


@_scheme
class ConFIG(Scheme):
    """``config``: conflict-free inverse gradients (Liu, Chu & Thuerey, arXiv:2408.11104, 2024).
    With the unit gradients ĝ_k = g_k / ‖g_k‖ as the rows of Ĝ, g_u = Ĝ⁺ 1 is the direction of
    equal cosine to every term's gradient; with its unit vector ĝ_u the update is
    (Σ_k g_k · ĝ_u) ĝ_u, the paper's default length (the sum of the gradients' projections).
    Ĝ⁺ 1 = Ĝᵀ (Ĝ Ĝᵀ)⁺ 1, from the K × K Gram matrix. Terms with a zero gradient are left out.
    Every step."""

    name = "config"
    needs = "grads"
    each_step = True
    direction = True

    def combine(self, grads: torch.Tensor, step: int) -> torch.Tensor:
        norms = torch.linalg.vector_norm(grads, dim=1)
        g = grads[norms > 0]
        if not len(g):
            return grads.sum(dim=0)
        unit = g / norms[norms > 0, None]
        u = unit.T @ (torch.linalg.pinv(unit @ unit.T) @ torch.ones(len(g), dtype=g.dtype))
        u = u / torch.linalg.vector_norm(u)
        return (g @ u).sum() * u


#: the scheme names, as the command line offers them
RULES = tuple(SCHEMES)
#: the schemes any loss of named terms takes; the others need what only some problems have:
#: analytic weights (``epsilon-optimal``) or per-sample residuals (``ntk``)
GENERIC = tuple(n for n, s in SCHEMES.items()
                if s.needs != "residuals" and n != "epsilon-optimal")
#: other spellings accepted on the command line, mapped to a scheme
ALIASES = {"id": "inverse-dirichlet", "maxavg": "max-avg", "analytic": "fixed"}
#: earlier names of schemes, kept as written: runs and study rows were recorded under them, and
#: a run resumes only under the configuration it was recorded with
RECORDED = {"fixed": "epsilon-optimal"}


def canonical_rule(rule: str) -> str:
    """The name ``rule`` is recorded under: a scheme's name, or an earlier one of
    :data:`RECORDED`."""
    rule = ALIASES.get(rule, rule)
    if rule not in SCHEMES and rule not in RECORDED:
        raise ValueError(f"unknown weighting {rule!r}; choose from {', '.join(RULES)} "
                         f"(or {', '.join((*ALIASES, *RECORDED))})")
    return rule


def scheme_name(rule: str) -> str:
    """The scheme ``rule`` (any accepted spelling) names."""
    rule = canonical_rule(rule)
    return RECORDED.get(rule, rule)


# ----------------------------------------------------------------------------- the weights
class Weighting:
    """The weights of the named loss terms ``names`` under ``rule`` (see the module doc).
    ``reference``: the reference term of ID and max/avg; ``alpha``: the moving-average factor
    of ID, max/avg and NTK; ``every``: steps between refreshes; ``fixed``: the constant
    weights of ``epsilon-optimal``; ``seed``: the random draws of PCGrad and ReLoBRaLo."""

    def __init__(
        self,
        names: Sequence[str],
        rule: str = "uniform",
        reference: str | None = None,
        alpha: float = 0.5,
        every: int = 5,
        fixed: Mapping[str, float] | None = None,
        seed: int = 0,
    ):
        self.names = tuple(names)
        if len(set(self.names)) != len(self.names) or not self.names:
            raise ValueError(f"loss term names must be distinct and non-empty, not {names}")
        self.rule = canonical_rule(rule)
        self.scheme = SCHEMES[scheme_name(rule)](self)
        if reference is not None and reference not in self.names:
            raise ValueError(f"reference term {reference!r} is not one of {self.names}")
        if self.scheme.name == "max-avg" and reference is None:
            raise ValueError("max-avg weighting needs a reference term (the PDE residual)")
        if not (0.0 < alpha <= 1.0):
            raise ValueError(f"alpha must be in (0, 1], not {alpha}")
        if every < 1:
            raise ValueError(f"every must be ≥ 1, not {every}")
        self.reference, self.alpha, self.every = reference, float(alpha), int(every)
        self.seed = int(seed)
        self.weights = {n: 1.0 for n in self.names}
        if self.scheme.name == "epsilon-optimal":
            fixed = dict(fixed or {})
            unknown = sorted(set(fixed) - set(self.names))
            if unknown:
                raise ValueError(f"fixed weights for unknown term(s) {unknown}; "
                                 f"terms: {self.names}")
            for n, w in fixed.items():
                if not math.isfinite(w) or w < 0:
                    raise ValueError(f"fixed weight of {n!r} must be finite and ≥ 0, not {w}")
                self.weights[n] = float(w)
        elif fixed:
            raise ValueError(f"fixed weights only go with rule 'epsilon-optimal', not "
                             f"{self.rule!r}")
        self.history: list[dict] = [{"step": 0, **self.weights}]
        self._batched = True  # until a graph turns out to have no batching rule

    @property
    def adaptive(self) -> bool:
        return bool(self.scheme.needs)

    def due(self, step: int) -> bool:
        """Whether the weights (or the direction) are refreshed at ``step``."""
        return self.adaptive and (self.scheme.each_step or step % self.every == 0)

    def blend(self, name: str, target: float) -> None:
        """λ ← (1 − α) λ + α target, unless that is not finite."""
        new = (1.0 - self.alpha) * self.weights[name] + self.alpha * target
        if math.isfinite(new):
            self.weights[name] = new

    def update(self, step: int, grads: Mapping[str, torch.Tensor | Sequence] | None = None,
               losses: Mapping[str, float] | None = None, record: bool = True,
               ) -> dict[str, float]:
        """Refresh the weights from the active terms' loss values and what the scheme needs of
        their gradients (per term a tensor or a list of per-parameter tensors, ``None`` for an
        unused one; for ``ntk`` a matrix of per-sample gradients, one row per sample); returns
        the new weights. ``record``: append them to :attr:`history`."""
        grads, losses = dict(grads or {}), dict(losses or {})
        unknown = sorted((set(grads) | set(losses)) - set(self.names))
        if unknown:
            raise ValueError(f"gradient for unknown term(s) {unknown}; terms: {self.names}")
        if not self.adaptive or self.scheme.direction:
            return dict(self.weights)
        order = [n for n in self.names if n in grads or n in losses]
        flat = {n: (grads[n].detach().double() if self.scheme.needs == "residuals"
                    else _flat(grads[n]).detach().double()) for n in order if n in grads}
        extra = self.scheme.refresh(step, {n: float(losses[n]) for n in order if n in losses},
                                    flat)
        if record:
            self.history.append({"step": int(step), **self.weights, **extra})
        return dict(self.weights)

    # ------------------------------------------------------------------ use in training
    def total(self, losses: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Σ_k λ_k L_k over the terms in ``losses`` (the active ones), current weights."""
        return sum(self.weights[n] * losses[n] for n in self.names if n in losses)

    def gradients(self, outputs: Sequence[torch.Tensor],
                  params: Sequence[torch.Tensor]) -> torch.Tensor:
        """:func:`term_gradients` of the scalars ``outputs``, one after another where the graph
        cannot be batched (each from its own graph: a slice of their stack would take every
        reverse pass through all of them); the graph is kept."""
        if self._batched:
            try:
                return term_gradients(torch.stack(list(outputs)), params, retain_graph=True)
            except RuntimeError as e:
                if "atching rule" not in str(e):
                    raise
                self._batched = False
        rows = []
        for out in outputs:
            g = torch.autograd.grad(out, params, retain_graph=True, materialize_grads=True)
            rows.append(torch.cat([gi.reshape(-1) for gi in g]))
        return torch.stack(rows)

    def _refresh(self, losses: Mapping[str, torch.Tensor], params: Sequence[torch.Tensor],
                 step: int, residuals: Callable[[], Mapping[str, torch.Tensor]] | None,
                 ) -> torch.Tensor | None:
        """Refresh when :meth:`due`; returns the active terms' gradients as rows when it took
        them (the graph kept), else None."""
        unknown = sorted(set(losses) - set(self.names))
        if unknown:
            raise ValueError(f"unknown loss term(s) {unknown}; terms: {self.names}")
        active = [n for n in self.names if n in losses]
        values = {n: losses[n].detach() for n in active}
        record = step % self.every == 0
        if not self.due(step):
            return None
        if self.scheme.needs == "losses":
            self.update(step, losses=values, record=record)
            return None
        if self.scheme.needs == "residuals":
            if residuals is None:
                raise ValueError("ntk weighting needs each term's per-sample residuals: "
                                 "pass residuals= to Weighting.backward")
            given = residuals()
            r = {n: given[n].reshape(-1) for n in active if n in given}
            rows = self.gradients([x for v in r.values() for x in v], params)
            self.update(step, dict(zip(r, rows.split([len(v) for v in r.values()]))), values,
                        record)
            return None
        rows = self.gradients([losses[n].reshape(()) for n in active], params)
        if self.scheme.direction:
            if record:
                self.history.append({"step": int(step), **self.weights})
        else:
            grads = dict(zip(active, rows))
            if self.scheme.layer:
                grads = {n: g[_last_layer(params)] for n, g in grads.items()}
            self.update(step, grads, values, record)
        return rows

    def weigh(self, losses: Mapping[str, torch.Tensor], params: Iterable[torch.Tensor],
              step: int) -> torch.Tensor:
        """Σ_k λ_k L_k with its graph, the weights refreshed first when :meth:`due` (from one
        batched reverse pass over the terms, the graph kept), for a caller that takes the
        gradient of the total its own way (a gradient flow of a closed loop, clipping). A
        direction scheme has no weights to give: use :meth:`backward`."""
        if self.scheme.direction:
            raise ValueError(f"{self.scheme.name} combines the terms' gradients into an update "
                             "direction, not weights: use Weighting.backward")
        params = [p for p in params if p.requires_grad]
        self._refresh(losses, params, step, None)
        return self.total(losses)

    def backward(
        self, losses: Mapping[str, torch.Tensor], params: Iterable[torch.Tensor], step: int,
        residuals: Callable[[], Mapping[str, torch.Tensor]] | None = None,
    ) -> torch.Tensor:
        """Leave the update in ``p.grad`` (accumulated like ``Tensor.backward``): ∇_θ Σ_k λ_k L_k,
        or a direction scheme's combination of the terms' gradients; refresh first when
        :meth:`due`. ``residuals`` returns each active term's per-sample residuals (``ntk``
        only; called on refresh steps). Returns the weighted total (detached)."""
        params = [p for p in params if p.requires_grad]
        rows = self._refresh(losses, params, step, residuals)
        active = [n for n in self.names if n in losses]
        if rows is not None:
            # the terms' gradients are at hand: the update needs no further reverse pass
            self._apply(params, self.scheme.combine(rows, step) if self.scheme.direction
                        else sum(self.weights[n] * row for n, row in zip(active, rows)))
            return self.total({n: losses[n].detach() for n in active})
        total = self.total(losses)
        total.backward()
        return total.detach()

    @staticmethod
    def _apply(params: Sequence[torch.Tensor], flat: torch.Tensor) -> None:
        for p, g in zip(params, flat.split([p.numel() for p in params])):
            g = g.view_as(p)
            p.grad = g if p.grad is None else p.grad + g

    def state_dict(self) -> dict:
        return {"rule": self.rule, "weights": dict(self.weights), "history": list(self.history),
                "scheme": self.scheme.state()}

    def load_state_dict(self, state: Mapping) -> None:
        rule = state.get("rule")
        same = rule in (*SCHEMES, *ALIASES, *RECORDED) and scheme_name(rule) == self.scheme.name
        if not same or set(state.get("weights", {})) != set(self.names):
            raise ValueError(f"weighting state of rule {rule!r} with terms "
                             f"{sorted(state.get('weights', {}))} does not match "
                             f"{self.rule!r} with {sorted(self.names)}")
        self.weights = {n: float(state["weights"][n]) for n in self.names}
        self.history = list(state["history"])
        self.scheme.load(state.get("scheme", {}))
