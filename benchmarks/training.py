"""Cost of one training iteration: KS correction, 33k ResNet (26 × 8), batch 16, unroll m = 4.

    python benchmarks/training.py [--repeats 30] [--dtype float32]

Side by side in one run:
* WIG iteration with adjointsim's solver (hand-written adjoint through
  ``adjointsim.train.bridge``), and the share of it spent in the solver's forward + adjoint;
* the same WIG iteration with a pure-torch (torch.fft) ETD1 solver under autograd;
* NOG and ONE iterations, for the ratio NOG / (m × ONE).
Targets: solver ≤ 20% of the WIG iteration; ≥ 3× faster than the torch-solver
iteration; NOG ≤ 1.1 × m × ONE.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from adjointsim.nets import ResNet, parameter_count  # noqa: E402
from adjointsim.spectral.etdrk import etdrk_coefficients  # noqa: E402
from adjointsim.train import bridge  # noqa: E402
from adjointsim.train.model import NeuralStepper  # noqa: E402
from adjointsim.train.problems import get_problem  # noqa: E402
from adjointsim.train.unroll import unrolled_loss  # noqa: E402


class TorchETD1KS:
    """The coarse KS solver of List et al. (ETD1, two sub-steps per frame) in torch.fft."""

    def __init__(self, stepper, dtype: torch.dtype):
        n, length = stepper.grid_shape[0], stepper.length
        h = stepper.dt / stepper.substeps
        k = 2 * np.pi * np.arange(n // 2 + 1) / length
        c = etdrk_coefficients(k**2 - k**4, h, 1)
        cdtype = torch.complex64 if dtype == torch.float32 else torch.complex128
        self.E = torch.tensor(c["E"], dtype=cdtype)
        self.phi1 = torch.tensor(c["phi1"], dtype=cdtype)
        k[-1] = 0.0  # no Nyquist mode in an odd derivative
        self.g = torch.tensor(-0.5j * k, dtype=cdtype)
        self.n, self.substeps, self.dt = n, stepper.substeps, stepper.dt

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        v = torch.fft.rfft(u)
        for _ in range(self.substeps):
            v = self.E * v + self.phi1 * (self.g * torch.fft.rfft(torch.fft.irfft(v, self.n) ** 2))
        return torch.fft.irfft(v, self.n)


class TorchCorrection(NeuralStepper):
    """Parallel correction with the torch solver in place of the bridge (one domain size)."""

    def __init__(self, net, torch_solver):
        super().__init__(net, "prediction")
        self.setup, self.torch_solver = "correction", torch_solver

    def forward(self, u, params, conditions, flow=None):
        # timed under WIG only, whose flow stops no gradient
        return self.torch_solver(u) + self.torch_solver.dt * self._f(u, conditions)


def training_step(model, frames, params, cond, mode):
    """One optimiser update of ``model``, as a callable."""
    opt = torch.optim.Adam(model.parameters(), lr=1e-5)

    def run():
        loss = unrolled_loss(model, frames, params, cond, mode)
        opt.zero_grad()
        loss.backward()
        opt.step()

    return run


def solver_step(step, x, m):
    """Forward (m single steps, as in training) and backward of a solver alone."""

    def run():
        y = x
        for _ in range(m):
            y = step(y)
        y.sum().backward()

    return run


def interleaved_medians(runs: dict, repeats: int) -> dict:
    """Median seconds per callable, measured round-robin so that drift on a shared machine
    (other jobs, frequency changes) hits every candidate alike."""
    times = {k: [] for k in runs}
    for i in range(repeats + 3):
        for name, run in runs.items():
            t = time.perf_counter()
            run()
            if i >= 3:
                times[name].append(time.perf_counter() - t)
    return {k: float(np.median(v)) for k, v in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    args = parser.parse_args()
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    m, batch = 4, 16
    ks = get_problem("ks")  # List et al.'s scenes
    stepper = ks.coarse(1.0)
    rng = np.random.default_rng(0)
    ref = ks.reference(1.0)
    u = ref.rollout(ref.random_state(rng, batch) * 0.5, 200, keep="all")[-m - 1:]
    frames = torch.from_numpy(np.swapaxes(u, 0, 1).copy()).to(dtype)
    params = torch.ones(batch, dtype=torch.float64)
    cond = torch.ones(batch, dtype=dtype)

    def net():
        torch.manual_seed(0)
        return ResNet.preset("small", 2, 1).to(dtype)

    ours = NeuralStepper(net(), "correction", lambda p: stepper)
    print(f"KS correction, N = 48, ResNet {parameter_count(ours.net):,} parameters, batch {batch}, "
          f"m = {m}, {args.dtype}, 1 thread, median of {args.repeats}, interleaved")
    torch_solver = TorchETD1KS(stepper, dtype)
    # Training batches mix the six domain sizes: one grouped solver call per step all the same.
    sizes = torch.tensor([(0.9, 0.95, 1.0, 1.1, 1.2, 1.3)[i % 6] for i in range(batch)],
                         dtype=torch.float64)
    mixed = NeuralStepper(net(), "correction", ks.coarse)
    x = frames[:, 0].clone().requires_grad_()
    t = interleaved_medians({
        "wig": training_step(ours, frames, params, cond, "WIG"),
        "torch": training_step(TorchCorrection(net(), torch_solver), frames, params, cond, "WIG"),
        "mixed": training_step(mixed, frames, sizes, cond, "WIG"),
        "nog": training_step(ours, frames, params, cond, "NOG"),
        # ONE's update: one step, flow R (unroll.schedule)
        "one": training_step(ours, frames[:, :2].contiguous(), params, cond, "R"),
        "solver": solver_step(lambda y: bridge.rollout(stepper, y, 1), x, m),
        "solver_torch": solver_step(torch_solver, x, m),
    }, args.repeats)
    t_wig, t_torch, t_mixed, t_nog, t_one = (t[k] for k in ("wig", "torch", "mixed", "nog", "one"))
    t_solver, t_solver_torch = t["solver"], t["solver_torch"]
    rows = [
        ("WIG iteration, adjointsim solver", t_wig, ""),
        ("  solver forward + adjoint (m steps)", t_solver,
         f"{t_solver / t_wig:.0%} of the iteration (target ≤ 20%)"),
        ("WIG iteration, six domain sizes per batch", t_mixed,
         f"{t_mixed / t_wig:.2f}x one size"),
        ("WIG iteration, torch.fft solver + autograd", t_torch,
         f"{t_torch / t_wig:.2f}x slower than ours (target ≥ 3x)"),
        ("  torch.fft solver forward + autograd backward", t_solver_torch,
         f"{t_solver_torch / t_solver:.1f}x our solver's time"),
        ("NOG iteration", t_nog, f"{t_nog / (m * t_one):.2f} × m × ONE (target ≤ 1.1)"),
        (f"ONE iteration (same batch {batch})", t_one, ""),
    ]
    print(f"| {'what':<44} | {'ms':>7} | note |\n|{'-' * 46}|{'-' * 9}|------|")
    for name, t, note in rows:
        print(f"| {name:<44} | {1e3 * t:7.2f} | {note} |")


if __name__ == "__main__":
    main()
