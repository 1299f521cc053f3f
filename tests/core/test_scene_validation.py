"""Scene validation: every constructor argument of every registered solver is
checked, with an error naming the argument; minimal and odd grids work or are refused clearly;
explicit schemes accept Δt at their stated limit and refuse it just beyond, naming the limit."""

from __future__ import annotations

import inspect
import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import adjointsim
from adjointsim import validate
from adjointsim.solvers.kuramoto_sivashinsky import KuramotoSivashinskyETDRK
from adjointsim.solvers.navier_stokes import NavierStokes2D
from adjointsim.stepper import Choice

NAMES = adjointsim.names()
BAD = (math.nan, math.inf, -math.inf)


# ------------------------------------------------------------------ the helpers themselves
def test_messages_name_solver_argument_value_and_what_is_accepted():
    with pytest.raises(ValueError) as err:
        validate.number("diffusion1d-ftcs", "dt", -0.1, gt=0)
    assert str(err.value) == "diffusion1d-ftcs: dt must be a finite number > 0, got -0.1"
    with pytest.raises(ValueError, match=r"^s: n must be an even integer ≥ 4, got 7 \(FFT\)$"):
        validate.integer("s", "n", 7, ge=4, even=True, why="FFT")
    with pytest.raises(ValueError, match=r"^s: cfl must be a finite number > 0 and ≤ 1, got 1.5$"):
        validate.number("s", "cfl", 1.5, gt=0, le=1)
    with pytest.raises(ValueError, match="^s: bc must be one of 'periodic', 'dirichlet', got 'x'$"):
        validate.choice("s", "bc", "x", ("periodic", "dirichlet"))
    # values read back from files (HDF5 attributes) come as NumPy scalars
    bc = validate.choice("s", "bc", np.str_("dirichlet"), ("periodic", "dirichlet"))
    assert bc == "dirichlet" and type(bc) is str
    assert validate.flag("s", "dealias", np.bool_(True)) is True
    with pytest.raises(ValueError, match="^s: k must be one of 1, 2, got True$"):
        validate.choice("s", "k", True, (1, 2))
    with pytest.raises(ValueError, match=r"^s: g must have shape \(1, 4\), got shape \(4,\)$"):
        validate.array("s", "g", np.zeros(4), (1, 4))
    with pytest.raises(ValueError, match=r"g must be finite; got nan at index \(0, 2\)"):
        validate.array("s", "g", [[0, 1, np.nan, 3]], (1, 4))


@pytest.mark.parametrize(
    "check, value",
    [
        (lambda x: validate.number("s", "dt", x), "0.1"),
        (lambda x: validate.number("s", "dt", x), True),
        (lambda x: validate.number("s", "dt", x), None),
        (lambda x: validate.number("s", "dt", x), 1j),
        (lambda x: validate.integer("s", "dt", x), 32.0),
        (lambda x: validate.integer("s", "dt", x), "32"),
        (lambda x: validate.integer("s", "dt", x), False),
        (lambda x: validate.flag("s", "dt", x), 1),
        (lambda x: validate.choice("s", "dt", x, ("a",)), ["a"]),
        (lambda x: validate.array("s", "dt", x, (2,)), ["a", "b"]),
        (lambda x: validate.array("s", "dt", x, (2,)), [1j, 2]),
    ],
)
def test_wrong_types_are_type_errors_naming_the_argument(check, value):
    with pytest.raises(TypeError, match="^s: dt must be "):
        check(value)


@settings(max_examples=60, deadline=None, database=None)
@given(st.floats(allow_nan=True, allow_infinity=True), st.floats(-10, 10), st.floats(-10, 10))
def test_number_accepts_exactly_the_finite_values_in_bounds(x, a, b):
    lo, hi = min(a, b), max(a, b)
    inside = math.isfinite(x) and lo < x <= hi
    if inside:
        assert validate.number("s", "x", x, gt=lo, le=hi) == x
        assert validate.number("s", "x", np.float64(x), gt=lo, le=hi) == x
        assert validate.number("s", "x", np.array(x), gt=lo, le=hi) == x
    else:
        with pytest.raises(ValueError, match=r"^s: x must be a finite number > .* and ≤ "):
            validate.number("s", "x", x, gt=lo, le=hi)


@settings(max_examples=40, deadline=None, database=None)
@given(st.integers(-50, 50), st.integers(-10, 10), st.booleans())
def test_integer_accepts_numpy_integers_and_checks_parity(k, lo, even):
    ok = k >= lo and not (even and k % 2)
    for value in (k, np.int64(k), np.int32(k)):
        if ok:
            assert validate.integer("s", "n", value, ge=lo, even=even) == k
        else:
            with pytest.raises(ValueError, match=f"^s: n must be an {'even ' if even else ''}int"):
                validate.integer("s", "n", value, ge=lo, even=even)


# ------------------------------------------------------------------ the registry sweep
def _numeric_arguments(cls: type) -> dict[str, str]:
    """Constructor keywords that take a number: name -> "int" or "float"."""
    out = {}
    for name, par in inspect.signature(cls.__init__).parameters.items():
        ann = str(par.annotation)
        if name == "self" or "ndarray" in ann or "str" in ann or "bool" in ann:
            continue
        if "float" in ann:
            out[name] = "float"
        elif "int" in ann:
            out[name] = "int"
    return out


def _names_argument(message: str, arg: str) -> bool:
    return re.search(rf"(?<![\w.]){arg}(?!\w)", message) is not None


def _works(stepper) -> None:
    """A scene that was accepted must step forward in time and give finite results."""
    assert stepper.dt > 0 and math.isfinite(stepper.dt)
    u = stepper.random_state(np.random.default_rng(0), 1)
    assert np.all(np.isfinite(u))
    out = stepper.rollout(u, 2)
    g = stepper.vjp(u, 2, out, wrt_params=True)
    assert np.all(np.isfinite(out)) and np.all(np.isfinite(g.state))
    assert all(math.isfinite(x) for x in g.params.values())


@pytest.mark.parametrize("name", NAMES)
def test_every_numeric_argument_is_checked(name):
    cls = adjointsim.get(name)
    args = _numeric_arguments(cls)
    assert args, f"{name}: no numeric constructor arguments found"
    for arg, kind in args.items():
        wrong_type = ["0.5", [1.0]] + ([2.5, 4.0] if kind == "int" else [True])
        for value in wrong_type:
            with pytest.raises(TypeError) as err:
                cls(**{arg: value})
            assert _names_argument(str(err.value), arg), (arg, value, str(err.value))
        for value in BAD:  # (a float for an integer argument is a TypeError)
            with pytest.raises(ValueError if kind == "float" else TypeError) as err:
                cls(**{arg: value})
            assert _names_argument(str(err.value), arg), (arg, value, str(err.value))
        for value in (0, -1) if kind == "int" else (0.0, -1.0, -1e-300):
            try:
                stepper = cls(**{arg: value})
            except ValueError as e:
                assert _names_argument(str(e), arg), (arg, value, str(e))
            else:
                _works(stepper)


@pytest.mark.parametrize("name", NAMES)
def test_time_step_is_positive_and_finite(name):
    cls = adjointsim.get(name)
    if "dt" not in inspect.signature(cls.__init__).parameters:
        pytest.skip(f"{name} takes no dt")
    for dt in (0.0, -0.1, -1e-300, math.nan, math.inf):
        with pytest.raises(ValueError, match=r"\bdt must be a finite number > 0"):
            cls(dt=dt)
    with pytest.raises(TypeError, match=r"\bdt must be a real number, got str '0.1'"):
        cls(dt="0.1")


@pytest.mark.parametrize("name", NAMES)
def test_declared_space_is_accepted(name):
    """Every Choice value and Range end of ``space`` (the property tests' draws) builds."""
    cls = adjointsim.get(name)

    def ends(spec):
        if isinstance(spec, Choice):
            return spec.values
        return (int(spec.lo), int(spec.hi)) if spec.integer else (spec.lo, spec.hi)

    base = {k: ends(v)[0] for k, v in cls.space.items()}
    for key, spec in cls.space.items():
        for value in ends(spec):
            cls(**{**base, key: value})
    cls.default()


# ------------------------------------------------------------------ grids
def _dot_product_error(stepper, steps: int = 3) -> float:
    """Relative error of ⟨J v, w⟩ against ⟨v, Jᵀ w⟩ for the state, with a rough random state
    (the solvers' smooth random states are constant on tiny grids)."""
    rng = np.random.default_rng(3)
    u = stepper.random_state(rng, 2)
    u = u + 0.1 * np.abs(u).max() * rng.standard_normal(u.shape)
    v, w = rng.standard_normal((2, *u.shape))
    p = np.array(stepper.param_values)
    none = np.zeros((0, 2, *(stepper.control_shape or ())))
    if stepper.complex_step:
        h = 1e-100
        run = stepper.rollout_prepared(u + 1j * h * v, steps, none + 0j, p + 0j, check_finite=False)
        jv = run.imag / h
    else:  # linear tangent by a central difference: the FFT solvers are smooth
        h = 1e-6
        plus = stepper.rollout_prepared(u + h * v, steps, none, p, check_finite=False)
        minus = stepper.rollout_prepared(u - h * v, steps, none, p, check_finite=False)
        jv = (plus - minus) / (2 * h)
    a, b = float(np.sum(jv * w)), float(np.sum(v * stepper.vjp(u, steps, w).state))
    return abs(a - b) / max(abs(a), abs(b))


def _grid_kwargs(name: str) -> list[dict]:
    cls = adjointsim.get(name)
    params = inspect.signature(cls.__init__).parameters
    variants = [{}]
    if "bc" in params:
        spec = cls.space.get("bc")
        variants = [{"bc": bc} for bc in (spec.values if spec else ("periodic",))]
    if name.startswith("ns2d"):  # forcing at wavenumber 1 fits every grid from n = 4
        variants = [{**kw, "forcing_wavenumber": 1, "dt": 0.05, "nu": 0.1} for kw in variants]
    return variants


@pytest.mark.parametrize("name", NAMES)
def test_smallest_and_odd_grids_work_or_are_refused(name):
    cls = adjointsim.get(name)
    if "n" not in inspect.signature(cls.__init__).parameters:
        pytest.skip(f"{name} has no grid size")
    for kw in _grid_kwargs(name):
        accepted = []
        for n in range(0, 8):
            try:
                stepper = cls(n=n, **kw)
            except ValueError as e:
                assert _names_argument(str(e), "n"), (kw, n, str(e))
                assert not accepted or n % 2, f"{name} {kw}: n = {n} refused after {accepted}"
                continue
            accepted.append(n)
        assert accepted and min(accepted) >= 1, (name, kw, accepted)
        # The smallest accepted grid and the next two work, adjoint included.
        for n in accepted[:3]:
            stepper = cls(n=n, **kw)
            _works(stepper)
            err = _dot_product_error(stepper)
            assert err < (1e-12 if stepper.complex_step else 1e-6), (name, kw, n, err)


# ------------------------------------------------------------------ stability limits
def _limit(stepper) -> float:
    """The largest stable Δt of an explicit scheme, from the limit its docstring states."""
    if stepper.name.endswith("-ftcs"):
        return 0.5 / (stepper.param_values[0] * sum(stepper.inv_h2))
    if stepper.name.startswith("advection"):
        return stepper.max_dt(np.array(stepper.param_values))
    return stepper.substeps / stepper._rate(stepper.param_values[0])  # Rusanov Burgers


EXPLICIT = [
    ("diffusion1d-ftcs", {"n": 16, "nu": 0.3, "bc": "dirichlet"}),
    ("diffusion2d-ftcs", {"n": 8, "nu": 0.7, "bc": "neumann"}),
    ("advection1d-upwind", {"n": 16, "velocity": -0.7}),
    ("advection2d-upwind", {"n": 8, "velocity_x": 0.4, "velocity_y": -1.3}),
    ("advection1d-lax-wendroff", {"n": 16, "velocity": 1.1}),
    ("advection2d-lax-wendroff", {"n": 8, "velocity_x": -0.9, "velocity_y": 0.6}),
    ("burgers1d-rusanov", {"n": 16, "nu": 0.1, "substeps": 2}),
    ("burgers2d-rusanov", {"n": 8, "nu": 0.05, "substeps": 1}),
]


@pytest.mark.parametrize("name, kw", EXPLICIT, ids=[e[0] for e in EXPLICIT])
def test_dt_at_the_limit_works_and_just_beyond_names_it(name, kw):
    cls = adjointsim.get(name)
    limit = _limit(cls(**kw))
    at = cls(**kw, dt=limit)
    assert at.dt == limit
    u = at.random_state(np.random.default_rng(1), 2)
    assert np.all(np.isfinite(at.rollout(u, 20)))
    with pytest.raises(ValueError, match="stability limit") as err:
        cls(**kw, dt=limit * (1 + 1e-6))
    message = str(err.value)
    assert f"largest stable Δt is {limit:.6g}" in message, message
    assert "dt ≤" in message or "substeps" in message, message
    # dt=None takes cfl × the limit; cfl must lie in (0, 1].
    if "cfl" in inspect.signature(cls.__init__).parameters:
        assert cls(**kw, cfl=1.0).dt == pytest.approx(limit, rel=1e-12)
        for cfl in (0.0, -0.5, 1.01, math.nan):
            with pytest.raises(ValueError, match=r"\bcfl must be a finite number > 0 and ≤ 1"):
                cls(**kw, cfl=cfl)


def test_zero_viscosity_without_dt_asks_for_dt():
    with pytest.raises(ValueError, match=r"nu must be a finite number > 0, got 0.0 .*give dt"):
        adjointsim.get("diffusion1d-ftcs")(nu=0.0)
    assert adjointsim.get("diffusion1d-ftcs")(nu=0.0, dt=0.1).dt == 0.1
    with pytest.raises(ValueError, match="velocity is zero.*give dt"):
        adjointsim.get("advection2d-upwind")(velocity_x=0.0, velocity_y=0.0)


# ------------------------------------------------------------------ other arguments, presets
@pytest.mark.parametrize(
    "name, kw, exc, arg",
    [
        ("diffusion1d-ftcs", {"bc": "robin"}, ValueError, "bc"),
        ("diffusion2d-crank-nicolson", {"bc": 1}, TypeError, "bc"),
        ("poisson2d", {"bc": "neumann"}, ValueError, "bc"),
        ("diffusion1d-ftcs", {"forcing": np.full((1, 32), np.inf)}, ValueError, "forcing"),
        ("diffusion2d-ftcs", {"n": 4, "forcing": np.ones((1, 4, 5))}, ValueError, "forcing"),
        ("ks1d-etdrk2", {"forcing": np.array([[np.nan] * 32])}, ValueError, "forcing"),
        ("ks1d-etdrk2", {"forcing": np.array([["a"] * 32])}, TypeError, "forcing"),
        ("ks1d-etdrk2", {"dealias": "yes"}, TypeError, "dealias"),
        ("ks1d-etdrk2", {"n": 30.0}, TypeError, "n"),
        ("ns2d-etdrk2", {"dealias": 1}, TypeError, "dealias"),
        ("ns2d-etdrk2", {"forcing_wavenumber": 2.0}, TypeError, "forcing_wavenumber"),
        ("ns2d-etdrk2", {"forcing_wavenumber": 0}, ValueError, "forcing_wavenumber"),
        ("schrodinger1d-cn", {"potential": "well"}, ValueError, "potential"),
        ("schrodinger1d-cn", {"n": 4, "potential": [0, 1, np.nan, 0]}, ValueError, "potential"),
        ("burgers1d-rusanov", {"substeps": 0}, ValueError, "substeps"),
    ],
)
def test_non_numeric_arguments(name, kw, exc, arg):
    with pytest.raises(exc) as err:
        adjointsim.get(name)(**kw)
    assert _names_argument(str(err.value), arg), str(err.value)


def test_presets_are_valid_and_check_their_own_arguments():
    KuramotoSivashinskyETDRK.kassam_trefethen()
    NavierStokes2D.kolmogorov_drag(re=500.0, n=16)
    for re_ in (0.0, -100.0, math.inf):
        with pytest.raises(ValueError, match=r"\bre must be a finite number > 0"):
            NavierStokes2D.kolmogorov_drag(re=re_)
    for name in NAMES:
        cls = adjointsim.get(name)
        cls.default()
        if "n" in inspect.signature(cls.__init__).parameters:
            with pytest.raises(TypeError, match=r"\bn must be an integer"):
                cls.benchmark_scene(16.0)


# ------------------------------------------------------------------ counts and size knobs
def test_count_takes_whole_numbers_and_names_what_it_refuses():
    for value in (0, 7, np.int32(7), np.array(7), 7.0, np.float64(7.0)):
        k = validate.count("s", "n", value)
        assert k == int(value) and type(k) is int
    for value in (-1, 2.5, math.nan, math.inf, -3.0):
        with pytest.raises(ValueError, match=r"^s: n must be a non-negative integer, got "
                                             r"\S+ \(the steps\)$"):
            validate.count("s", "n", value, why="the steps")
    for value in (None, True, "3", 1j, [3]):
        with pytest.raises(TypeError, match=r"^s: n must be a non-negative integer, got \w+ "):
            validate.count("s", "n", value)


@pytest.mark.parametrize("name", ["cartpole", "guidance"])
def test_benchmark_size_knob_is_an_integer(name):
    """These scenes map the benchmarks' size knob onto a count of bodies: NaN went through."""
    cls = adjointsim.get(name)
    for value in (math.nan, None, 2.5, True, 16.0):
        with pytest.raises(TypeError, match=rf"^{name}: n must be an integer, got \w+ "):
            cls.benchmark_scene(value)
    for value in (0, 1, 3, 64):
        cls.benchmark_scene(value)
