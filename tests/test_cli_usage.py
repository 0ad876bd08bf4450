"""`lagrax` command line: usage errors and helpers that need no sweep to run.

Each case fails before any work (the sweep is replaced by one that fails the test if
called), so these are cheap; the end-to-end runs are in test_cli.py.
"""

import os
import re
import sys
import textwrap

import jax.numpy as jnp
import matplotlib.ticker
import numpy as np
import pytest

import lagrax
from lagrax._cli import (
    chart,
    main as _cli,
    output,
    parser,
    processes,
    run as cli_run,
    targets,
)
from lagrax.systems import pendulum


def run(capsys, *argv):
    rc = _cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture
def no_sweep(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("the sweep ran")

    monkeypatch.setattr(lagrax, "sweep_periods", boom)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--rows", "-1"], "--rows must be >= 0"),
        (["--max-steps", "0"], "--max-steps must be positive"),
        (["--min", "nan"], "--min must be a finite number"),
        (["--max", "inf"], "--max must be a finite number"),
        (["--atol", "0"], "--atol must be a positive number"),
        (["--timeout", "0"], "--timeout must be a positive number"),
        (["--param", "g=(1, 'x')"], "a sequence value must hold numbers"),
        (["--param", "2g=1"], "--param must be NAME=VALUE"),
        (["pendulum", "pendulum"], "a TARGET is given twice"),
        (["both", "cycloid"], "a TARGET is given twice"),
        (
            ["--coordinator", "h:1", "--num-processes", "0", "--process-id", "0"],
            "--num-processes must be positive",
        ),
        (
            ["--coordinator", "h:99999", "--num-processes", "2", "--process-id", "0"],
            "--coordinator must be HOST:PORT",
        ),
        (["--out", "results.npy"], "--out must end in .csv or .npz"),
    ],
)
def test_usage_errors_name_the_option(capsys, no_sweep, argv, message):
    rc, out, err = run(capsys, "sweep", *argv)
    assert rc == 2 and out == ""
    assert err.startswith("lagrax: error:") and err.count("\n") == 1, err
    assert message in err, err


def test_output_path_that_is_a_directory_is_refused(capsys, no_sweep, tmp_path):
    target = tmp_path / "res.csv"
    target.mkdir()
    rc, _, err = run(capsys, "sweep", "--out", target)
    assert rc == 2 and "it is a directory" in err


MODULE = textwrap.dedent(
    """
    import jax.numpy as jnp


    def returns_number():
        return 3


    def returns_two_args():
        return lambda q, qdot: q[0]


    def needs_k(*, k):
        def L(q, qdot, t):
            return 0.5 * qdot[0] ** 2 - 0.5 * k * q[0] ** 2

        return L


    def always_fails(q, qdot, t):
        raise ValueError("never traceable")


    class Box:
        pass


    box = Box()
    """
)


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    (tmp_path / "cli_usage_systems.py").write_text(MODULE)
    (tmp_path / "cli_usage_broken.py").write_text("raise RuntimeError('bad import')\n")
    (tmp_path / "cli_usage_missing_dep.py").write_text("import no_such_dep_xyz\n")
    (tmp_path / "data.txt").write_text("not python\n")
    monkeypatch.chdir(tmp_path)
    yield tmp_path
    for name in ("cli_usage_systems", "cli_usage_broken", "cli_usage_missing_dep"):
        sys.modules.pop(name, None)


@pytest.mark.parametrize(
    "target, extra, message",
    [
        ("cli_usage_systems:returns_number", [], "returned a int, not a Lagrangian"),
        (
            "cli_usage_systems:returns_two_args",
            [],
            "returned a function of 2 required argument(s)",
        ),
        ("cli_usage_systems:needs_k", [], "needs the parameter 'k'"),
        ("cli_usage_systems:always_fails", [], "failed: ValueError: never traceable"),
        ("cli_usage_systems:box.missing", [], "has no attribute 'missing'"),
        ("cli_usage_systems:", [], "expected module:attr"),
        ("cli_usage_broken:L", [], "raised RuntimeError: bad import"),
        ("cli_usage_broken.py:L", [], "raised RuntimeError: bad import"),
        ("cli_usage_missing_dep:L", [], "raised ModuleNotFoundError"),
        ("./data.txt:L", [], "(not Python)"),
    ],
)
def test_bad_user_targets_are_usage_errors(
    capsys, no_sweep, user_dir, target, extra, message
):
    rc, out, err = run(
        capsys, "sweep", target, "--min", "0.1", "--max", "1", "--count", "4", *extra
    )
    assert rc == 2 and out == "", err
    assert err.startswith("lagrax: error:") and err.count("\n") == 1, err
    assert message in err, err


def test_factory_with_a_required_parameter_runs_when_given(capsys, user_dir, tmp_path):
    out = tmp_path / "k.npz"
    rc, _, err = run(
        capsys, "sweep", "cli_usage_systems:needs_k", "--param", "k=4", "--min", "0.1",
        "--max", "1", "--count", "4", "--lanes", "4", "--out", out, "--quiet",
    )  # fmt: skip
    assert rc == 0, err
    with np.load(out) as f:
        # A harmonic oscillator: T = 2π/√k at every amplitude.
        np.testing.assert_allclose(f["period"], np.pi, rtol=1e-10)


def test_unreachable_cluster_exits_3(capsys, monkeypatch):
    def unreachable(args):
        raise processes.Unreachable("could not join the other processes")

    monkeypatch.setattr(_cli, "run_sweep", unreachable)
    rc, out, err = run(capsys, "sweep")
    assert rc == 3 and out == ""
    assert err == "lagrax: error: could not join the other processes\n"


def test_cpu_count_without_affinity(monkeypatch):
    assert parser.cpu_count() >= 1
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    assert parser.cpu_count() == (os.cpu_count() or 1)


def test_status_names_follow_the_status_codes():
    for code, name in lagrax.STATUS_CODES.items():
        expected = name if isinstance(name, str) else str(name[0])
        assert output.status_name(code) == expected
    unknown = max(lagrax.STATUS_CODES) + 100
    assert output.status_name(unknown) == f"status_{unknown}"


def test_chart_switches_to_a_log_axis_for_a_wide_range():
    # Periods over two decades of T/T0 (a well that stiffens and softens a lot).
    amplitude = np.linspace(0.1, 3.0, 30)
    period = 2 * np.pi * np.geomspace(1.0, 100.0, 30)
    target = targets.Target("pendulum", None, "θ₀ (rad)", T0=2 * np.pi)
    target.extra["reference"] = "none"
    r = {
        "system": "pendulum",
        "target": target,
        "amplitude": amplitude,
        "q0": amplitude,
        "period": period,
        "status": np.zeros(amplitude.size, np.int32),
    }
    cli_run.add_reference(r, target, None)
    assert np.nanmax(period) / np.nanmin(period) > 30
    fig = chart.chart([r], 1e-13)
    top = fig.axes[0]
    assert top.get_yscale() == "log"
    assert isinstance(top.yaxis.get_major_formatter(), matplotlib.ticker.FuncFormatter)
    fig.canvas.draw()
    labels = [t.get_text() for t in top.get_yticklabels() if t.get_text()]
    assert labels and not any("10^" in s or "×" in s for s in labels)


def test_the_command_line_names_no_system():
    # Each system declares what the command needs (lagrax.systems.SweepSpec): the
    # command line's own code special-cases none of them by name.
    names = targets.builtin_names()
    assert {"pendulum", "cycloid", "asymmetric_well"} <= set(names)
    folder = os.path.dirname(targets.__file__)
    for file in os.listdir(folder):
        if file.endswith(".py"):
            with open(os.path.join(folder, file), encoding="utf-8") as f:
                source = f.read()
            for name in names:
                assert not re.search(rf"\b{name}\b", source), (file, name)


def test_a_system_is_swept_as_its_sweep_spec_says(monkeypatch):
    from lagrax.systems import rotating_hoop, SweepSpec

    def sweep_range(*, R=1.0):
        return 0.1 * R, 0.5 * R

    spec = SweepSpec("bead on a hoop", "θ₀ (rad)", sweep_range, (0.0, 1.0), "quarter")
    monkeypatch.setattr(rotating_hoop, "SWEEP", spec, raising=False)
    target = targets.builtin("rotating_hoop", {"R": 2.0})
    assert target.default_range == (0.2, 1.0) and target.bounds == (0.0, 1.0)
    assert target.method == "quarter" and target.amplitude_label == "θ₀ (rad)"
    assert chart.label({"target": target}) == "bead on a hoop (amplitude θ₀ (rad))"
    # Without a SweepSpec: the release point is the amplitude, no default range.
    monkeypatch.delattr(rotating_hoop, "SWEEP")
    target = targets.builtin("rotating_hoop", {})
    assert target.default_range is None and target.method == "matched"
    assert target.amplitude_label == "q₀" and target.to_q0 is None


def test_a_lagrangian_summed_over_its_coordinates_is_of_one_coordinate():
    # It runs at every shape: one coordinate when given one, whatever the widest
    # shape it accepts.
    L = lambda q, qdot, t: 0.5 * np.sum(qdot**2) - 0.5 * np.sum(q**2)
    targets.check_one_dof(targets.Target("mine:L", L))
    unpacked = lambda q, qdot, t: (lambda a, b: a * b)(*q) + qdot @ qdot
    with pytest.raises(parser.UsageError, match="'mine:L' has 2 coordinates"):
        targets.check_one_dof(targets.Target("mine:L", unpacked))


def test_chart_draws_the_cutoff_that_decides_with_legends_off_the_curves():
    # Estimates between rtol and 100 rtol: every lane succeeded, and the chart must
    # not read as failure. The line drawn is the cutoff that decides.
    amplitude = np.linspace(0.1, 3.1, 200)
    period = np.asarray(pendulum.period(amplitude)) * (1 + 1e-14)
    target = targets.Target("pendulum", None, "θ₀ (rad)", T0=2 * np.pi)
    target.exact = lambda a: np.asarray(pendulum.period(a))
    target.extra["reference"] = "exact"
    r = {
        "system": "pendulum",
        "target": target,
        "amplitude": amplitude,
        "q0": amplitude,
        "period": period,
        "status": np.zeros(amplitude.size, np.int32),
        "error_estimate": np.geomspace(2e-13, 5e-12, amplitude.size),
    }
    cli_run.add_reference(r, target, None)
    fig = chart.chart([r], 1e-13)
    top, bottom = fig.axes
    flat = [
        line.get_ydata()[0]
        for line in bottom.get_lines()
        if len(set(line.get_ydata())) == 1 and len(line.get_ydata()) == 2
    ]
    assert flat == [pytest.approx(1e-11)]  # 100 rtol, not rtol
    assert any("cutoff" in text.get_text() for text in bottom.get_legend().texts)
    assert bottom.get_ylim()[0] < 2e-13 and bottom.get_ylim()[1] > 1e-11
    fig.canvas.draw()
    for ax in (top, bottom):
        box = ax.get_legend().get_window_extent()
        for line in ax.get_lines():
            xy = line.get_transform().transform(line.get_xydata())
            inside = (
                (xy[:, 0] >= box.x0)
                & (xy[:, 0] <= box.x1)
                & (xy[:, 1] >= box.y0)
                & (xy[:, 1] <= box.y1)
            )
            assert not inside.any(), (ax.get_ylabel(), line.get_label())


def test_small_oscillation_period_at_the_bottom_of_the_well():
    # A cubic well whose bottom is at x = 1.5, stiffness 9: T₀ = 2π/3, from release
    # points on either side; none for a free particle or a hump.
    well = lambda q, v, t: 0.5 * v[0] ** 2 - 4.5 * (q[0] - 1.5) ** 2 - (q[0] - 1.5) ** 3
    for q0 in (1.2, 2.0, 1.5):
        T0 = targets.small_oscillation_period(well, q0)
        assert T0 == pytest.approx(2 * np.pi / 3, rel=1e-12)
    # The pendulum from near its hump, on both sides: the bottom at 0, not the hump.
    pendulum_L = lambda q, v, t: 0.5 * v[0] ** 2 + 4 * jnp.cos(q[0])
    for q0 in (3.1, -3.0):
        T0 = targets.small_oscillation_period(pendulum_L, q0)
        assert T0 == pytest.approx(np.pi, rel=1e-12)
    assert (
        targets.small_oscillation_period(lambda q, v, t: 0.5 * v[0] ** 2, 1.0) is None
    )
    hump = lambda q, v, t: 0.5 * v[0] ** 2 + 0.5 * q[0] ** 2
    assert targets.small_oscillation_period(hump, 1.0) is None


def test_no_known_T0_leaves_the_column_out(tmp_path):
    target = targets.Target("mine:L", None)
    target.extra["reference"] = "none"
    r = {
        "system": "mine:L",
        "target": target,
        "amplitude": np.array([0.1, 0.2]),
        "q0": np.array([0.1, 0.2]),
        "period": np.array([6.3, 6.4]),
        "status": np.zeros(2, np.int32),
        "steps": np.array([10, 11]),
    }
    cli_run.add_reference(r, target, None)
    output.write_out(str(tmp_path / "res.csv"), [r])
    header = (tmp_path / "res.csv").read_text().splitlines()[0].split(",")
    assert "period" in header and "T_over_T0" not in header
