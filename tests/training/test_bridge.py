"""The torch bridge: gradcheck for every registered solver, zero-copy inputs, clear errors."""

import numpy as np
import pytest
import torch

import adjointsim
from adjointsim.train import bridge

NAMES = adjointsim.names()


def _inputs(stepper, n, dtype=torch.float64, batch=2):
    rng = np.random.default_rng(0)
    u0 = torch.from_numpy(stepper.random_state(rng, batch)).to(dtype).requires_grad_()
    ctrl = None
    if stepper.control_shape is not None:
        ctrl = torch.from_numpy(stepper.random_controls(rng, n, batch)).to(dtype).requires_grad_()
    params = None
    if stepper.param_names:
        params = torch.tensor(stepper.param_values, dtype=dtype, requires_grad=True)
    return u0, ctrl, params


@pytest.mark.parametrize("name", NAMES)
def test_torch_gradcheck_every_solver(name):
    stepper = adjointsim.get(name).default()
    n = 3
    u0, ctrl, params = _inputs(stepper, n)
    inputs = [x for x in (u0, ctrl, params) if x is not None]

    def f(*xs):
        it = iter(xs)
        u = next(it)
        c = next(it) if ctrl is not None else None
        p = next(it) if params is not None else None
        return bridge.rollout(stepper, u, n, c, p, keep="all")

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_grouped_rollout_is_one_node_with_each_rows_own_scene():
    ks = adjointsim.get("ks1d-etdrk1")
    small, large = (ks(n=48, length=2 * np.pi * 8 * f, dt=1.0, substeps=2) for f in (0.9, 1.3))
    rng = np.random.default_rng(1)
    u0 = torch.from_numpy(small.random_state(rng, 5)).requires_grad_()
    groups = [(small, np.array([0, 3])), (large, np.array([1, 2, 4]))]

    def f(u):
        return bridge.rollout_grouped(groups, u, 2)

    assert torch.autograd.gradcheck(f, (u0,), eps=1e-6, atol=1e-6, rtol=1e-4)
    out = f(u0)
    torch.testing.assert_close(out[[0, 3]], bridge.rollout(small, u0[[0, 3]].detach(), 2))
    torch.testing.assert_close(out[[1, 2, 4]], bridge.rollout(large, u0[[1, 2, 4]].detach(), 2))
    before = bridge.ADJOINT_CALLS["count"]
    out.square().sum().backward()
    assert bridge.ADJOINT_CALLS["count"] == before + 1


@pytest.mark.parametrize("keep", ["last", "all"])
def test_in_place_edits_after_the_forward_do_not_change_the_gradient(keep):
    stepper = adjointsim.get("burgers1d-rusanov").default()
    u0, _, _ = _inputs(stepper, 4)
    (expected,) = torch.autograd.grad(bridge.rollout(stepper, u0, 4, keep=keep).sum(), u0)
    x = u0.detach().clone().requires_grad_()
    out = bridge.rollout(stepper, x, 4, keep=keep)
    with torch.no_grad():
        x.mul_(3.0)
    out.detach().mul_(-2.0)  # shares memory with out
    (got,) = torch.autograd.grad(out.sum(), x)
    torch.testing.assert_close(got, expected)


def test_checkpointed_backward_matches_stored():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, ctrl, params = _inputs(stepper, 20)
    grads = []
    for checkpoint in (None, 5):
        out = bridge.rollout(stepper, u0, 20, ctrl, params, checkpoint=checkpoint)
        grads.append(torch.autograd.grad(out.square().sum(), (u0, ctrl, params)))
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


def test_no_grad_runs_no_adjoint_and_stores_nothing():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, _, _ = _inputs(stepper, 5)
    before = bridge.ADJOINT_CALLS["count"]
    with torch.no_grad():
        out = bridge.rollout(stepper, u0, 5)
    assert out.grad_fn is None
    out = bridge.rollout(stepper, u0.detach(), 5)
    assert out.grad_fn is None
    assert bridge.ADJOINT_CALLS["count"] == before


def test_no_grad_keeps_no_trajectory_even_for_inputs_that_require_grad(monkeypatch):
    """ctx.needs_input_grad is True under torch.no_grad() too: the forward must not trust it."""
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, _, _ = _inputs(stepper, 5)
    params = torch.tensor(stepper.param_values, dtype=u0.dtype, requires_grad=True)
    saved = []
    forward = bridge._forward

    def spy(*args, **kwargs):
        out, kept = forward(*args, **kwargs)
        saved.append(kept)
        return out, kept

    monkeypatch.setattr(bridge, "_forward", spy)
    with torch.no_grad():
        bridge.rollout(stepper, u0, 5, params=params)
        bridge.step(stepper, u0, params=params)
        bridge.rollout_grouped([(stepper, slice(None))], u0, 5)
    assert saved == [None, None, None]


@pytest.mark.parametrize("keep", ["last", "all"])
@pytest.mark.parametrize("checkpoint", [None, 3])
def test_inputs_are_validated_once_and_both_passes_take_the_fast_path(keep, checkpoint):
    stepper = adjointsim.get("ks1d-etdrk4").default()  # a taped stepper
    n = 4
    u0, ctrl, params = _inputs(stepper, n)
    calls: dict[str, int] = {}
    for name in ("prepare", "check_state", "check_controls", "check_cotangents", "param_array",
                 "rollout", "vjp", "rollout_prepared", "vjp_prepared"):
        method = getattr(stepper, name)

        def counted(*args, _name=name, _method=method, **kwargs):
            calls[_name] = calls.get(_name, 0) + 1
            return _method(*args, **kwargs)

        setattr(stepper, name, counted)
    out = bridge.rollout(stepper, u0, n, ctrl, params, keep=keep, checkpoint=checkpoint)
    w = torch.from_numpy(np.random.default_rng(3).standard_normal(out.shape))
    grads = torch.autograd.grad(out, (u0, ctrl, params), w)
    # A checkpoint adds one vjp_prepared of zero steps on an empty batch: the stepper's check
    # of it, made before the rollout.
    assert calls == {"check_state": 1, "check_controls": 1, "param_array": 1,
                     "rollout_prepared": 1, "vjp_prepared": 1 + (checkpoint is not None)}
    # ... and the same numbers as the checked path, bit for bit.
    arrays = [x.detach().numpy() for x in (u0, ctrl, params)]
    cot = w.numpy() if keep == "all" else {-1: w.numpy()}
    ref = stepper.vjp(arrays[0], n, cot, arrays[1], arrays[2], wrt_params=True,
                      checkpoint=checkpoint)
    expected = (ref.state, ref.controls, np.array(list(ref.params.values())))
    for got, want in zip(grads, expected, strict=True):
        assert got.numpy().tobytes() == want.tobytes()
    rolled = stepper.rollout(arrays[0], n, arrays[1], arrays[2], keep=keep)
    assert out.detach().numpy().tobytes() == rolled.tobytes()


def test_float32_in_float32_out():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, ctrl, params = _inputs(stepper, 4, dtype=torch.float32)
    out = bridge.rollout(stepper, u0, 4, ctrl, params)
    assert out.dtype == torch.float32
    out.sum().backward()
    assert u0.grad.dtype == ctrl.grad.dtype == params.grad.dtype == torch.float32


def test_bad_tensors_get_clear_errors():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, ctrl, params = _inputs(stepper, 4)
    with pytest.raises(TypeError, match="cast it"):
        bridge.rollout(stepper, u0, 4, ctrl, params.float())
    with pytest.raises(TypeError, match="float32 or torch.float64"):
        bridge.rollout(stepper, u0.detach().to(torch.float16), 4)
    meta = torch.empty(u0.shape, device="meta", dtype=torch.float64)
    with pytest.raises(ValueError, match="CPU"):
        bridge.rollout(stepper, meta, 4)


def test_tensors_of_any_strides_give_the_contiguous_numbers_and_gradients():
    """A transposed, strided or expanded view is taken as it is (copied once, only then)."""
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, ctrl, params = _inputs(stepper, 3, batch=4)
    views = [
        (u0.detach().transpose(0, 2).contiguous().transpose(0, 2), ctrl.detach(), params),
        (torch.cat([u0, u0]).detach()[::2], torch.cat([ctrl, ctrl], 1).detach()[:, ::2], params),
        (u0.detach()[:1].expand(4, -1, -1), ctrl.detach()[:, :1].expand(-1, 4, *ctrl.shape[2:]),
         params.detach().repeat(2)[::2]),
    ]
    for u, c, p in views:
        assert not (u.is_contiguous() and c.is_contiguous() and p.is_contiguous())
        u, c, p = (x.requires_grad_() if not x.requires_grad else x for x in (u, c, p))
        out = bridge.rollout(stepper, u, 3, c, p)
        dense = [x.detach().contiguous().requires_grad_() for x in (u, c, p)]
        ref = bridge.rollout(stepper, *dense[:1], 3, *dense[1:])
        assert out.detach().numpy().tobytes() == ref.detach().numpy().tobytes()
        w = torch.from_numpy(np.random.default_rng(5).standard_normal(out.shape))
        got = torch.autograd.grad(out, (u, c, p), w)
        want = torch.autograd.grad(ref, dense, w)
        for a, b in zip(got, want, strict=True):
            assert a.numpy().tobytes() == b.numpy().tobytes()
    one = bridge.step(stepper, u0.detach().transpose(0, 2).contiguous().transpose(0, 2),
                      ctrl.detach()[0].transpose(0, -1).contiguous().transpose(0, -1))
    ref = bridge.step(stepper, u0.detach(), ctrl.detach()[0].contiguous())
    assert one.numpy().tobytes() == ref.numpy().tobytes()


def test_a_stepper_dropped_after_the_forward_pass_still_runs_the_backward_pass():
    """The operators know a stepper by a key into a weak table; the graph keeps it alive."""
    import gc

    u0, _, _ = _inputs(adjointsim.get("burgers1d-rusanov").default(), 2, batch=3)
    out = bridge.rollout(adjointsim.get("burgers1d-rusanov").default(), u0, 2)
    grouped = bridge.rollout_grouped(
        [(adjointsim.get("burgers1d-rusanov").default(), slice(None))], u0, 2)
    gc.collect()
    (g,) = torch.autograd.grad(out.square().sum() + grouped.square().sum(), u0)
    stepper = adjointsim.get("burgers1d-rusanov").default()
    (want,) = torch.autograd.grad(2 * bridge.rollout(stepper, u0, 2).square().sum(), u0)
    torch.testing.assert_close(g, want, rtol=1e-14, atol=0)


# ------------------------------------------------------------------ edges
@pytest.mark.parametrize("name", NAMES)
def test_zero_steps_and_empty_batches_through_the_bridge(name):
    """n = 0 returns u0 (the cotangent passes straight through), B = 0 gives empty results,
    and otherwise the bridge agrees with the stepper, for every registered solver."""
    stepper = adjointsim.get(name).default()
    for batch in (0, 1, 3):
        for n in (0, 1, 2):
            u0, ctrl, params = _inputs(stepper, n, batch=batch)
            inputs = [x for x in (u0, ctrl, params) if x is not None]
            for keep in ("last", "all"):
                out = bridge.rollout(stepper, u0, n, ctrl, params, keep=keep)
                shape = u0.shape if keep == "last" else (n + 1, *u0.shape)
                assert out.shape == shape
                w = torch.from_numpy(np.random.default_rng(n).standard_normal(shape))
                grads = torch.autograd.grad((w * out).sum(), inputs)
                for x, g in zip(inputs, grads, strict=True):
                    assert g.shape == x.shape and torch.isfinite(g).all()
                if n == 0:
                    torch.testing.assert_close(out.reshape(u0.shape), u0.detach(), rtol=0, atol=0)
                    assert batch == 0 or out.data_ptr() != u0.data_ptr()
                    torch.testing.assert_close(grads[0], w.reshape(u0.shape), rtol=0, atol=0)
                    for g in grads[1:]:
                        assert not g.any()
                elif batch:
                    c = None if ctrl is None else ctrl.detach().numpy()
                    p = None if params is None else params.detach().numpy()
                    expected = stepper.rollout(u0.detach().numpy(), n, c, p, keep=keep)
                    np.testing.assert_allclose(out.detach().numpy(), expected, rtol=1e-12)


def test_zero_steps_with_checkpointing_and_step_on_an_empty_batch():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, _, _ = _inputs(stepper, 0)
    out = bridge.rollout(stepper, u0, 0, checkpoint=4)
    (g,) = torch.autograd.grad(out.sum() * 3.0, u0)
    torch.testing.assert_close(g, torch.full_like(u0, 3.0))
    u, ctrl, params = _inputs(stepper, 1, batch=0)
    out = bridge.step(stepper, u, ctrl[0].detach().requires_grad_(), params)
    assert out.shape == u.shape
    out.sum().backward()
    assert u.grad.shape == u.shape and params.grad.shape == params.shape


@pytest.mark.parametrize("n", [-1, 2.5, 1.0, "3", None, True])
def test_invalid_step_counts_get_a_clear_error(n):
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, _, _ = _inputs(stepper, 1)
    with pytest.raises(ValueError, match="non-negative integer"):
        bridge.rollout(stepper, u0, n)
    with pytest.raises(ValueError, match="non-negative integer"):
        bridge.rollout_grouped([(stepper, slice(None))], u0, n)


# ------------------------------------------------------------------ second derivatives
ONCE = "once-differentiable"


def test_gradgradcheck_raises_the_clear_error_and_gradcheck_still_passes():
    stepper = adjointsim.get("burgers1d-rusanov").default()
    u0, _, _ = _inputs(stepper, 2)

    def f(u):
        return bridge.rollout(stepper, u, 2)

    assert torch.autograd.gradcheck(f, (u0,), eps=1e-6, atol=1e-6, rtol=1e-4)
    with pytest.raises(RuntimeError, match=f"burgers1d-rusanov.*{ONCE}.*finite differences"):
        torch.autograd.gradgradcheck(f, (u0,))


@pytest.mark.parametrize("objective", ["square", "linear"])
def test_gradient_penalty_raises_instead_of_dropping_its_term(objective):
    """The issue's case: a gradient penalty through a nonlinear solver. Its second derivative
    is not zero even when the objective is linear in the output (then the incoming cotangent
    does not require grad, and torch's once_differentiable would return a graph-less gradient
    whose penalty term is silently lost)."""
    stepper = adjointsim.get("burgers1d-rusanov").default()
    u0, _, _ = _inputs(stepper, 3)
    out = bridge.rollout(stepper, u0, 3)
    loss = out.square().sum() if objective == "square" else out.sum()
    (g,) = torch.autograd.grad(loss, u0, create_graph=True)
    assert g.requires_grad
    with pytest.raises(RuntimeError, match=ONCE):
        (loss + g.square().sum()).backward()


def test_grouped_rollout_is_once_differentiable_too():
    stepper = adjointsim.get("burgers1d-rusanov").default()
    u0, _, _ = _inputs(stepper, 1, batch=3)

    def f(u):
        return bridge.rollout_grouped([(stepper, np.array([0, 2])), (stepper, [1])], u, 1)

    with pytest.raises(RuntimeError, match=ONCE):
        torch.autograd.gradgradcheck(f, (u0,))


def test_create_graph_is_fine_when_the_second_backward_avoids_the_solver():
    """d/du0 of (d/dw L)² with L = Σ w · S(u0): the second pass runs the solver's first-order
    adjoint only, so the answer is exact: 2 (Σ S(u0)) · S'(u0)^T 1."""
    stepper = adjointsim.get("burgers1d-rusanov").default()
    u0, _, _ = _inputs(stepper, 2)
    w = torch.tensor(1.5, dtype=torch.float64, requires_grad=True)
    out = bridge.rollout(stepper, u0, 2)
    g_w, _ = torch.autograd.grad((w * out).sum(), (w, u0), create_graph=True)
    (got,) = torch.autograd.grad(g_w.square(), u0)
    (jt1,) = torch.autograd.grad(bridge.rollout(stepper, u0, 2).sum(), u0)
    torch.testing.assert_close(got, 2.0 * out.sum().detach() * jt1)


# ------------------------------------------------------------------ grouped rollouts
def test_groups_must_partition_the_batch():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, _, _ = _inputs(stepper, 1, batch=5)
    cases = {
        "rows \\[2, 4\\] are in no group": [(stepper, [0, 1]), (stepper, np.array([3]))],
        "rows \\[1\\] are in more than one group": [(stepper, [0, 1, 2]), (stepper, [1, 3, 4])],
        "rows \\[-1, 7\\] are outside the batch 0..4": [(stepper, [0, 1, 2, 3, 4, 7, -1])],
        "boolean row mask needs shape \\(5,\\)": [(stepper, np.ones(4, dtype=bool))],
        "1-D integer array": [(stepper, np.array([0.0, 1.0]))],
        "in no group": [],
    }
    for message, groups in cases.items():
        with pytest.raises(ValueError, match=message):
            bridge.rollout_grouped(groups, u0, 1)


def test_grouped_rollout_with_empty_groups_masks_and_zero_steps():
    small = adjointsim.get("diffusion1d-ftcs")(n=16, nu=0.05)
    large = adjointsim.get("diffusion1d-ftcs")(n=16, nu=0.1)
    u0, _, _ = _inputs(small, 2, batch=4)
    mask = np.array([True, False, True, False])
    groups = [(small, mask), (large, np.array([], dtype=int)), (large, slice(1, None, 2))]

    def f(u):
        return bridge.rollout_grouped(groups, u, 2)

    assert torch.autograd.gradcheck(f, (u0,), eps=1e-6, atol=1e-6, rtol=1e-4)
    out = f(u0)
    torch.testing.assert_close(out[mask], bridge.rollout(small, u0[mask].detach(), 2))
    torch.testing.assert_close(out[1::2], bridge.rollout(large, u0[1::2].detach().contiguous(), 2))
    same = bridge.rollout_grouped(groups, u0, 0)
    torch.testing.assert_close(same, u0.detach(), rtol=0, atol=0)
    (g,) = torch.autograd.grad(same.sum(), u0)
    torch.testing.assert_close(g, torch.ones_like(u0))
    empty = u0[:0].detach().requires_grad_()
    out = bridge.rollout_grouped([(small, slice(None))], empty, 2)
    assert out.shape == empty.shape
    (g,) = torch.autograd.grad(out.sum(), empty)
    assert g.shape == empty.shape


# ------------------------------------------------------------------ validation in the forward call
BAD_CHECKPOINTS = [2, 0, -1, 2.5, "8", True]


@pytest.mark.parametrize("checkpoint", BAD_CHECKPOINTS)
@pytest.mark.parametrize("grad", [True, False])
def test_bad_checkpoints_are_refused_before_the_rollout_runs(checkpoint, grad, monkeypatch):
    """With the stepper's own message, with or without a backward pass to come."""
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u0, ctrl, params = _inputs(stepper, 5)
    try:
        stepper.vjp(u0.detach().numpy(), 5, np.ones(u0.shape), checkpoint=checkpoint)
    except ValueError as e:
        expected = str(e)
    else:
        raise AssertionError(f"the stepper accepts checkpoint={checkpoint!r}")

    def no_kernel(*args):
        raise AssertionError("the rollout ran before checkpoint was checked")

    monkeypatch.setattr(stepper, "_forward", no_kernel)
    with torch.set_grad_enabled(grad), pytest.raises(ValueError) as info:
        bridge.rollout(stepper, u0, 5, ctrl, params, checkpoint=checkpoint)
    assert str(info.value) == expected


def _numpy_inputs(stepper, n, batch=2):
    u0, ctrl, params = _inputs(stepper, n, batch=batch)
    return u0.detach().numpy(), ctrl.detach().numpy(), params.detach().numpy()


@pytest.mark.parametrize("keep", ["last", "all"])
def test_numpy_arrays_in_tensors_out(keep):
    """Zero-copy, the stepper's numbers bit for bit, and gradients for the tensors among them."""
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u, c, p = _numpy_inputs(stepper, 3)
    before = [a.copy() for a in (u, c, p)]
    expected = stepper.rollout(u, 3, c, p, keep=keep)
    out = bridge.rollout(stepper, u, 3, c, p, keep=keep)
    assert isinstance(out, torch.Tensor) and out.grad_fn is None
    assert out.numpy().tobytes() == expected.tobytes()
    for a, b in zip((u, c, p), before, strict=True):
        np.testing.assert_array_equal(a, b)
    # A tensor among arrays still gets its gradient.
    ctrl = torch.from_numpy(c).requires_grad_()
    out = bridge.rollout(stepper, u, 3, ctrl, p, keep=keep)
    (g,) = torch.autograd.grad(out.sum(), ctrl)
    ref = stepper.vjp(u, 3, np.ones(out.shape) if keep == "all" else np.ones(u.shape), c, p)
    assert g.numpy().tobytes() == ref.controls.tobytes()
    # One step, and a grouped rollout.
    one = bridge.step(stepper, u, c[0], p)
    assert one.numpy().tobytes() == stepper.step(u, c[0], p).tobytes()
    grouped = bridge.rollout_grouped([(stepper, slice(None))], u, 3)
    assert grouped.numpy().tobytes() == stepper.rollout(u, 3).tobytes()


def test_numpy_arrays_of_any_layout_and_read_only_ones_are_taken_as_the_stepper_takes_them():
    import warnings

    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u, c, p = _numpy_inputs(stepper, 2, batch=4)
    strided, reversed_rows = u[::2], u[::-1]
    frozen = c.copy()
    frozen.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # torch warns about read-only arrays: not for ours
        for x in (strided, reversed_rows):
            out = bridge.rollout(stepper, x, 2)
            assert out.numpy().tobytes() == stepper.rollout(x, 2).tobytes()
        out = bridge.rollout(stepper, u, 2, frozen, p)
        assert out.numpy().tobytes() == stepper.rollout(u, 2, frozen, p).tobytes()


def test_inputs_that_are_neither_tensors_nor_arrays_are_refused_by_name():
    stepper = adjointsim.get("diffusion1d-ftcs").default()
    u, c, p = _numpy_inputs(stepper, 1)
    pass_one = "pass a torch.Tensor or a NumPy array"
    cases = [
        (lambda: bridge.rollout(stepper, u.tolist(), 1), f"u0 is a list; {pass_one}"),
        (lambda: bridge.rollout(stepper, None, 1), f"u0 is None; {pass_one}"),
        (lambda: bridge.rollout(stepper, u, 1, c.tolist()), f"controls is a list; {pass_one}"),
        (lambda: bridge.rollout(stepper, u, 1, c, tuple(p)), f"params is a tuple; {pass_one}"),
        (lambda: bridge.step(stepper, u.tolist()), f"u is a list; {pass_one}"),
        (lambda: bridge.step(stepper, u, c[0].tolist()), f"control is a list; {pass_one}"),
        (lambda: bridge.step(stepper, u, c[0], 0.05), f"params is a float; {pass_one}"),
        (lambda: bridge.rollout_grouped([(stepper, slice(None))], u.tolist(), 1),
         f"u0 is a list; {pass_one}"),
    ]
    for call, message in cases:
        with pytest.raises(TypeError, match=message.replace("(", r"\(")):
            call()
    with pytest.raises(TypeError, match=r"u0 is a NumPy array of dtype int64; expected float32 "
                       r"or float64 \(convert with u0.astype\(np.float64\)\)"):
        bridge.rollout(stepper, u.astype(np.int64), 1)


def test_something_other_than_a_scene_is_named_not_a_weakref_error():
    """a registry name or a solver class failed deep in weakref or in the stepper's checks."""
    cls = adjointsim.get("diffusion1d-ftcs")
    u0 = torch.zeros(2, 1, 16)
    for solver, what in (("diffusion1d-ftcs", "str 'diffusion1d-ftcs'"),
                         (cls, f"the class {cls.__name__}")):
        with pytest.raises(TypeError, match=f"the solver given is {what}, not a scene of one; "
                                            r"pass an instance, such as adjointsim\.get\(name\)"):
            bridge.rollout(solver, u0, 3)
        with pytest.raises(TypeError, match=f"the solver given is {what}"):
            bridge.step(solver, u0)
        with pytest.raises(TypeError, match=f"the solver given is {what}"):
            bridge.rollout_grouped([(solver, slice(None))], u0, 3)


def test_a_tape_too_long_to_keep_names_checkpointing():
    s = adjointsim.get("diffusion1d-ftcs")(n=2**22)  # 305 TiB of states: beyond any address space
    u0 = torch.zeros(1, 1, 2**22, dtype=torch.float64, requires_grad=True)
    with pytest.raises(MemoryError, match=r"keeping the 10000001 states .*; pass checkpoint=s"):
        bridge.rollout(s, u0, 10**7)
