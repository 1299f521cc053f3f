"""PhiFlow's twin of ``incompressible2d-sl``'s benchmark scene, for ``incompressible.py``.

The same flow with PhiFlow's own operators on its torch backend (float64, one thread): a
channel of 2n × n cells and length 2, uniform inflow of speed 1 on the left, a zero-gradient
outflow on the right, free-slip walls (normal velocity zero, tangential zero gradient), the
cylinder of diameter ¼ of the height centred half a height from the inflow, ν, buoyancy on an
advected smoke density, Δt; each step in our order: semi-Lagrangian advection of the density and
the velocity, explicit diffusion, buoyancy, ``fluid.make_incompressible`` with the cylinder as
an obstacle. PhiFlow's torch backend has no direct sparse solve, so its pressure is solved by
conjugate gradients to a relative and absolute tolerance of 1e-8 (ours: a direct solve,
factorised once). The step is compiled with ``math.jit_compile`` (traced once; the function
takes and returns value tensors, so every call reuses the trace) and the gradient is
``math.gradient`` of ⟨w, state after ``steps`` steps⟩ (torch autograd through the traced steps,
PhiFlow's implicit adjoint for the pressure solve).

PhiFlow stores only the faces its boundary conditions leave free; ours stores every face: its
x-velocity is our u[1:], its y-velocity our v[:, 1:-1]. ``prepare`` starts from our state, so
the two flows can be compared step for step (the solvers differ in the obstacle's faces, the
advection's boundary samples and the solve's tolerance: the comparison says the twin is the
same scene, not that it agrees to round-off).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np


def prepare(stepper, u0: np.ndarray, w: np.ndarray, steps: int) -> dict[str, Callable]:
    """``forward()`` (``steps`` steps from ``u0``, batch 1) and ``gradient()`` (the gradient of
    ⟨w, u_steps⟩ in the velocity and the density), and ``last()``: the state after ``steps``
    steps in our layout, to compare with ours."""
    import torch
    from phi.torch import flow as phi
    from phiml.math.extrapolation import combine_by_direction

    torch.set_num_threads(1)
    # PhiFlow builds its pressure matrix as a torch sparse CSR tensor, which torch flags as beta
    warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
    phi.math.set_global_precision(64)
    math = phi.math
    nx, ny = stepper.nx, stepper.ny
    domain = {"x": nx, "y": ny, "bounds": phi.Box(x=stepper.length, y=ny * stepper.h)}
    nu, buoyancy, inflow = (stepper.params[k] for k in ("nu", "buoyancy", "inflow_speed"))
    slip = combine_by_direction(normal=0, tangential=phi.ZERO_GRADIENT)
    velocity = phi.StaggeredGrid(0, {"x-": phi.vec(x=inflow, y=0.0), "x+": phi.ZERO_GRADIENT,
                                     "y": slip}, **domain)
    smoke = phi.CenteredGrid(0, phi.ZERO_GRADIENT, **domain)
    radius = ny * stepper.h / 8
    cylinder = phi.Obstacle(phi.Sphere(x=ny * stepper.h / 2, y=ny * stepper.h / 2,
                                       radius=radius))
    dt, solve = stepper.dt, phi.Solve("scipy-direct")

    def step(vv, sv):
        v, s = velocity.with_values(vv), smoke.with_values(sv)
        s = phi.advect.semi_lagrangian(s, v, dt)
        v = phi.advect.semi_lagrangian(v, v, dt)
        v = phi.diffuse.explicit(v, nu, dt)
        # on the values: a sum of fields may take another boundary, and the projection reads it
        v = v.with_values(v.values + dt * buoyancy * (s * (0, 1)).at(v).values)
        v, _ = phi.fluid.make_incompressible(v, cylinder, solve)
        return v.values, s.values

    jstep = math.jit_compile(step)
    xy = phi.spatial("x,y")

    def values(u: np.ndarray):
        vv = math.stack({"x": math.tensor(u[0, 1:, :ny], xy, convert=True),
                         "y": math.tensor(u[1, :nx, 1:ny], xy, convert=True)},
                        phi.dual(vector="x,y"))
        return vv, math.tensor(u[2, :nx, :ny], xy, convert=True)

    def rollout(vv, sv):
        for _ in range(steps):
            vv, sv = jstep(vv, sv)
        return vv, sv

    start, (wv, ws) = values(u0[0]), values(w[0])

    def loss(vv, sv):
        vv, sv = rollout(vv, sv)
        return math.sum(vv * wv) + math.sum(sv * ws)

    grad = math.gradient(loss, wrt="vv,sv", get_output=False)

    def last() -> np.ndarray:
        vv, sv = rollout(*start)
        out = np.zeros_like(u0)
        out[0, 0, 1:, :ny] = vv[{"~vector": "x"}].numpy("x,y")
        out[0, 0, 0, :ny] = inflow  # the inflow faces
        out[0, 1, :nx, 1:ny] = vv[{"~vector": "y"}].numpy("x,y")
        out[0, 2, :nx, :ny] = sv.numpy("x,y")
        return out

    return {"forward": lambda: rollout(*start), "gradient": lambda: grad(*start), "last": last}
