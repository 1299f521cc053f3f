"""Work-precision diagrams of the spectral ETDRK solvers: error at t_end against run time.

    adjointsim bench work-precision ks|ns [--out DIR] [--quick] [--repeats R] [--no-exponax]

Scenes (float64, batch 1):

``ks``  Kassam & Trefethen's Kuramoto–Sivashinsky (conservative form, no dealiasing) on
        [0, 32π), u0 = cos(x/16)(1 + sin(x/16)), t_end = 10; N = 128, 256; Δt = 1 … 1/32.
``ns``  2D Kolmogorov flow (vorticity form, forcing sin(4y) in x-momentum, ν = 0.01, no drag,
        2/3 dealiasing) on [0, 2π)² from smooth random vorticity (modes |k| ≤ 4, unit RMS,
        seed 0), t_end = 0.5; 64², 128²; Δt = 0.1 … 1/160.

Schemes: ours at ETDRK orders 1–4 (``ks1d-etdrk*``, ``ns2d-etdrk*``), the vectorised NumPy
ETDRK4 of :class:`NumpyETDRK4` (numpy.fft) and, when installed, exponax's ETDRK4 (JAX, jit,
configured to the identical discretisation by :func:`exponax_twin`). Error: relative L∞ error
at t_end against a reference, ETDRK4 at Δt_min/16 on a grid twice as fine as the finest swept
(spectrally resampled onto each grid). Run time: median over ``--repeats`` samples of the
process CPU time of the whole rollout (steady on a shared machine; every library runs one
thread). ``--quick`` sweeps one grid and four (KS) or three (NS) step sizes: under a minute.

Output in ``--out`` (default ``.``): ``work_precision_<scene>.csv`` with one row per
(scheme, N, Δt) and ``work_precision_<scene>.png``, error against run time on log-log axes,
one curve per scheme and grid.
"""

from __future__ import annotations

import csv
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from adjointsim.files import pyplot, save_figure

from ..registry import get
from ..spectral import fft1d, fft2d
from ..spectral.etdrk import etdrk_coefficients, reference_step
from ..stepper import Stepper

#: XLA's option for single-threaded CPU kernels; it takes effect only if jax is not imported yet
#: (process CPU time, the clock here, counts every thread anyway)
XLA_ONE_THREAD = "--xla_cpu_multi_thread_eigen=false"
ORDERS = (1, 2, 3, 4)
CSV_FIELDS = (
    "scene", "scheme", "order", "n", "dt", "steps", "t_end", "error", "time_s", "ref_n", "ref_dt",
)


# ----------------------------------------------------------------- scenes
@dataclass(frozen=True)
class Sweep:
    grids: tuple[int, ...]
    dts: tuple[float, ...]
    ref_n: int


@dataclass(frozen=True)
class Scene:
    """A work-precision scene: registry prefix and scene options of (N, Δt), the initial state
    on N points, the horizon and the full and quick sweeps."""

    name: str
    prefix: str
    dims: int
    title: str
    options: Callable[[int, float], dict]
    initial: Callable[[int], np.ndarray]
    t_end: float
    full: Sweep
    quick: Sweep

    def make(self, order: int, n: int, dt: float) -> Stepper:
        return get(f"{self.prefix}-etdrk{order}")(**self.options(n, dt))

    def resample(self, u: np.ndarray, n: int) -> np.ndarray:
        return (fft1d if self.dims == 1 else fft2d).resample(u, n)


def _ks_options(n: int, dt: float) -> dict:
    return dict(n=n, length=32 * np.pi, dt=dt)


def _ks_initial(n: int) -> np.ndarray:
    return get("ks1d-etdrk4")(**_ks_options(n, 1.0)).kassam_trefethen_state()


def _ns_options(n: int, dt: float) -> dict:
    return dict(n=n, nu=0.01, dt=dt, forcing_wavenumber=4)


def _ns_initial(n: int) -> np.ndarray:
    # Drawn on 32² and resampled: the field is band-limited (|k| ≤ 4), so every grid gets the
    # same one exactly.
    u0 = get("ns2d-etdrk4")(**_ns_options(32, 1.0)).random_state(np.random.default_rng(0), 1)
    return fft2d.resample(u0, n)


SCENES = {
    "ks": Scene(
        "ks", "ks1d", 1, "Kuramoto–Sivashinsky (Kassam–Trefethen), L = 32π, t = 10", _ks_options,
        _ks_initial, 10.0,
        full=Sweep((128, 256), (1, 1 / 2, 1 / 4, 1 / 8, 1 / 16, 1 / 32), 512),
        quick=Sweep((256,), (1, 1 / 2, 1 / 4, 1 / 8), 512),
    ),
    "ns": Scene(
        "ns", "ns2d", 2, "2D Kolmogorov flow, k_f = 4, ν = 0.01, t = 0.5", _ns_options, _ns_initial,
        0.5,
        full=Sweep((64, 128), (0.1, 0.05, 0.025, 0.0125, 0.00625), 256),
        quick=Sweep((64,), (0.1, 0.05, 0.025), 128),
    ),
}


# ----------------------------------------------------------------- NumPy baseline
class NumpyETDRK4:
    """Vectorised NumPy ETDRK4 (numpy.fft, batched) of a KS or 2D Navier–Stokes scene: the same
    discretisation, coefficients and Δt as the scene's stepper, none of its kernels.

    KS: N(v) = −½ i k ⊙ rfft(irfft(v)²) (times the 2/3 mask if the scene dealiases) plus the
    forcing. NS: N(v) = −m ⊙ (i k_x ℱ(u ω) + i k_y ℱ(v ω)) + F̂ with (u, v, ω) from m ⊙ v.
    """

    def __init__(self, stepper: Stepper):
        self.shape = stepper.grid_shape
        if len(self.shape) == 1:
            h = stepper.dt / stepper.substeps
            self.substeps = stepper.substeps
            lin = stepper.linear_operator()
            self._mult = 1j * stepper.nonlinear_multiplier
            self._force = (stepper.forcing_hat * stepper.param_values[-1]
                           if stepper.forcing_hat.size else 0.0)
            self._nonlinear = self._n1d
        else:
            h, self.substeps = stepper.dt, 1
            n = stepper.grid_shape[0]
            params = stepper.params
            kx, ky = fft2d.wavenumbers(n)
            k2 = kx**2 + ky**2
            lin = -params["nu"] * k2 - params.get("drag", 0.0)
            self._dkx, self._dky = fft2d.derivative_wavenumbers(n)
            self._inv_k2 = np.where(k2 > 0, 1.0 / np.where(k2 > 0, k2, 1.0), 0.0)
            self._mask = fft2d.dealias_multiplier(n) if stepper.dealias else 1.0
            self._force = np.zeros(k2.shape, dtype=complex)
            if stepper.forcing_wavenumber is not None:
                kf = stepper.forcing_wavenumber
                self._force[0, kf] = -params["forcing"] * kf * n * n / 2
            self._nonlinear = self._n2d
        self.c = etdrk_coefficients(lin, h, 4)

    def _n1d(self, v: np.ndarray) -> np.ndarray:
        return self._mult * np.fft.rfft(np.fft.irfft(v, self.shape[0]) ** 2) + self._force

    def _n2d(self, v: np.ndarray) -> np.ndarray:
        x = self._mask * v
        psi = self._inv_k2 * x
        u = np.fft.irfft2(1j * self._dky * psi, s=self.shape)
        w = np.fft.irfft2(-1j * self._dkx * psi, s=self.shape)
        omega = np.fft.irfft2(x, s=self.shape)
        fx, fy = np.fft.rfft2(u * omega), np.fft.rfft2(w * omega)
        return -self._mask * (1j * self._dkx * fx + 1j * self._dky * fy) + self._force

    def rollout(self, u0: np.ndarray, n: int) -> np.ndarray:
        """u_n for a batch u0 of shape (B, 1, *grid)."""
        axes = tuple(range(-len(self.shape), 0))
        c, nl = self.c, self._nonlinear
        v = np.fft.rfftn(u0, axes=axes)
        for _ in range(n * self.substeps):
            v = reference_step(v, c, 4, nl)
        return np.fft.irfftn(v, s=self.shape, axes=axes)


# ----------------------------------------------------------------- exponax (optional)
def load_exponax() -> tuple[Any, Any] | None:
    """(jax, exponax) with float64 enabled and XLA on one CPU thread, or None if not installed."""
    os.environ.setdefault("XLA_FLAGS", XLA_ONE_THREAD)
    try:
        import exponax
        import jax
    except ImportError:
        return None
    jax.config.update("jax_enable_x64", True)
    return jax, exponax


def exponax_twin(stepper: Stepper) -> tuple[Any, float]:
    """exponax's stepper for the discretisation of ``stepper`` and the sign s with
    (exponax state) = s · (our state).

    KS (no dealiasing, one sub-step, no forcing): ``KuramotoSivashinskyConservative`` without
    dealiasing. NS: ``KolmogorovFlowVorticity`` (or ``NavierStokesVorticity`` unforced); exponax's
    vorticity has the opposite sign (s = −1), hence the injection scale −a, and its drag is −μ;
    its 2/3 mask keeps |k| ≤ fraction · n/2 − 1 per axis, so fraction = (K + 1.5)/(n/2) keeps
    our K. It evaluates u·∇ω (4 inverse + 1 forward FFT per stage) where we evaluate ∇·(u ω)
    (3 + 2); with the 2/3 rule both are the same Galerkin product, so the two agree to
    round-off. Both use the contour-integral coefficients on 32 points.
    """
    loaded = load_exponax()
    if loaded is None:
        raise ImportError("exponax is not installed (pip install exponax)")
    _, ex = loaded
    common = dict(order=stepper.order, num_circle_points=32)
    if len(stepper.grid_shape) == 1:
        if stepper.dealias or stepper.substeps != 1 or stepper.forcing_hat.size:
            raise ValueError(f"{stepper.name}: exponax has no exact twin of a dealiased, "
                             "sub-stepped or forced KS scene")
        alpha, beta = stepper.param_values[:2]
        twin = ex.stepper.KuramotoSivashinskyConservative(
            1, stepper.length, stepper.grid_shape[0], stepper.dt, second_order_scale=alpha,
            fourth_order_scale=beta, dealiasing_fraction=None, **common,
        )
        return twin, 1.0
    n, params = stepper.n, stepper.params
    fraction = (fft2d.dealias_cutoff(n) + 1.5) / (n // 2) if stepper.dealias else None
    kw = dict(diffusivity=params["nu"], drag=-params.get("drag", 0.0),
              dealiasing_fraction=fraction, **common)
    if stepper.forcing_wavenumber is None:
        twin = ex.stepper.NavierStokesVorticity(2, 2 * np.pi, n, stepper.dt, **kw)
    else:
        twin = ex.stepper.KolmogorovFlowVorticity(
            2, 2 * np.pi, n, stepper.dt, injection_mode=stepper.forcing_wavenumber,
            injection_scale=-params["forcing"], **kw,
        )
    return twin, -1.0


def exponax_rollout(twin: Any, n: int) -> Callable:
    """The jax function u0 (B, C, *grid) → u_n of ``n`` steps of ``twin`` (vmap over the batch,
    lax.scan over the steps); jit it or differentiate it."""
    jax, _ = load_exponax()

    def run(u):
        return jax.lax.scan(lambda c, _: (twin(c), None), u, None, length=n)[0]

    return jax.vmap(run)


# ----------------------------------------------------------------- measuring
def median_times(
    fns: dict[str, Callable[[], Any]], repeats: int = 5, min_time: float = 0.02,
    clock: Callable[[], float] = time.process_time,
) -> dict[str, float]:
    """Median seconds per call of each function over ``repeats`` samples, after one warm-up
    call each. A sample repeats the call until it lasts ``min_time`` (short calls are timed in
    loops); the functions are sampled in turn, so that a change of load on a shared machine
    affects them alike."""
    loops = {}
    for key, fn in fns.items():
        t0 = clock()
        fn()
        loops[key] = max(1, math.ceil(min_time / max(clock() - t0, 1e-9)))
    samples: dict[str, list[float]] = {key: [] for key in fns}
    for _ in range(repeats):
        for key, fn in fns.items():
            t0 = clock()
            for _ in range(loops[key]):
                fn()
            samples[key].append((clock() - t0) / loops[key])
    return {key: float(np.median(v)) for key, v in samples.items()}


def median_time(fn: Callable[[], Any], repeats: int = 5, min_time: float = 0.02) -> float:
    """:func:`median_times` of one function."""
    return median_times({"fn": fn}, repeats, min_time)["fn"]


def relative_error(u: np.ndarray, ref: np.ndarray) -> float:
    """max |u − ref| / max |ref|."""
    return float(np.abs(u - ref).max() / np.abs(ref).max())


def _schemes(scene: Scene, with_exponax: bool) -> list[tuple[str, int, Callable]]:
    """(scheme name, order, factory (N, Δt, steps) → rollout u0 ↦ u_steps)."""
    def ours(order):
        return lambda n, dt, steps: partial(scene.make(order, n, dt).rollout, n=steps)

    def numpy(n, dt, steps):
        return partial(NumpyETDRK4(scene.make(4, n, dt)).rollout, n=steps)

    def exponax(n, dt, steps):
        jax, _ = load_exponax()
        twin, sign = exponax_twin(scene.make(4, n, dt))
        run = jax.jit(exponax_rollout(twin, steps))
        return lambda u0: sign * np.asarray(run(sign * u0).block_until_ready())

    out = [(f"{scene.prefix}-etdrk{o}", o, ours(o)) for o in ORDERS]
    out.append(("numpy-etdrk4", 4, numpy))
    if with_exponax:
        out.append(("exponax-etdrk4", 4, exponax))
    return out


def sweep(
    scene: Scene, quick: bool = False, repeats: int = 5, with_exponax: bool = True,
    progress: bool = True,
) -> list[dict]:
    """Run the sweep of ``scene``: one row (CSV_FIELDS) per scheme, grid and step size."""
    cfg = scene.quick if quick else scene.full
    schemes = _schemes(scene, with_exponax)
    ref_dt = min(cfg.dts) / 16
    ref_steps = round(scene.t_end / ref_dt)
    jobs = [(r, n, dt) for r in schemes for n in cfg.grids for dt in cfg.dts]
    bar = tqdm(total=len(jobs) + 1, desc=f"work-precision {scene.name}", disable=not progress)
    bar.set_postfix_str(f"reference: ETDRK4, N = {cfg.ref_n}, {ref_steps} steps")
    ref = scene.make(4, cfg.ref_n, ref_dt).rollout(scene.initial(cfg.ref_n), ref_steps)
    refs = {n: scene.resample(ref, n) for n in cfg.grids}
    bar.update()
    rows = []
    for (scheme, order, factory), n, dt in jobs:
        bar.set_postfix_str(f"{scheme}, N = {n}, dt = {dt:g}")
        steps = round(scene.t_end / dt)
        run, u0 = factory(n, dt, steps), scene.initial(n)
        error = relative_error(run(u0), refs[n])
        seconds = median_time(partial(run, u0), repeats)
        rows.append(dict(scene=scene.name, scheme=scheme, order=order, n=n, dt=dt, steps=steps,
                         t_end=scene.t_end, error=error, time_s=seconds, ref_n=cfg.ref_n,
                         ref_dt=ref_dt))
        bar.update()
    bar.close()
    return rows


# ----------------------------------------------------------------- output
def write_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        writer.writerows(rows)


def plot(rows: list[dict], scene: Scene, path: Path) -> None:
    """Error against run time, log-log: colour per scheme, line style per grid."""
    plt = pyplot()

    schemes = list(dict.fromkeys(r["scheme"] for r in rows))
    grids = sorted({r["n"] for r in rows}, reverse=True)
    styles = ["-", "--", ":", "-."]
    colours = plt.get_cmap("tab10")
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    for i, scheme in enumerate(schemes):
        for j, n in enumerate(grids):
            pts = sorted((r["time_s"], r["error"]) for r in rows
                         if r["scheme"] == scheme and r["n"] == n)
            if not pts:
                continue
            t, e = zip(*pts)
            grid = f"{n}" if scene.dims == 1 else f"{n}²"
            ax.loglog(t, e, styles[j % len(styles)], marker="o", ms=3.5, color=colours(i),
                      label=f"{scheme}, N = {grid}")
    r0 = rows[0]
    ax.set_xlabel("run time of the rollout [s] (process CPU time, one thread)")
    ax.set_ylabel(f"relative L∞ error at t = {r0['t_end']:g}")
    ax.set_title(f"{scene.title}\nreference: ETDRK4, N = {r0['ref_n']}, Δt = {r0['ref_dt']:.3g}",
                 fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path, dpi=120)


def run(scene_name: str, out: Path, quick: bool = False, repeats: int | None = None,
        exponax: bool = True, progress: bool = True) -> list[dict]:
    """The sweep of one scene: rows, ``work_precision_<scene>.csv`` and ``.png`` in ``out``,
    and the table printed; ``exponax=False`` leaves the peer out."""
    scene = SCENES[scene_name]
    with_exponax = exponax and load_exponax() is not None
    if exponax and not with_exponax:
        print("exponax: skipped (not installed; pip install exponax)")
    rows = sweep(scene, quick, repeats or (3 if quick else 5), with_exponax, progress)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / f"work_precision_{scene.name}.csv"
    png_path = out / f"work_precision_{scene.name}.png"
    write_csv(rows, csv_path)
    plot(rows, scene, png_path)
    print(f"{'scheme':<16} {'N':>4} {'dt':>9} {'steps':>6} {'error':>9} {'time [ms]':>10}")
    for r in rows:
        print(f"{r['scheme']:<16} {r['n']:>4} {r['dt']:>9.4g} {r['steps']:>6} "
              f"{r['error']:>9.2e} {1e3 * r['time_s']:>10.3f}")
    print(f"wrote {csv_path} and {png_path}")
    return rows
