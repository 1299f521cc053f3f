"""Weights λ_k for a loss with several named terms, L = Σ_k λ_k L_k (Maddu et al., MLST 2022).

Rules (``Weighting(names, rule=...)``):

* ``uniform``: every λ_k = 1.
* ``inverse-dirichlet`` (ID): g_k = ∇_θ L_k over every parameter, concatenated; its spread
  s_k = std(g_k). Every ``every`` steps the target is λ̂_k = s_ref / s_k and
  λ_k ← (1 − α) λ_k + α λ̂_k (α = 0.5, all λ start at 1). ``reference`` names the reference
  term, which keeps λ = 1 (the authors' code: the PDE residual); ``reference=None`` takes the
  term with the largest spread at each update (s_ref = max_k s_k), as several later
  implementations do. Both equalise λ_k² Var(g_k).
* ``max-avg`` (learning-rate annealing, Wang, Teng & Perdikaris 2021, as in the authors'
  reference code): λ̂_k = max|g_ref| / mean|λ_k g_k| with the *current* λ_k inside the mean,
  and the same moving average. Needs a named reference term.
* ``fixed``: the given constant weights (e.g. the analytic ε-optimal ones of the Poisson
  problem); missing names get 1.

Guard: a term whose gradient is zero or non-finite (s_k = 0, mean|g_k| = 0) keeps its weight,
and a zero or non-finite reference spread leaves every weight as it is; no weight becomes inf
or NaN.

Terms may join one after another (sequential training): :meth:`backward` and :meth:`update`
take the *active* terms only, and an absent term keeps its weight. While the named reference
is absent, ID takes the active term of largest spread as the reference.

Every update appends ``{"step": s, "<name>": λ, ..., "spread/<name>": s_k, ...}`` to
:attr:`Weighting.history`. The class works on any multi-term loss: :meth:`backward` takes the
named terms and the parameters they act on, refreshes the weights when due (one reverse pass
per term, whose results are combined, so the update costs no extra backward) and leaves
∇_θ Σ λ_k L_k in ``p.grad``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import torch

RULES = ("uniform", "inverse-dirichlet", "max-avg", "fixed")
#: other spellings accepted on the command line
ALIASES = {"id": "inverse-dirichlet", "maxavg": "max-avg", "analytic": "fixed"}


def canonical_rule(rule: str) -> str:
    rule = ALIASES.get(rule, rule)
    if rule not in RULES:
        raise ValueError(f"unknown weighting {rule!r}; choose from {', '.join(RULES)} "
                         f"(or {', '.join(ALIASES)})")
    return rule


def _flat(grads: torch.Tensor | Sequence[torch.Tensor | None],
          like: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
    if isinstance(grads, torch.Tensor):
        return grads.reshape(-1)
    parts = []
    for i, g in enumerate(grads):
        if g is None:
            if like is None:
                continue
            g = torch.zeros_like(like[i])
        parts.append(g.reshape(-1))
    return torch.cat(parts) if parts else torch.zeros(0)


class Weighting:
    """The weights of the named loss terms ``names`` under ``rule`` (see the module doc)."""

    def __init__(
        self,
        names: Sequence[str],
        rule: str = "uniform",
        reference: str | None = None,
        alpha: float = 0.5,
        every: int = 5,
        fixed: Mapping[str, float] | None = None,
    ):
        self.names = tuple(names)
        if len(set(self.names)) != len(self.names) or not self.names:
            raise ValueError(f"loss term names must be distinct and non-empty, not {names}")
        self.rule = canonical_rule(rule)
        if reference is not None and reference not in self.names:
            raise ValueError(f"reference term {reference!r} is not one of {self.names}")
        if self.rule == "max-avg" and reference is None:
            raise ValueError("max-avg weighting needs a reference term (the PDE residual)")
        if not (0.0 < alpha <= 1.0):
            raise ValueError(f"alpha must be in (0, 1], not {alpha}")
        if every < 1:
            raise ValueError(f"every must be ≥ 1, not {every}")
        self.reference, self.alpha, self.every = reference, float(alpha), int(every)
        self.weights = {n: 1.0 for n in self.names}
        if self.rule == "fixed":
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
            raise ValueError(f"fixed weights only go with rule 'fixed', not {self.rule!r}")
        self.history: list[dict] = [{"step": 0, **self.weights}]

    @property
    def adaptive(self) -> bool:
        return self.rule in ("inverse-dirichlet", "max-avg")

    def due(self, step: int) -> bool:
        """Whether the weights are refreshed at ``step`` (steps 0, every, 2·every, ...)."""
        return self.adaptive and step % self.every == 0

    # ------------------------------------------------------------------ the rules
    def update(self, step: int, grads: Mapping[str, torch.Tensor | Sequence]) -> dict[str, float]:
        """Refresh the weights from each active term's parameter gradient (a tensor or a list
        of per-parameter tensors, ``None`` for an unused one); returns the new weights."""
        unknown = sorted(set(grads) - set(self.names))
        if unknown:
            raise ValueError(f"gradient for unknown term(s) {unknown}; terms: {self.names}")
        if not self.adaptive:
            return dict(self.weights)
        active = [n for n in self.names if n in grads]
        flat = {n: _flat(grads[n]).detach().double() for n in active}
        spread = {n: float(g.std(unbiased=False)) if g.numel() else 0.0
                  for n, g in flat.items()}
        usable = {n: math.isfinite(s) and s > 0.0 for n, s in spread.items()}
        ref = self.reference if self.reference in grads else None
        if self.rule == "inverse-dirichlet":
            if ref is None:
                ref = max((n for n in active if usable[n]), key=spread.get, default=None)
            if ref is not None and usable[ref]:
                for n in active:
                    if n == self.reference or not usable[n]:
                        continue
                    self._blend(n, spread[ref] / spread[n])
        elif ref is not None:  # max-avg, while its reference is active
            top = float(flat[ref].abs().max()) if flat[ref].numel() else 0.0
            if math.isfinite(top) and top > 0.0:
                for n in active:
                    if n == ref:
                        continue
                    avg = float((self.weights[n] * flat[n]).abs().mean()) if usable[n] else 0.0
                    if math.isfinite(avg) and avg > 0.0:
                        self._blend(n, top / avg)
        self.history.append({"step": int(step), **self.weights,
                             **{f"spread/{n}": spread[n] for n in active}})
        return dict(self.weights)

    def _blend(self, name: str, target: float) -> None:
        new = (1.0 - self.alpha) * self.weights[name] + self.alpha * target
        if math.isfinite(new):
            self.weights[name] = new

    # ------------------------------------------------------------------ use in training
    def total(self, losses: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Σ_k λ_k L_k over the terms in ``losses`` (the active ones), current weights."""
        return sum(self.weights[n] * losses[n] for n in self.names if n in losses)

    def backward(
        self, losses: Mapping[str, torch.Tensor], params: Iterable[torch.Tensor], step: int
    ) -> torch.Tensor:
        """Leave ∇_θ Σ_k λ_k L_k in ``p.grad`` (accumulated like ``Tensor.backward``),
        refreshing the weights first when :meth:`due`; returns the weighted total (detached)."""
        params = [p for p in params if p.requires_grad]
        unknown = sorted(set(losses) - set(self.names))
        if unknown:
            raise ValueError(f"unknown loss term(s) {unknown}; terms: {self.names}")
        if not self.due(step):
            total = self.total(losses)
            total.backward()
            return total.detach()
        active = [n for n in self.names if n in losses]
        per_term = {}
        for i, n in enumerate(active):
            last = i == len(active) - 1
            g = torch.autograd.grad(losses[n], params, retain_graph=not last, allow_unused=True)
            per_term[n] = [torch.zeros_like(p) if gi is None else gi for gi, p in zip(g, params)]
        self.update(step, per_term)
        for j, p in enumerate(params):
            g = sum(self.weights[n] * per_term[n][j] for n in active)
            p.grad = g if p.grad is None else p.grad + g
        return self.total({n: losses[n].detach() for n in active})

    def state_dict(self) -> dict:
        return {"rule": self.rule, "weights": dict(self.weights), "history": list(self.history)}

    def load_state_dict(self, state: Mapping) -> None:
        if state.get("rule") != self.rule or set(state.get("weights", {})) != set(self.names):
            raise ValueError(f"weighting state of rule {state.get('rule')!r} with terms "
                             f"{sorted(state.get('weights', {}))} does not match "
                             f"{self.rule!r} with {sorted(self.names)}")
        self.weights = {n: float(state["weights"][n]) for n in self.names}
        self.history = list(state["history"])
