"""Ensembles: K runs of one configuration that differ in the seed train in one process.

Our networks are small, so an update costs per-operation overhead rather than arithmetic. An
ensemble stacks its members' parameters (``torch.func.stack_module_state``), runs their
networks as one vectorised call and hands the solver every member's rows as one batch: one
bridge call per step for the whole ensemble. A plain chain of linear layers runs as batched
matrix products (:func:`batched_layers`), as do 1D convolutions and 1D ResNets with circular
padding (each convolution one batched product of the neighbours' channels), any other network
under ``torch.func.vmap`` over ``functional_call``. The tape is ordinary autograd over these
stacked operations. The other route, ``vmap`` of ``grad`` of one member's whole loss with the
solver call inside (the bridge's vmap rule makes that one call too), computes the same update
but is several times slower on the cart-pole controller, since every operation of the forward
and the backward pass goes through vmap's batching rules (``benchmarks/ensemble.py --routes``).

Each member keeps what its separate run has: its initialisation (the net its seed builds), its
initial states and data order (its seed's), and its own Adam state. Adam is elementwise, so one
Adam over the stacked parameters is K Adams as long as every per-member quantity is computed per
member: the step count (a member whose update is skipped does not advance), the learning rate,
the clipping of the update and the update norm in the history. Each member's run therefore
equals its separate run to float rounding, and its run directory holds exactly what a separate
run writes (``config.json``, ``history.csv``, ``checkpoint.pt``, ``result.json``, plots): a
member resumes, is evaluated and is tabulated as an ordinary run, alone or in an ensemble again.

The stacking (:class:`Stack`, :class:`EnsembleNet`) serves any network; :func:`train_ensemble`
trains controllers (members may differ in ``seed``, ``out``, ``clip`` and ``lr``) and neural
time-steppers (``seed``, ``out`` and ``lr``; every unrolling mode, prediction and correction):
each member keeps its own spike cutoff and rollback guard, as in its separate run.

The ``compile`` key compiles an ensemble's loss as it does a separate run's
(:mod:`adjointsim.train.compiled`): the stacked network and the closed loop or unroll around it,
traced once per shape; the epoch's diagnosed update (a doubled batch) runs eager.

An ensemble saves every member's checkpoint at the end of each epoch and on Ctrl-C between two
updates. Should it die between two members' saves, the members resume from different points:
each group of members at the same point then trains on as an ensemble of its own.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.func import functional_call, stack_module_state, vmap

from adjointsim import engine
from adjointsim.errors import UserError
from adjointsim.nets.mlp import MLP, Sin
from adjointsim.nets.resnet import ResNet
from adjointsim.stepper import NonFiniteInputError, NonFiniteStateError

from . import control as ctl
from .compiled import compiled
from .evaluate import BLOW_UPS
from .model import NeuralStepper
from .tasks import Task
from .threads import use_threads
from .trainer import StepperRun, TrainConfig, prepare
from .unroll import GradientFlow, Update, clip_update, unrolled_loss

#: config keys members of a controller ensemble may differ in
CONTROL_FREE = ("seed", "out", "clip", "lr")
#: config keys members of a neural-stepper ensemble may differ in
STEPPER_FREE = ("seed", "out", "lr")
_BLOW_UPS = (NonFiniteStateError, NonFiniteInputError, FloatingPointError)


def check_members(cfgs: Sequence, free: Sequence[str]) -> None:
    """Refuse an ensemble whose configs differ in more than ``free``, or share a run
    directory."""
    if not cfgs:
        raise UserError("an ensemble needs at least one member")
    kinds = {type(c) for c in cfgs}
    if len(kinds) > 1:
        raise UserError("an ensemble's members must be configs of one kind")
    first = dataclasses.asdict(cfgs[0])
    for cfg in cfgs[1:]:
        differ = [k for k, v in dataclasses.asdict(cfg).items()
                  if v != first[k] and k not in free]
        if differ:
            raise UserError(f"ensemble members may differ only in {', '.join(free)}; "
                            f"{cfg.out} differs from {cfgs[0].out} in {', '.join(differ)}")
    outs = [str(Path(c.out).resolve()) for c in cfgs]
    if len(set(outs)) < len(outs):
        raise UserError("ensemble members need run directories of their own (--out)")


# ----------------------------------------------------------------------------- stacking
class Stack:
    """K networks of one architecture as stacked tensors (leading axis: the member), with
    one Adam state per member (elementwise, as ``torch.optim.Adam`` on CPU computes it).
    ``batched=False`` runs every network under ``vmap`` (see :func:`batched_layers`)."""

    def __init__(self, nets: Sequence[nn.Module], lrs: Sequence[float],
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 batched: bool = True):
        params, _ = stack_module_state(list(nets))
        self.names = list(params)
        self.tensors = [params[n].detach() for n in self.names]
        self.exp_avg = [torch.zeros_like(t) for t in self.tensors]
        self.exp_avg_sq = [torch.zeros_like(t) for t in self.tensors]
        self.steps = [0] * len(nets)
        self.lrs = list(lrs)
        self.betas, self.eps = betas, eps
        self.template = copy.deepcopy(nets[0])
        self.plan = batched_layers(self.template, self.names) if batched else None

    @property
    def members(self) -> int:
        return len(self.steps)

    def leaves(self, idx: Sequence[int] | None = None) -> list[torch.Tensor]:
        """Fresh leaves of the members ``idx`` (all: no copy) for one update's tape."""
        if idx is None or len(idx) == self.members:
            return [t.detach().requires_grad_() for t in self.tensors]
        sel = torch.tensor(list(idx))
        return [t[sel].requires_grad_() for t in self.tensors]

    def net(self, leaves: Sequence[torch.Tensor], rows: int) -> EnsembleNet:
        return EnsembleNet(self.template, self.names, list(leaves), rows, self.plan)

    def adam(self, grads: Sequence[torch.Tensor], idx: Sequence[int]) -> None:
        """One Adam step of the members ``idx`` (the others keep weights and state);
        ``grads`` holds the gradients of exactly those members, stacked."""
        if not idx:
            return
        b1, b2 = self.betas
        for k in idx:
            self.steps[k] += 1
        steps = [self.steps[k] for k in idx]
        size = [self.lrs[k] / (1 - b1**s) for k, s in zip(idx, steps)]
        root = [(1 - b2**s) ** 0.5 for s in steps]
        every = len(idx) == self.members
        sel = None if every else torch.tensor(list(idx))
        for p, g, m, v in zip(self.tensors, grads, self.exp_avg, self.exp_avg_sq):
            shape = (-1,) + (1,) * (p.ndim - 1)
            neg = torch.tensor([-s for s in size], dtype=p.dtype).view(shape)
            div = torch.tensor(root, dtype=p.dtype).view(shape)
            mm, vv, pp = (m, v, p) if every else (m[sel], v[sel], p[sel])
            mm.lerp_(g, 1 - b1)
            vv.mul_(b2).addcmul_(g, g, value=1 - b2)
            denom = (vv.sqrt() / div).add_(self.eps)
            # addcdiv's own order: p + (value · m) / denom, with a value per member
            pp.add_(neg * mm / denom)
            if not every:
                m[sel], v[sel], p[sel] = mm, vv, pp

    def load(self, k: int, net: nn.Module, opt: torch.optim.Adam) -> None:
        """Member ``k`` from its ordinary network and optimiser (a restored run)."""
        params = dict(net.named_parameters())
        state = opt.state
        for i, name in enumerate(self.names):
            p = params[name]
            self.tensors[i][k] = p.detach()
            if p in state:
                self.exp_avg[i][k] = state[p]["exp_avg"]
                self.exp_avg_sq[i][k] = state[p]["exp_avg_sq"]
        steps = {int(s["step"]) for s in state.values()}
        self.steps[k] = steps.pop() if steps else 0

    def store(self, k: int, net: nn.Module, opt: torch.optim.Adam) -> None:
        """Member ``k`` into its ordinary network and optimiser, as its separate run holds
        them (for its checkpoint, plots and result)."""
        params = dict(net.named_parameters())
        with torch.no_grad():
            for i, name in enumerate(self.names):
                params[name].copy_(self.tensors[i][k])
        if self.steps[k]:
            for i, name in enumerate(self.names):
                opt.state[params[name]] = {
                    "step": torch.tensor(float(self.steps[k]), dtype=torch.get_default_dtype()),
                    "exp_avg": self.exp_avg[i][k].clone(),
                    "exp_avg_sq": self.exp_avg_sq[i][k].clone(),
                }


#: parameter-free layers that act elementwise, the same for every member
_ELEMENTWISE = (nn.Tanh, nn.ReLU, nn.LeakyReLU, nn.GELU, nn.SiLU, nn.Sigmoid, Sin)


def batched_layers(template: nn.Module, names: list[str]) -> list[tuple] | None:
    """The template as a chain of batched layers (a linear layer or a 1D convolution becomes
    one batched matrix product over the members, a 1D circular ResNet one op of them), or None
    where it is not a plain chain of linear layers, 1D convolutions padded by half their reach,
    elementwise activations, flattening and such ResNets: those networks run under ``vmap``.
    For our small networks the batched chain is faster (MLPs: it skips vmap's per-call
    overhead; convolutions: one matrix product each beats the grouped convolution vmap makes
    of them)."""
    index = {n: i for i, n in enumerate(names)}
    plan: list[tuple] = []

    def conv(module: nn.Module, prefix: str) -> tuple | None:
        """A 1D convolution padded by half its reach (circular or zeros): its plan entry."""
        ok = (isinstance(module, nn.Conv1d) and module.padding_mode in ("circular", "zeros")
              and module.bias is not None and module.groups == 1
              and module.padding == (module.dilation[0] * (module.kernel_size[0] // 2),)
              and module.kernel_size[0] % 2 == 1)
        return (index[prefix + "weight"], index[prefix + "bias"], module.dilation[0],
                module.stride[0], module.padding_mode) if ok else None

    def resnet(module: ResNet, prefix: str) -> bool:
        if module.encode.padding_mode != "circular":  # walls: the vmap route
            return False
        convs = [conv(module.encode, prefix + "encode."), conv(module.decode, prefix + "decode.")]
        blocks = [(conv(b.conv1, f"{prefix}blocks.{i}.conv1."),
                   conv(b.conv2, f"{prefix}blocks.{i}.conv2."), b.act)
                  for i, b in enumerate(module.blocks)]
        if None in convs or any(None in b for b in blocks) \
                or any(type(b[2]) not in _ELEMENTWISE for b in blocks):
            return False
        plan.append(("resnet", convs[0], blocks, convs[1]))
        return True

    def walk(module: nn.Module, prefix: str) -> bool:
        if type(module) is ResNet:
            return resnet(module, prefix)
        if isinstance(module, nn.Sequential | MLP):
            return all(walk(m, f"{prefix}{n}.") for n, m in module.named_children())
        if isinstance(module, nn.Linear) and module.bias is not None:
            plan.append(("linear", index[prefix + "weight"], index[prefix + "bias"]))
            return True
        if isinstance(module, nn.Flatten) and module.start_dim == 1 and module.end_dim == -1:
            plan.append(("flatten",))
            return True
        if type(module) in _ELEMENTWISE:
            plan.append(("act", module))
            return True
        if (entry := conv(module, prefix)) is not None:
            plan.append(("conv", entry))
            return True
        return False

    return plan if walk(template, "") else None


class EnsembleNet(nn.Module):
    """The members' networks as one module. Its input's rows come in blocks of members × rows
    (member-major: member 0's ``rows`` rows, member 1's, ...); each member's network sees its
    own rows, all in one vectorised call."""

    def __init__(self, template: nn.Module, names: list[str], leaves: list[torch.Tensor],
                 rows: int, plan: list[tuple] | None):
        super().__init__()
        object.__setattr__(self, "_template", template)  # not a submodule: its weights unused
        self.names, self.leaves, self.rows, self.plan = names, leaves, rows, plan
        self._call = vmap(self._one)
        # a net lives for one update but runs at every step: each linear layer's bias and
        # transposed weight are made once here, not once per step (fewer nodes on the tape)
        self._layers = [self._batched(op) for op in plan or ()]

    def _batched(self, op: tuple) -> tuple:
        """``op`` of the plan with its stacked weights in the layout of its batched product."""
        if op[0] == "linear":
            return "linear", self.leaves[op[2]].unsqueeze(1), self.leaves[op[1]].transpose(1, 2)
        if op[0] not in ("resnet", "conv"):
            return op

        def conv(w: int, b: int, dilation: int, stride: int, padding: str) -> tuple:
            # (K, out, in, kernel) → (K, kernel·in, out): the rows of _conv1d's columns
            weight = self.leaves[w]
            return (weight.permute(0, 3, 2, 1).flatten(1, 2), self.leaves[b].unsqueeze(1),
                    dilation, weight.shape[-1], stride, padding)

        if op[0] == "conv":
            return "conv", conv(*op[1])
        return ("resnet", conv(*op[1]),
                [(conv(*c1), conv(*c2), act) for c1, c2, act in op[2]], conv(*op[3]))

    def _one(self, params: tuple[torch.Tensor, ...], x: torch.Tensor) -> torch.Tensor:
        return functional_call(self._template, dict(zip(self.names, params)), (x,))

    def _chain(self, x: torch.Tensor) -> torch.Tensor:
        for op in self._layers:
            if op[0] == "linear":
                x = torch.baddbmm(op[1], x, op[2])
            elif op[0] == "flatten":
                x = x.flatten(2)
            elif op[0] == "conv":
                x = _conv1d(x.transpose(2, 3), *op[1]).transpose(2, 3)
            elif op[0] == "resnet":
                _, encode, blocks, decode = op
                h = _conv1d(x.transpose(2, 3), *encode)  # channels last from here
                for conv1, conv2, act in blocks:
                    h = h + _conv1d(act(_conv1d(act(h), *conv1)), *conv2)
                x = _conv1d(h, *decode).transpose(2, 3)
            else:
                x = op[1](x)
        return x

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        k, rest = len(self.leaves[0]), x.shape[1:]
        blocks = x.shape[0] // (k * self.rows)
        if blocks == 1:  # the common case: no transposes, fewer nodes on the tape
            xs = x.reshape(k, self.rows, *rest)
        else:
            xs = x.reshape(blocks, k, self.rows, *rest).transpose(0, 1)
            xs = xs.reshape(k, blocks * self.rows, *rest)
        out = self._call(tuple(self.leaves), xs) if self.plan is None else self._chain(xs)
        if blocks > 1:
            out = out.reshape(k, blocks, self.rows, *out.shape[2:]).transpose(0, 1)
        return out.reshape(x.shape[0], *out.shape[(3 if blocks > 1 else 2):])


def _conv1d(h: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, dilation: int,
            kernel: int, stride: int, padding: str) -> torch.Tensor:
    """Every member's 1D convolution of ``h`` (members, rows, grid, channels), padded by half
    its reach (``circular`` or ``zeros``), as one batched matrix product: each output point's
    ``kernel`` neighbours' channels in a row, times the member's (kernel · channels, out)
    weight."""
    n, pad = h.shape[2], dilation * (kernel // 2)
    if padding == "circular":
        if pad > n:
            raise ValueError(f"a circular convolution reaching {pad} points needs a grid of at "
                             f"least {pad} points, not {n}")
        p = torch.cat([h[:, :, n - pad:], h, h[:, :, :pad]], 2) if pad else h
    else:
        p = nn.functional.pad(h, (0, 0, pad, pad))
    out = (n - 1) // stride + 1
    cols = torch.cat([p[:, :, j * dilation:j * dilation + stride * (out - 1) + 1:stride]
                      for j in range(kernel)], 3)
    return torch.baddbmm(bias, cols.flatten(1, 2), weight).unflatten(1, (h.shape[1], out))


# ----------------------------------------------------------------------------- controllers
class _MemberLoss:
    """A control task whose loss is one per member (a (K,) tensor): what
    :func:`adjointsim.train.control.closed_loop` sums over steps."""

    def __init__(self, task: Task, members: int, rows: int):
        self.task, self.members, self.rows = task, members, rows
        self.solver, self.steps = task.solver, task.steps

    def control(self, out: torch.Tensor) -> torch.Tensor:
        return self.task.control(out)

    def step_loss(self, x: torch.Tensor, c: torch.Tensor, t: int) -> torch.Tensor | None:
        # one call for every member's rows (blocks of members × rows), each member's mean
        rows = self.task.row_loss(x, c, t)
        return None if rows is None else rows.reshape(-1, self.members, self.rows).mean((0, 2))

    def total(self, terms: list[torch.Tensor]) -> torch.Tensor:
        return torch.stack(terms).sum(dim=0)


def _control_losses(task: Task, stack: Stack, leaves: list[torch.Tensor], x0: torch.Tensor,
                    rows: int, flow: GradientFlow) -> torch.Tensor:
    k = len(leaves[0])
    return ctl.closed_loop(_MemberLoss(task, k, rows), stack.net(leaves, rows), x0, flow)[0]


@torch.no_grad()
def _evaluate(task: Task, stack: Stack, x0s: list[torch.Tensor]) -> list[float]:
    """Each member's mean loss over its initial states (one rollout for all; a member whose
    rollout blows up gets NaN, as in its separate run)."""
    rows = len(x0s[0])
    try:
        losses = _control_losses(task, stack, stack.leaves(), torch.cat(x0s), rows,
                                 GradientFlow("R"))
        return [float(v) for v in losses]
    except _BLOW_UPS:
        out = []
        for k, x0 in enumerate(x0s):
            try:
                out.append(float(_control_losses(task, stack, stack.leaves([k]), x0, rows,
                                                  GradientFlow("R"))[0]))
            except _BLOW_UPS:
                out.append(float("nan"))
        return out


def _control_update(members: list[ctl.Controller], stack: Stack, batches: list[torch.Tensor],
                    idx: list[int], losses_of: Callable[..., torch.Tensor] = _control_losses
                    ) -> None:
    """One minibatch update of the members ``idx`` (each its batch), recorded in their
    epoch's progress as :func:`adjointsim.train.control.minibatch_update` records a separate
    run's; ``losses_of`` is :func:`_control_losses` or it compiled."""
    task, first = members[0].task, members[idx[0]].state["step"] == 0
    leaves = stack.leaves(idx)
    flow = GradientFlow(members[0].config.mode, diagnose=first)
    run = _control_losses if flow.doubled else losses_of  # a doubled batch breaks the graph
    try:
        losses = run(task, stack, leaves, torch.cat([batches[k] for k in idx]),
                     len(batches[0]), flow)
    except (NonFiniteStateError, NonFiniteInputError):
        if len(idx) > 1:  # whose rows blew up is unknown: each member alone
            for k in idx:
                _control_update(members, stack, batches, [k], losses_of)
        else:
            members[idx[0]].state["skipped"] += 1
        return
    update = flow.backward(losses.sum(), leaves)
    keep, grads, records = [], [], []
    for j, k in enumerate(idx):
        upd = Update(clip_update([g[j] for g in update.grads], members[k].config.clip),
                     None if update.g_m is None else [g[j] for g in update.g_m],
                     None if update.g_r is None else [g[j] for g in update.g_r])
        loss = float(losses[j].detach())
        if not (math.isfinite(loss) and math.isfinite(upd.norm())):
            members[k].state["skipped"] += 1
            continue
        keep.append(j)
        grads.append(upd.grads)
        records.append((k, loss, upd))
    stack.adam([torch.stack(gs) for gs in zip(*grads)], [idx[j] for j in keep])
    for k, loss, upd in records:
        ctl.record(members[k].state, loss, upd, first)


class ControllerEnsemble:
    """Controllers at one point of their runs as one vectorised updater (an
    :class:`adjointsim.engine.Updater`): one closed loop, one backward pass and one stacked Adam
    step per minibatch for all members, each member's batch, progress, history row and epoch
    boundary its own run's (:class:`adjointsim.train.control.Controller`)."""

    def __init__(self, members: list[ctl.Controller]):
        self.members = members
        group = members[0].optimizer.param_groups[0]
        self.stack = Stack([m.net for m in members], [m.config.lr for m in members],
                           group["betas"], group["eps"])
        for k, m in enumerate(members):
            self.stack.load(k, m.net, m.optimizer)
        self.losses_of = compiled(_control_losses, members[0].config.compile)

    def done(self) -> bool:
        return self.members[0].done()

    def update(self) -> bool:
        """One minibatch of every member; at the end of the epoch, their evaluation (one
        rollout for all) and history rows: a boundary. Each member is charged its share of
        the time."""
        members, start = self.members, time.perf_counter()
        _control_update(members, self.stack, [m.batch() for m in members],
                        list(range(len(members))), self.losses_of)
        share = (time.perf_counter() - start) / len(members)
        if not all([m.advance(share) for m in members]):
            return False
        start = time.perf_counter()
        task = members[0].task
        train = _evaluate(task, self.stack, [m.x_train for m in members])
        test = _evaluate(task, self.stack, [m.x_test for m in members])
        share = (time.perf_counter() - start) / len(members)
        for m, losses in zip(members, zip(train, test)):
            m.end_epoch(losses, share)
        return True

    def sync(self) -> None:
        """Each member's weights and Adam state back into its network and optimiser, as its
        separate run holds them (for its checkpoint, result and plots)."""
        for k, m in enumerate(self.members):
            self.stack.store(k, m.net, m.optimizer)


# ----------------------------------------------------------------------------- neural steppers
class StepperEnsemble:
    """Neural-stepper runs at one point as one vectorised update (the engine's updater of an
    ensemble): one tape and one solver call per step for every member, while each member's
    batch, spike cutoff, history row, rollback guard and checkpoint boundary are its own run's
    (:class:`adjointsim.train.trainer.StepperRun`)."""

    def __init__(self, group: Sequence[StepperRun]):
        self.group = list(group)
        adam = self.group[0].optimizer.param_groups[0]
        self.stack = Stack([p.model.net for p in self.group],
                           [p.optimizer.param_groups[0]["lr"] for p in self.group],
                           adam["betas"], adam["eps"])
        for k, p in enumerate(self.group):
            self.stack.load(k, p.model.net, p.optimizer)
        self.losses_of = compiled(_stepper_losses, self.group[0].config.compile)

    def done(self) -> bool:
        return self.group[0].done()

    def update(self) -> bool:
        self._evaluate()
        stage, wins = [p.begin() for p in self.group][0]
        self._update(stage, wins, list(range(len(self.group))))
        self._evaluate()
        return self.group[0].boundary()

    def _evaluate(self) -> None:
        """Each member's test error where its run's cadence (``eval_every``) asks for it, from
        its weights brought back from the stack."""
        if any(p.evaluation_due() for p in self.group):
            self.sync()
            for p in self.group:
                if p.evaluation_due():
                    p.evaluate_curve()

    def sync(self) -> None:
        """Each member's weights, Adam state and rate into its own model and optimiser, as its
        separate run holds them (for its checkpoint, plots and result)."""
        for k, p in enumerate(self.group):
            self.stack.store(k, p.model.net, p.optimizer)
            for g in p.optimizer.param_groups:
                g["lr"] = self.stack.lrs[k]

    def _update(self, stage: dict, wins: np.ndarray, idx: list[int]) -> None:
        """One update of the members ``idx``, as :meth:`StepperRun.update` makes one for a
        separate run: the losses, gradients and their norms, the spike cutoff, Adam, the
        history rows and the rollback guard, each member's own."""
        runs, stack = self.group, self.stack
        cfg = runs[0].config
        batches = [runs[k].batch(wins) for k in idx]
        for k, batch in zip(idx, batches):
            stack.lrs[k] = batch[3]
        leaves = stack.leaves(idx)
        solver = runs[0].model.solver if cfg.setup == "correction" else None
        flow = GradientFlow(stage["flow"])
        try:
            frames, params, conditions = (torch.cat(t) for t in list(zip(*batches))[:3])
            losses = self.losses_of(cfg, stack, leaves, solver, frames, params, conditions,
                                    flow)
            finite = torch.isfinite(losses.detach())
            if finite.any():
                grads = flow.backward(losses[finite].sum(), leaves).grads
                # as clip_grad_norm_: the norm of the tensors' norms, each member's own
                norms = torch.stack([g.flatten(1).norm(dim=1) for g in grads], 1).norm(dim=1)
        except BLOW_UPS:  # the coarse solver refused a state some member's model made
            if len(idx) > 1:  # whose is unknown: each member alone
                for k in idx:
                    self._update(stage, wins, [k])
                return
            losses, finite = torch.tensor([float("nan")]), torch.tensor([False])
        skipped = [not bool(finite[j]) or runs[k].spike(float(norms[j]))
                   for j, k in enumerate(idx)]
        step = [j for j, s in enumerate(skipped) if not s]
        if step:
            sel = torch.tensor(step)
            stack.adam([g[sel] for g in grads], [idx[j] for j in step])
        due = [runs[k].record(stage, batches[j][3], float(losses[j].detach()), skipped[j])
               for j, k in enumerate(idx)]
        if any(due):
            for k in idx:
                run = runs[k]
                stack.store(k, run.model.net, run.optimizer)
                run.guard()
                stack.load(k, run.model.net, run.optimizer)


def _stepper_losses(cfg: TrainConfig, stack: Stack, leaves: list[torch.Tensor],
                    solver: object, frames: torch.Tensor, params: torch.Tensor,
                    conditions: torch.Tensor, flow: GradientFlow) -> torch.Tensor:
    """Each member's unrolled loss (a (K,) tensor) of its rows of ``frames``."""
    k = len(leaves[0])
    model = NeuralStepper(stack.net(leaves, len(frames) // k), cfg.setup, solver,
                          cfg.correction)
    return unrolled_loss(model, frames, params, conditions, flow, cfg.warmup, cfg.truncate,
                         members=k)


def _stepper_ensemble(cfgs: list[TrainConfig], resume: bool, progress: bool,
                      overwrite: bool, until: float | None) -> list[NeuralStepper]:
    cfgs, data = prepare(cfgs)
    runs = [StepperRun(c, data) for c in cfgs]
    engine.run(runs, resume=resume, overwrite=overwrite, progress=progress,
               ensemble=StepperEnsemble, until=until)
    return [run.trained() for run in runs]


# ----------------------------------------------------------------------------- entry point
def train_ensemble(cfgs: Sequence, resume: bool = False, progress: bool = True,
                   overwrite: bool = False, until: float | None = None) -> list:
    """Train the controllers or neural time-steppers ``cfgs`` (configs of one kind differing
    only in the seed, the run directory and what :data:`CONTROL_FREE` / :data:`STEPPER_FREE`
    allow) as one ensemble; returns what each separate run returns, in order. ``resume`` and
    ``overwrite`` apply to every member as to a separate run: finished members are read back,
    the rest train together. ``until`` (epochs, or updates of a time-stepper) stops the members
    there, saved and unfinished (None in the returned list), as :func:`adjointsim.engine.run`
    does."""
    cfgs = list(cfgs)
    if resume and overwrite:
        raise UserError("--resume continues a run and --overwrite discards it: pass one")
    for cfg in cfgs:
        cfg.validate()
    if isinstance(cfgs[0], TrainConfig):
        check_members(cfgs, STEPPER_FREE)
        return _stepper_ensemble(cfgs, resume, progress, overwrite, until)
    if not isinstance(cfgs[0], ctl.ControlConfig):
        raise UserError("ensembles train controllers (ControlConfig) and neural time-steppers "
                        f"(TrainConfig), not {type(cfgs[0]).__name__}")
    check_members(cfgs, CONTROL_FREE)
    if cfgs[0].weighting != "uniform":
        raise UserError("an ensemble trains the task's loss as it is (weighting uniform), "
                        f"not {cfgs[0].weighting}")
    return _control_ensemble(cfgs, resume, progress, overwrite, until)


def _control_ensemble(cfgs: list[ctl.ControlConfig], resume: bool, progress: bool,
                      overwrite: bool, until: float | None) -> list[dict]:
    use_threads(cfgs[0].threads)
    members = [ctl.Controller(c) for c in cfgs]
    # resume: continue the members that hold a run, start the others (a study's new cells)
    resume = resume and any(engine.RunDir(m).holds() for m in members)
    return engine.run(members, resume=resume, overwrite=overwrite, progress=progress,
                      ensemble=ControllerEnsemble, until=until)
