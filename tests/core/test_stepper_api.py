"""The shared contract: validation messages, non-finite detection, cotangent forms, the fast
path (validate once, then run and reverse), re-entrant steppers, no caller of the steppers'
private methods."""

import re
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest

import adjointsim
from adjointsim import NonFiniteStateError
from adjointsim.stepper import Stepper

FTCS = adjointsim.get("diffusion1d-ftcs")
ROOT = Path(__file__).resolve().parents[2]


def test_unknown_solver_lists_the_registered_ones():
    with pytest.raises(KeyError, match="diffusion1d-ftcs"):
        adjointsim.get("no-such-solver")


def test_bad_state_shape_and_dtype_say_what_is_expected():
    s = FTCS(n=16)
    with pytest.raises(ValueError, match=r"expected \(B, 1, 16\)"):
        s.rollout(np.zeros((2, 16)), 1)
    with pytest.raises(TypeError, match="expected float32 or float64"):
        s.rollout(np.zeros((2, 1, 16), dtype=np.int64), 1)
    bad = np.zeros((3, 1, 16))
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match=r"non-finite values in batch element\(s\) \[1\]"):
        s.rollout(bad, 1)


def test_bad_controls_and_params():
    s = FTCS(n=16)
    u = np.zeros((2, 1, 16))
    with pytest.raises(ValueError, match=r"expected \(3, 2, 1, 16\)"):
        s.rollout(u, 3, controls=np.zeros((3, 1, 16)))
    with pytest.raises(TypeError, match="dtype"):
        s.rollout(u, 3, controls=np.zeros((3, 2, 1, 16), dtype=np.float32))
    with pytest.raises(ValueError, match="its parameters are"):
        s.rollout(u, 1, params={"viscosity": 1.0})
    with pytest.raises(ValueError, match=r"parameters must be finite, got nu = nan$"):
        s.rollout(u, 1, params={"nu": np.nan})
    with pytest.raises(ValueError, match="keep must be"):
        s.rollout(u, 1, keep="some")


def test_stability_limit_names_the_largest_stable_dt():
    s = FTCS(n=16, nu=1.0)
    limit = 0.5 * s.h**2
    with pytest.raises(ValueError, match=r"largest stable Δt is ([0-9.e-]+)") as err:
        FTCS(n=16, nu=1.0, dt=1.01 * limit)
    stated = float(re.search(r"largest stable Δt is ([0-9.e-]+)", str(err.value)).group(1))
    assert stated == pytest.approx(limit, rel=1e-5)
    with pytest.raises(ValueError, match="stability limit"):
        s.rollout(np.zeros((1, 1, 16)), 1, params={"nu": 3.0})


def test_blow_up_reports_the_first_non_finite_step():
    s = FTCS(n=16, nu=1.0)
    n = 1999
    u = np.random.default_rng(0).standard_normal((1, 1, 16))
    ctrl = np.zeros((n, 1, 1, 16))
    ctrl[600:] = 1e308  # finite controls whose accumulated effect overflows
    with np.errstate(all="ignore"):
        traj = s.rollout_prepared(*s.prepare(u, n, ctrl), keep="all", check_finite=False)
    first = int(np.argmax(~np.isfinite(traj).reshape(n + 1, -1).all(axis=1)))
    assert 256 < first < n  # exercises the chunked replay
    with pytest.raises(NonFiniteStateError, match=f"non-finite at step {first} ") as err:
        with np.errstate(all="ignore"):
            s.rollout(u, n, controls=ctrl)
    assert err.value.step == first


def test_cotangent_forms_agree():
    s = FTCS(n=12)
    rng = np.random.default_rng(1)
    u = rng.standard_normal((2, 1, 12))
    n = 5
    every = rng.standard_normal((n + 1, 2, 1, 12))
    as_dict = s.vjp(u, n, {k: every[k] for k in range(n + 1)}).state
    np.testing.assert_allclose(s.vjp(u, n, every).state, as_dict, rtol=1e-14)
    last = s.vjp(u, n, every[n]).state
    np.testing.assert_allclose(s.vjp(u, n, {-1: every[n]}).state, last, rtol=1e-14)
    with pytest.raises(ValueError, match="outside the rollout"):
        s.vjp(u, n, {n + 1: every[0]})


def test_zero_steps_is_identity():
    s = FTCS(n=12)
    u = np.random.default_rng(2).standard_normal((1, 1, 12))
    np.testing.assert_array_equal(s.rollout(u, 0), u)
    np.testing.assert_array_equal(s.vjp(u, 0, u).state, u)


def test_checkpoint_budget_names_its_minimum():
    s = FTCS(n=12)
    u = np.random.default_rng(3).standard_normal((1, 1, 12))
    for bad in (2, 4.5, True):
        with pytest.raises(ValueError, match="at least 3 stored states"):
            s.vjp(u, 5, u, checkpoint=bad)
    np.testing.assert_allclose(s.vjp(u, 5, u, checkpoint=3).state, s.vjp(u, 5, u).state,
                               rtol=1e-14)


# ------------------------------------------------------------------ the fast path
VALIDATORS = ("check_state", "check_controls", "check_cotangents", "param_array")


def count_validation(stepper) -> dict[str, int]:
    """Count the calls of each public validator of one stepper."""
    calls = dict.fromkeys(VALIDATORS, 0)
    for name in VALIDATORS:
        method = getattr(stepper, name)

        def counted(*args, _name=name, _method=method, **kwargs):
            calls[_name] += 1
            return _method(*args, **kwargs)

        setattr(stepper, name, counted)
    return calls


def same_bits(a, b) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def same_cotangents(a, b) -> bool:
    controls = (a.controls is None and b.controls is None) or same_bits(a.controls, b.controls)
    return same_bits(a.state, b.state) and controls and a.params == b.params


def test_prepare_returns_the_checked_inputs_and_raises_what_rollout_raises():
    s = FTCS(n=16)
    u = np.asfortranarray(np.random.default_rng(0).standard_normal((2, 1, 16)))
    u0, n, c, p = s.prepare(u, 3.0)
    assert u0.flags.c_contiguous and n == 3 and isinstance(n, int)
    assert c.shape == (0, 2, 1, 16) and c.dtype == u0.dtype
    assert p.dtype == u0.dtype and p.tolist() == list(s.param_values)
    u32, _, _, p32 = s.prepare(u.astype(np.float32), 3, params={"nu": 0.125})
    assert u32.dtype == p32.dtype == np.float32 and p32.tolist() == [0.125]
    with pytest.raises(ValueError, match=r"expected \(B, 1, 16\)"):
        s.prepare(np.zeros((2, 16)), 1)
    with pytest.raises(ValueError, match=r"expected \(3, 2, 1, 16\)"):
        s.prepare(u, 3, controls=np.zeros((3, 1, 16)))
    with pytest.raises(ValueError, match="non-negative integer"):
        s.prepare(u, -1)
    with pytest.raises(ValueError, match="stability limit"):
        s.prepare(u, 1, params={"nu": 1e3})


@pytest.mark.parametrize(
    "name", ["diffusion1d-ftcs", "schrodinger1d-cn", "ks1d-etdrk4", "ns2d-etdrk2"]
)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_fast_path_gives_the_checked_results_bit_for_bit(name, dtype):
    s = adjointsim.get(name).default()
    rng = np.random.default_rng(4)
    n = 7
    u = s.random_state(rng, 2, dtype)
    ctrl = None if s.control_shape is None else s.random_controls(rng, n, 2, dtype)
    cot = {k: s.random_state(rng, 2, dtype) for k in (0, 3, -1)}
    u0, n, c, p = s.prepare(u, n, ctrl)
    rows, cmap = s.check_cotangents(cot, n, u0)
    traj = s.rollout_prepared(u0, n, c, p, keep="all")
    assert same_bits(traj, s.rollout(u, n, ctrl, keep="all"))
    assert same_bits(s.rollout_prepared(u0, n, c, p), s.rollout(u, n, ctrl))
    for ctrl_run in [ctrl, None] if ctrl is not None else [None]:
        c_run = s.check_controls(ctrl_run, n, u0)
        traj_run = s.rollout_prepared(u0, n, c_run, p, keep="all")
        for wrt_params in (False, True):
            for checkpoint in (None, 3, 5):
                fast = s.vjp_prepared(u0, n, c_run, p, rows, cmap, wrt_params, checkpoint)
                checked = s.vjp(u, n, cot, ctrl_run, wrt_params=wrt_params,
                                checkpoint=checkpoint)
                if ctrl_run is None:  # the fast path returns the zero-length array
                    assert checked.controls is None and fast.controls.shape == c_run.shape
                    fast = type(fast)(fast.state, None, fast.params)
                assert same_cotangents(fast, checked), (ctrl_run is None, wrt_params, checkpoint)
            fast = s.vjp_prepared(u0, n, c_run, p, rows, cmap, wrt_params, trajectory=traj_run)
            checked = s.vjp(u, n, cot, ctrl_run, wrt_params=wrt_params, trajectory=traj_run)
            assert same_bits(fast.state, checked.state) and fast.params == checked.params


def test_the_checked_path_validates_once_and_the_fast_path_not_at_all():
    s = FTCS(n=12)
    rng = np.random.default_rng(5)
    u = s.random_state(rng, 2)
    ctrl = s.random_controls(rng, 4, 2)
    calls = count_validation(s)
    s.rollout(u, 4, ctrl)
    assert calls == {"check_state": 1, "check_controls": 1, "check_cotangents": 0,
                     "param_array": 1}
    s.vjp(u, 4, u, ctrl, wrt_params=True, checkpoint=3)
    assert calls == {"check_state": 2, "check_controls": 2, "check_cotangents": 1,
                     "param_array": 2}
    u0, n, c, p = s.prepare(u, 4, ctrl)
    rows, cmap = s.check_cotangents(u, n, u0)
    before = dict(calls)
    for _ in range(3):
        traj = s.rollout_prepared(u0, n, c, p, keep="all")
        s.rollout_prepared(u0, n, c, p)
        s.vjp_prepared(u0, n, c, p, rows, cmap, wrt_params=True, checkpoint=3)
        s.vjp_prepared(u0, n, c, p, rows, cmap, trajectory=traj)
    assert calls == before


def test_the_fast_path_takes_what_the_checks_would_refuse():
    """Complex-step perturbations (the verification harness's tangent model) run unchecked."""
    s = FTCS(n=12)
    rng = np.random.default_rng(6)
    u0, n, c, p = s.prepare(s.random_state(rng, 1), 5)
    v, h = s.random_state(rng, 1), 1e-30
    with pytest.raises(TypeError, match="expected float32 or float64"):
        s.rollout(u0 + 1j * h * v, n)
    z = s.rollout_prepared(u0 + 1j * h * v, n, c + 0j, p + 0j)
    assert same_bits(z.real.copy(), s.rollout_prepared(u0, n, c, p).copy())
    # The rollout is linear in u0: the complex step's tangent is the rollout of v.
    np.testing.assert_allclose(z.imag / h, s.rollout(v, n), rtol=1e-12, atol=1e-14)


def test_the_fast_path_still_reports_a_blow_up_unless_told_not_to():
    s = FTCS(n=16, nu=1.0)
    n = 1999
    u = np.random.default_rng(0).standard_normal((1, 1, 16))
    ctrl = np.zeros((n, 1, 1, 16))
    ctrl[600:] = 1e308  # as in test_blow_up_reports_the_first_non_finite_step
    u0, n, c, p = s.prepare(u, n, ctrl)
    with np.errstate(all="ignore"):
        with pytest.raises(NonFiniteStateError) as err:
            s.rollout_prepared(u0, n, c, p)
        with pytest.raises(NonFiniteStateError) as err_all:
            s.rollout_prepared(u0, n, c, p, keep="all")
        traj = s.rollout_prepared(u0, n, c, p, keep="all", check_finite=False)
    assert err.value.step == err_all.value.step > 600
    assert not np.isfinite(traj[-1]).all() and np.isfinite(traj[err.value.step - 1]).all()


# ------------------------------------------------------------------ re-entrant steppers
TAPED = ["ks1d-etdrk4", "burgers1d-etdrk3", "ns2d-etdrk4"]
#: budgets for 12 steps: one recorded segment, and five segments of which one is recorded
BUDGETS = (None, 5)


def _sweep_args(stepper, seed: int, batch: int) -> tuple:
    """The arguments (u0, n, cotangents, controls) of a vjp of 12 steps."""
    rng = np.random.default_rng(seed)
    n = 12
    u = stepper.random_state(rng, batch)
    ctrl = None if stepper.control_shape is None else stepper.random_controls(rng, n, batch)
    return u, n, {k: stepper.random_state(rng, batch) for k in (1, -1)}, ctrl


def _spy_kernels(stepper, log) -> None:
    """Append each kernel call of ``stepper`` to the list ``log()`` returns: the forward's
    steps and whether it recorded a tape, the adjoint's steps and whether it got one."""
    forward, adjoint = stepper._forward, stepper._adjoint

    def spied_forward(states, n, *args):
        tape = forward(states, n, *args)
        log().append(("forward", n, tape is not None))
        return tape

    def spied_adjoint(states, *args):
        log().append(("adjoint", states.shape[0], len(args) > 8 and args[8] is not None))
        adjoint(states, *args)

    stepper._forward, stepper._adjoint = spied_forward, spied_adjoint


def _sweeps(stepper, args: tuple) -> tuple:
    """A vjp for each budget, then the rollout, of the same inputs."""
    u, n, cot, ctrl = args
    grads = [stepper.vjp(u, n, cot, ctrl, checkpoint=b) for b in BUDGETS]
    return grads, stepper.rollout(u, n, ctrl, keep="all")


def _fresh(name: str, args: tuple) -> tuple:
    """What :func:`_sweeps` gives on a stepper of its own, and the kernel calls it makes."""
    fresh, calls = adjointsim.get(name).default(), []
    _spy_kernels(fresh, lambda: calls)
    return _sweeps(fresh, args), calls


def _same_sweeps(a: tuple, b: tuple) -> bool:
    return all(map(same_cotangents, a[0], b[0])) and same_bits(a[1], b[1])


@pytest.mark.parametrize("name", TAPED)
def test_taped_steppers_are_reentrant_in_one_thread(name):
    """Sweeps run inside another vjp's adjoint kernel call, on the same stepper, while the
    tape of that vjp waits for the kernel: each sweep makes the kernel calls, tapes
    included, and gets the results, bit for bit, of the same sweep on a fresh stepper."""
    s = adjointsim.get(name).default()
    assert s._records_tape
    outer_args, inner_args = _sweep_args(s, 0, 2), _sweep_args(s, 1, 3)  # two tape sizes
    outer_ref, outer_calls = _fresh(name, outer_args)
    inner_ref, inner_calls = _fresh(name, inner_args)
    assert outer_calls[:2] == [("forward", 12, True), ("adjoint", 12, True)]
    # ... and a taped segment among the untaped ones of the budget of 5
    assert [t for k, _, t in inner_calls if k == "adjoint"].count(True) == 2

    logs: list[list] = [[]]
    _spy_kernels(s, lambda: logs[-1])
    adjoint, inner = s._adjoint, []

    def interleaved(*args):
        if not inner:
            inner.append(logs[-1])  # first, as the nested sweeps call this kernel too
            logs.append([])
            inner[:] = [_sweeps(s, inner_args), logs.pop()]
        adjoint(*args)

    s._adjoint = interleaved
    outer = _sweeps(s, outer_args)
    assert logs == [outer_calls] and inner[1] == inner_calls
    assert _same_sweeps(outer, outer_ref)
    assert _same_sweeps(inner[0], inner_ref)


@pytest.mark.parametrize("name", TAPED)
def test_taped_steppers_are_reentrant_across_threads(name):
    s = adjointsim.get(name).default()
    cases = [_sweep_args(s, seed, 1 + seed) for seed in range(2)]
    refs = [_fresh(name, args) for args in cases]
    logs: dict[int, list] = {}
    _spy_kernels(s, lambda: logs[threading.get_ident()])
    failures, start = [], threading.Barrier(2)

    def work(i: int) -> None:
        start.wait()
        for _ in range(3):
            logs[threading.get_ident()] = []
            if not (_same_sweeps(_sweeps(s, cases[i]), refs[i][0])
                    and logs[threading.get_ident()] == refs[i][1]):
                failures.append(i)

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads between (almost) any two kernel calls
    try:
        threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(old)
    assert not failures


# ------------------------------------------------------------------ no reaching into privates
def _stepper_privates() -> set[str]:
    """Names of the private methods of Stepper and of every registered solver class."""
    classes = {Stepper} | {k for name in adjointsim.names() for k in adjointsim.get(name).__mro__
                           if issubclass(k, Stepper)}
    return {attr for k in classes for attr, value in vars(k).items()
            if attr.startswith("_") and not attr.startswith("__")
            and callable(getattr(value, "__func__", value))}


def test_nothing_outside_the_contract_calls_a_stepper_private():
    """Callers use the public API (the fast path included); only the Stepper and the solvers
    themselves call the kernels, the sweep and the validators' internals."""
    privates = _stepper_privates()
    assert {"_forward", "_adjoint", "_run", "_raise_nonfinite"} <= privates
    call = re.compile(r"\b(\w+)\s*\.\s*(_\w+)\s*\(")
    inside = [ROOT / "adjointsim" / "stepper.py", ROOT / "adjointsim" / "solvers"]
    found = []
    for top in ("adjointsim", "train", "nets", "cli", "benchmarks"):
        for path in sorted((ROOT / top).rglob("*.py")):
            if any(path == p or p in path.parents for p in inside):
                continue
            text = path.read_text(encoding="utf-8")
            for m in call.finditer(text):
                if m.group(2) in privates and m.group(1) not in ("self", "cls"):
                    line = text.count("\n", 0, m.start()) + 1
                    found.append(f"{path.relative_to(ROOT)}:{line}: {m.group(0)}")
    assert not found, "calls to Stepper privates:\n" + "\n".join(found)


# ------------------------------------------------------------------ step counts, parameters
def test_the_step_count_is_checked_with_the_solver_named():
    s = FTCS(n=16)
    u = np.zeros((2, 1, 16))
    for bad in (np.nan, np.inf, 2.5, -1):
        with pytest.raises(ValueError, match=r"^diffusion1d-ftcs: n must be a non-negative "
                                             r"integer, got .* \(the number of steps\)$"):
            s.rollout(u, bad)
    for bad in (None, True, np.bool_(False), "3", 1 + 0j):
        with pytest.raises(TypeError, match=r"^diffusion1d-ftcs: n must be a non-negative "
                                            r"integer, got \w+ "):
            s.vjp(u, bad, u)
    for whole in (3, np.int64(3), np.array(3), 3.0, np.float32(3.0)):
        u0, n, _, _ = s.prepare(u, whole)
        assert n == 3 and type(n) is int


def test_complex_parameters_are_refused_where_a_cast_would_drop_their_imaginary_part():
    s = FTCS(n=16)
    u = s.random_state(np.random.default_rng(7), 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # refused, not cast with a ComplexWarning
        with pytest.raises(TypeError, match=r"parameters must be real numbers, got nu = "
                                            r"\(0\.1\+2j\)"):
            s.rollout(u, 2, params={"nu": 0.1 + 2j})
        with pytest.raises(TypeError, match="parameters must be real numbers"):
            s.vjp(u, 2, u, params=np.array([0.1 + 0j]), wrt_params=True)
        with pytest.raises(TypeError, match="parameters must be real numbers"):
            s.prepare(u, 2, params=[np.complex128(0.1)])
        # The checks' complex-step perturbation of a parameter takes the fast path, which runs it.
        u0, n, c, p = s.prepare(u, 2)
        z = s.rollout_prepared(u0 + 0j, n, c + 0j, p + 1e-30j)
    assert same_bits(z.real.copy(), s.rollout(u, 2))


@pytest.mark.parametrize("params", [{"nu": "abc"}, ["abc"], np.array(["0.1"]), {"nu": None},
                                    {"nu": True}])
def test_a_parameter_that_is_not_a_number_is_named_with_the_solver(params):
    s = FTCS(n=16)
    u = s.random_state(np.random.default_rng(7), 2)
    value = params["nu"] if isinstance(params, dict) else str(params[0])
    with pytest.raises(TypeError) as info:
        s.rollout(u, 2, params=params)
    assert str(info.value) == (f"diffusion1d-ftcs: parameters must be real numbers, got "
                               f"nu = {value!r}; give a number for each of ['nu']")


def test_a_trajectory_of_the_wrong_shape_or_dtype_says_what_is_expected():
    s = FTCS(n=16)
    u = s.random_state(np.random.default_rng(8), 2)
    traj = s.rollout(u, 5, keep="all")
    with pytest.raises(ValueError, match=r"trajectory has shape \(5, 2, 1, 16\); expected "
                                         r"\(6, 2, 1, 16\), the 6 states u_0 \.\. u_5"):
        s.vjp(u, 5, u, trajectory=traj[:5])
    for wrong in (traj.astype(np.float32), traj + 0j):
        with pytest.raises(TypeError, match=rf"trajectory has dtype {wrong.dtype} but the "
                                            "state is float64"):
            s.vjp(u, 5, u, trajectory=wrong)
    assert same_bits(s.vjp(u, 5, u, trajectory=list(traj)).state, s.vjp(u, 5, u).state)


def test_a_trajectory_of_another_rollout_is_refused_not_reversed():
    """the trajectory of 2·u0 gave twice the parameter gradient without a word."""
    s = FTCS(n=16)
    u = s.random_state(np.random.default_rng(8), 2)
    with pytest.raises(ValueError, match=r"trajectory\[0\] is not u0, so the trajectory is of "
                                         r"another rollout; pass rollout\(\.\.\., keep=\"all\"\)"):
        s.vjp(u, 4, u, wrt_params=True, trajectory=s.rollout(2 * u, 4, keep="all"))


def test_wrt_params_is_a_flag_not_any_truthy_value():
    s = FTCS(n=16)
    u = s.random_state(np.random.default_rng(8), 2)
    with pytest.raises(TypeError,
                       match="diffusion1d-ftcs: wrt_params must be True or False, got str 'no'"):
        s.vjp(u, 2, u, wrt_params="no")


def test_a_reverse_pass_too_long_to_keep_names_checkpointing():
    """numpy's 'Unable to allocate' gave the size but not the way around it."""
    s = FTCS(n=2**22)
    u = np.zeros(s.state_shape())
    # 305 TiB of states: beyond x86-64's 128 TiB address space, so refused whatever the
    # machine's overcommit policy (a smaller size could be granted and then filled)
    n = 10**7
    with pytest.raises(MemoryError, match=rf"diffusion1d-ftcs: keeping the {n + 1} states of the "
                                          r"rollout for the reverse pass needs more memory than "
                                          r"there is \(.*\); pass checkpoint=s"):
        s.vjp(u, n, u)


@pytest.mark.parametrize(("name", "n"), [("ks1d-etdrk4", 2**62), ("ns2d-etdrk4", 10**30),
                                         ("poisson2d", 2**62)])
def test_a_scene_beyond_numpys_largest_array_is_a_memory_error(name, n):
    """numpy's three ways of saying so ('Maximum allowed size/dimension exceeded', 'array is
    too big') name no key; the CLI shows a MemoryError as its one-line 'not enough memory'."""
    from adjointsim import scenes

    with pytest.raises(MemoryError, match=rf"{name} with \{{'n': {n}\}} asks for arrays larger "
                                          "than numpy can index"):
        scenes.build(name, {"n": n})
