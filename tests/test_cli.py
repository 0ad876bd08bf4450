import dataclasses
import os
import stat
import sys
import textwrap
import warnings

import matplotlib.image
import numpy as np
import pytest

import lagrax
from lagrax._cli import chart, main as _cli, run as cli_run, targets
from lagrax.systems import pendulum


def run(capsys, *argv):
    rc = _cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def exact_pendulum(amplitude, g=1.0):
    return np.asarray(pendulum.period(amplitude, r=1.0, g=g))


USER_MODULE = textwrap.dedent(
    """
    import jax.numpy as jnp


    def pendulum(g=1.0, r=1.0):
        def L(q, qdot, t):
            return 0.5 * r**2 * qdot[0] ** 2 + g * r * jnp.cos(q[0])

        return L


    def L(q, qdot, t):  # the pendulum with g = r = 1, given directly (the factory's
        # terms: one compiled program for both, their constants are its arguments)
        return 0.5 * qdot[0] ** 2 + 1.0 * jnp.cos(q[0])


    def double(q, qdot, t):
        return 0.5 * (qdot[0] ** 2 + qdot[1] ** 2) + jnp.cos(q[0]) + jnp.cos(q[1])


    def vector(q, qdot, t):
        return 0.5 * qdot**2 + jnp.cos(q)


    def unpacked(q, qdot, t):
        a, b = q
        return 0.5 * qdot @ qdot + jnp.cos(a) + jnp.cos(b)


    def two(a, b):
        return a


    def broken_factory(g=1.0):
        raise RuntimeError("no such physics")


    not_callable = 3
    """
)


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    path = tmp_path / "my_systems.py"
    path.write_text(USER_MODULE)
    monkeypatch.chdir(tmp_path)
    yield path
    sys.modules.pop("my_systems", None)


@pytest.mark.parametrize(
    "argv",
    [
        ["sweep", "--count", "0"],
        ["sweep", "pendulum", "--min", "4"],
        ["sweep", "pendulum", "--min", "1", "--max", "0.5"],
        ["sweep", "spring"],
        ["sweep", "--rtol", "-1"],
        ["sweep", "--count", "ten"],
        ["sweep", "--out", "results.txt"],
        ["sweep", "--solver", "euler"],
        ["sweep", "--param", "g"],
        ["sweep", "--param", "g=fast"],
        ["sweep", "--devices", "0"],
        ["sweep", "--coordinator", "127.0.0.1:1234"],
        ["sweep", "--coordinator=nohost", "--num-processes=2", "--process-id=0"],
        ["sweep", "--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"],
        [],
    ],
)
def test_bad_arguments_exit_2_with_one_line(capsys, argv):
    rc, out, err = run(capsys, *argv)
    assert rc == 2
    assert out == ""
    assert err.startswith("lagrax: error:") and err.count("\n") == 1
    assert "Traceback" not in err


@pytest.mark.parametrize(
    "target, extra, message",
    [
        ("no_such_module:L", [], "no module named 'no_such_module'"),
        ("my_systems:nothing", [], "has no attribute 'nothing'"),
        ("my_systems:not_callable", [], "not callable"),
        ("my_systems:two", [], "takes 2 required argument(s)"),
        ("my_systems:double", [], "has 2 coordinates"),
        ("my_systems:vector", [], "must return a real floating-point scalar"),
        ("my_systems:unpacked", [], "has 2 coordinates"),
        ("my_systems:pendulum", ["--param", "gravity=2"], "no parameter 'gravity'"),
        ("my_systems:L", ["--param", "g=2"], "not a factory"),
        ("my_systems:broken_factory", [], "raised RuntimeError: no such physics"),
        ("missing.py:L", [], "no such file 'missing.py'"),
        ("my_systems.py:double", [], "has 2 coordinates"),
        ("pendulum", ["--param", "l=2"], "no parameter 'l'"),
        ("double_pendulum", [], "has 2 coordinates"),
    ],
)
def test_bad_targets_exit_2_naming_the_problem_before_any_work(
    capsys, monkeypatch, user_module, target, extra, message
):
    def boom(*args, **kwargs):
        raise AssertionError("the sweep ran")

    monkeypatch.setattr(lagrax, "sweep_periods", boom)
    rc, out, err = run(
        capsys, "sweep", target, "--min", "0.1", "--max", "1", "--count", "4", *extra
    )
    assert rc == 2, err
    assert out == ""
    assert err.startswith("lagrax: error:") and err.count("\n") == 1, err
    assert message in err


def test_user_lagrangian_needs_a_range_and_exact_needs_a_reference(
    capsys, monkeypatch, user_module
):
    monkeypatch.setattr(lagrax, "sweep_periods", None)
    rc, _, err = run(capsys, "sweep", "my_systems:L")
    assert rc == 2 and "--min and --max" in err
    rc, _, err = run(
        capsys, "sweep", "my_systems:L", "--min", "0.1", "--max", "1", "--reference",
        "exact",
    )  # fmt: skip
    assert rc == 2 and "no exact period" in err


def test_unwritable_output_fails_before_the_sweep(capsys, monkeypatch, tmp_path):
    def boom(*args, **kwargs):
        raise AssertionError("the sweep ran")

    monkeypatch.setattr(lagrax, "sweep_periods", boom)
    missing = tmp_path / "no" / "such" / "dir" / "out.csv"
    rc, out, err = run(capsys, "sweep", "--out", missing)
    assert rc == 2 and "cannot write" in err
    rc, out, err = run(capsys, "sweep", "--plot", tmp_path)
    assert rc == 2


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


def test_sweep_writes_table_csv_and_two_panel_chart(capsys, tmp_path, umask_022):
    out_csv = tmp_path / "res.csv"
    chart = tmp_path / "chart.png"
    svg = tmp_path / "chart.svg"
    argv = ["sweep", "pendulum", "--count", "40", "--lanes", "16", "--rows", "5"]
    rc, out, err = run(capsys, *argv, "--out", out_csv, "--plot", chart)
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[0].split()[:3] == ["system", "amplitude", "period"]
    assert sum(line.startswith("pendulum ") for line in lines) == 5
    assert "max relative error" in out and "vs the exact period" in out
    data = np.genfromtxt(out_csv, delimiter=",", names=True, dtype=None, encoding=None)
    assert len(data) == 40
    np.testing.assert_allclose(
        data["period"], exact_pendulum(data["amplitude"]), rtol=1e-12
    )
    np.testing.assert_allclose(data["reference"], exact_pendulum(data["amplitude"]))
    assert set(data["reference_kind"]) == {"exact"}
    assert np.all(data["status"] == 0) and set(data["status_name"]) == {"success"}
    assert np.all(data["rel_error"] < 1e-12)
    # The per-lane error estimate, once SweepResult has one, is a column of its own.
    fields = {f.name for f in dataclasses.fields(lagrax.SweepResult)}
    if hasattr(lagrax.SweepResult, "error_estimate") or "error_estimate" in fields:
        assert np.all(np.isfinite(data["error_estimate"]))
    else:
        assert "error_estimate" not in data.dtype.names
    image = matplotlib.image.imread(chart)
    assert chart.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and image.ndim == 3
    assert not os.path.exists(str(out_csv) + ".partial")
    # Readable by others, as the umask says (not 0600 from a temporary file).
    assert mode(out_csv) == mode(chart) == 0o644
    # The same chart as SVG: two axes, T/T0 above and the relative error below.
    rc, _, err = run(capsys, *argv, "--plot", svg, "--quiet")
    assert rc == 0, err
    text = svg.read_text()
    assert text.count('<g id="axes_') == 2
    assert "T / T₀" in text or "T / T" in text
    assert "relative error" in text


def test_chart_marks_failures_and_plots_the_error(tmp_path):
    amplitude = np.linspace(0.1, 3.0, 20)
    period = exact_pendulum(amplitude) * (1 + 1e-14)
    status = np.zeros(20, np.int32)
    status[[3, 17]] = 2
    period[[3, 17]] = np.nan
    target = targets.Target("pendulum", None, "θ₀ (rad)", T0=2 * np.pi)
    target.extra["reference"] = "exact"
    r = {
        "system": "pendulum",
        "target": target,
        "amplitude": amplitude,
        "q0": amplitude,
        "period": period,
        "status": status,
    }
    target.exact = exact_pendulum
    cli_run.add_reference(r, target, None)
    fig = chart.chart([r], 1e-13)
    top, bottom = fig.axes
    assert top.get_ylabel() == "T / T₀" and bottom.get_yscale() == "log"
    failed = [line for line in top.get_lines() if line.get_marker() == "x"]
    assert len(failed) == 1 and len(failed[0].get_xdata()) == 2
    errors = [line for line in bottom.get_lines() if line.get_marker() == "."]
    assert len(errors) == 1 and len(errors[0].get_xdata()) == 18
    # Readable tick labels: no "6×10⁰" on a linear T/T₀ axis.
    fig.canvas.draw()
    labels = [t.get_text() for t in top.get_yticklabels() if t.get_text()]
    assert labels and not any("10^" in s or "×" in s for s in labels)


def test_user_module_by_attr_and_by_path_with_and_without_param(
    capsys, user_module, tmp_path
):
    common = ["--min", "0.5", "--max", "2.5", "--count", "12", "--lanes", "4"]
    results = {}
    for target, extra in [
        ("my_systems:L", []),
        (f"{user_module}:L", []),
        ("my_systems:pendulum", ["--param", "g=4"]),
        ("my_systems.py:pendulum", []),
    ]:
        out = tmp_path / f"{len(results)}.npz"
        rc, stdout, err = run(
            capsys, "sweep", target, *common, *extra, "--method", "quarter",
            "--out", out, "--quiet",
        )  # fmt: skip
        assert rc == 0, err
        assert "no reference" in stdout
        with np.load(out) as f:
            assert set(f["reference_kind"]) == {"none"}
            assert np.all(f["status"] == 0)
            results[target] = (f["amplitude"], f["period"])
            # T₀ from the small oscillations at the bottom of the well: 2π/√g.
            g = 4.0 if "g=4" in extra else 1.0
            np.testing.assert_allclose(
                f["T_over_T0"], f["period"] / (2 * np.pi / np.sqrt(g)), rtol=1e-12
            )
        assert "T/T0" in stdout.splitlines()[0]
    amplitude, period = results["my_systems:L"]
    np.testing.assert_allclose(period, exact_pendulum(amplitude), rtol=1e-12)
    np.testing.assert_array_equal(results[f"{user_module}:L"][1], period)
    np.testing.assert_array_equal(results["my_systems.py:pendulum"][1], period)
    # g = 4 halves the period: T ∝ 1/√g.
    np.testing.assert_allclose(
        results["my_systems:pendulum"][1], exact_pendulum(amplitude, g=4.0), rtol=1e-12
    )
    np.testing.assert_allclose(
        results["my_systems:pendulum"][1], period / 2, rtol=1e-12
    )


# `--reference quadrature` runs every time on a built-in system below.
@pytest.mark.slow
def test_quadrature_reference_agrees_with_the_exact_period(
    capsys, user_module, tmp_path
):
    out = tmp_path / "q.csv"
    rc, stdout, err = run(
        capsys, "sweep", "my_systems:pendulum", "--param", "g=9.81", "--min", "0.05",
        "--max", "3.0", "--count", "24", "--lanes", "8", "--method", "quarter",
        "--reference", "quadrature", "--out", out, "--quiet",
    )  # fmt: skip
    assert rc == 0, err
    assert "vs lagrax.quadrature_period" in stdout
    data = np.genfromtxt(out, delimiter=",", names=True, dtype=None, encoding=None)
    assert set(data["reference_kind"]) == {"quadrature"}
    exact = exact_pendulum(data["amplitude"], g=9.81)
    np.testing.assert_allclose(data["reference"], exact, rtol=1e-12)
    assert np.all(data["rel_error"] < 1e-11)


def test_systems_lists_builtins_with_parameters_and_defaults(capsys):
    rc, out, err = run(capsys, "systems")
    assert rc == 0, err
    lines = {line.split()[0]: line for line in out.splitlines()}
    assert {"pendulum", "cycloid", "asymmetric_well", "double_pendulum"} <= set(lines)
    assert "m=1.0" in lines["pendulum"] and "g=1.0" in lines["pendulum"]
    assert "exact period" in lines["pendulum"]
    assert "no exact period" in lines["asymmetric_well"]
    assert "2 coordinates" in lines["double_pendulum"]
    # (Its drag is a force, which a period sweep does not take.)
    assert "not for lagrax sweep" in lines["damped_pendulum"]
    assert "quadrature" not in lines["damped_pendulum"]
    # A function-valued default by its name, not its repr with an address.
    assert "potential=harmonic " in lines["rectilinear"] and " at 0x" not in out


def test_a_damped_system_is_refused_by_name(capsys):
    rc, _, err = run(capsys, "sweep", "damped_pendulum", "--min", "0.1", "--max", "1")
    assert rc == 2 and "damped_pendulum is damped" in err


def test_builtin_without_exact_period_uses_quadrature_on_request(capsys, tmp_path):
    out = tmp_path / "w.npz"
    rc, stdout, err = run(
        capsys, "sweep", "asymmetric_well", "--count", "8", "--lanes", "4",
        "--reference", "quadrature", "--out", out, "--quiet",
    )  # fmt: skip
    assert rc == 0, err
    with np.load(out) as f:
        assert np.all(f["status"] == 0)
        assert np.all(f["rel_error"] < 1e-10)
        # T0 = 2π√(m/k) and the asymmetric well's period grows with amplitude.
        assert np.all(np.diff(f["T_over_T0"]) > 0) and f["T_over_T0"][0] > 1


def test_failures_exit_1_and_are_named(capsys, tmp_path, user_module):
    # Released at q0 = 0, the bottom of the well: no oscillation, a failure per lane.
    # (The shape and options of the user-module sweeps above: their compiled program.)
    rc, out, err = run(
        capsys, "sweep", "my_systems:L", "--min", "0", "--max", "1", "--count", "12",
        "--lanes", "4", "--method", "quarter", "--quiet",
    )  # fmt: skip
    assert rc == 1
    assert "1 failed" in out
    assert "1 amplitudes failed" in err and "does not oscillate" in err


# Interrupted and killed sweeps resume every time in tests/test_faults.py.
@pytest.mark.slow
def test_interrupted_sweep_leaves_no_file_and_resumes(
    capsys, monkeypatch, tmp_path, umask_022
):
    out_npz = tmp_path / "res.npz"
    argv = [
        "sweep", "pendulum", "--count", "100", "--lanes", "8", "--devices", "1",
        "--out", out_npz,
    ]  # fmt: skip
    real = lagrax.sweep_periods
    calls = []

    def interrupt_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(lagrax, "sweep_periods", interrupt_second)
    rc, out, err = run(capsys, *argv)
    assert rc == 130 and "resume" in err
    assert not out_npz.exists()
    partial = str(out_npz) + ".partial"
    assert sorted(os.listdir(partial)) == ["manifest.json", "pendulum-00000.npz"]
    assert mode(os.path.join(partial, "pendulum-00000.npz")) == 0o644
    calls.clear()

    def count(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(lagrax, "sweep_periods", count)
    rc, out, err = run(capsys, *argv)
    assert rc == 0
    assert "resuming" in err and "1 of 4 blocks" in err
    assert len(calls) == 3  # blocks of 32: 4 blocks, the first one resumed
    with np.load(out_npz) as f:
        assert len(f["period"]) == 100 and np.all(f["status"] == 0)
        np.testing.assert_allclose(
            f["period"], exact_pendulum(f["amplitude"]), rtol=1e-12
        )
    assert not os.path.exists(str(out_npz) + ".partial")
    # Another command (other tolerances) does not reuse the checkpoints of this one.
    monkeypatch.setattr(lagrax, "sweep_periods", interrupt_second)
    calls.clear()
    rc, _, _ = run(capsys, *argv[:-2], "--out", out_npz.with_suffix(".csv"))
    assert rc == 130
    calls.clear()
    monkeypatch.setattr(lagrax, "sweep_periods", count)
    rc, _, err = run(
        capsys, *argv[:-2], "--rtol", "1e-12", "--out", out_npz.with_suffix(".csv")
    )
    assert rc == 0 and "resuming" not in err and len(calls) == 4


def test_sweep_with_the_taylor_solver(capsys, tmp_path):
    # (The shape of the table's sweep above, which the default runs with Taylor too:
    # its compiled program.)
    out_csv = tmp_path / "taylor.csv"
    argv = ["sweep", "pendulum", "--count", "40", "--lanes", "16", "--quiet"]
    rc, out, err = run(capsys, *argv, "--solver", "taylor", "--out", out_csv)
    assert rc == 0, err
    data = np.genfromtxt(out_csv, delimiter=",", names=True, dtype=None, encoding=None)
    assert len(data) == 40 and np.all(data["status"] == 0)
    np.testing.assert_allclose(
        data["period"], exact_pendulum(data["amplitude"]), rtol=1e-12
    )


def test_the_librarys_notices_print_as_one_line(monkeypatch, capsys):
    from lagrax._cli import main as cli_main

    def lines():
        warnings.warn("lagrax: a notice", stacklevel=2)
        warnings.warn("another warning", UserWarning, stacklevel=2)
        return ["a line"]

    monkeypatch.setattr(cli_main, "systems_lines", lines)
    with pytest.warns(UserWarning, match="another warning"):
        assert cli_main.main(["systems"]) == 0
    err = capsys.readouterr().err
    assert "lagrax: a notice\n" in err.splitlines(keepends=True)
    assert "UserWarning: lagrax" not in err
