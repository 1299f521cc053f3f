"""adjointsim bench work-precision: the CSV and PNG it writes for the KS scene (--quick), its
error falling with Δt for every scheme, the NumPy ETDRK4 baseline giving our ETDRK4's errors,
and an unknown scene refused in one line."""

import csv

import pytest

from adjointsim.bench.work_precision import ORDERS
from adjointsim.cli import main


@pytest.fixture(scope="module")
def ks_quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("wp")
    code = main(["bench", "work-precision", "ks", "--quick", "--out", str(out), "--no-exponax",
                 "--no-progress", "--repeats", "1"])
    assert code == 0
    return out


def test_work_precision_quick_writes_csv_and_png(ks_quick):
    png = ks_quick / "work_precision_ks.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with open(ks_quick / "work_precision_ks.csv") as f:
        rows = list(csv.DictReader(f))
    schemes = {r["scheme"] for r in rows}
    assert schemes == {f"ks1d-etdrk{o}" for o in ORDERS} | {"numpy-etdrk4"}
    assert all(float(r["time_s"]) > 0 and float(r["error"]) > 0 for r in rows)


def test_work_precision_error_decreases_with_dt(ks_quick):
    with open(ks_quick / "work_precision_ks.csv") as f:
        rows = list(csv.DictReader(f))
    for scheme in {r["scheme"] for r in rows}:
        pts = sorted((float(r["dt"]), float(r["error"])) for r in rows if r["scheme"] == scheme)
        errors = [e for _, e in pts]
        assert all(a < b for a, b in zip(errors, errors[1:])), (scheme, pts)
        # The coarsest step is at least 10x less accurate than the finest (16x smaller) one.
        assert errors[-1] > 10 * errors[0], (scheme, pts)


def test_numpy_baseline_is_the_same_scheme(ks_quick):
    with open(ks_quick / "work_precision_ks.csv") as f:
        rows = list(csv.DictReader(f))
    ours = {r["dt"]: float(r["error"]) for r in rows if r["scheme"] == "ks1d-etdrk4"}
    numpy = {r["dt"]: float(r["error"]) for r in rows if r["scheme"] == "numpy-etdrk4"}
    for dt, e in ours.items():
        assert numpy[dt] == pytest.approx(e, rel=1e-6)


def test_cli_rejects_unknown_scene(capsys):
    assert main(["bench", "work-precision", "heat"]) == 2
    err = capsys.readouterr().err.strip()
    assert "invalid choice" in err and len(err.splitlines()) == 1
