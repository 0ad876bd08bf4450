import os

import numpy as np
import pytest

import lagrax._period
from lagrax import _cli
from lagrax.systems import pendulum


def run(capsys, *argv):
    rc = _cli.main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


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
        [],
    ],
)
def test_bad_arguments_exit_2_with_one_line(capsys, argv):
    rc, out, err = run(capsys, *argv)
    assert rc == 2
    assert out == ""
    assert err.startswith("lagrax: error:") and err.count("\n") == 1
    assert "Traceback" not in err


def test_unwritable_output_fails_before_the_sweep(capsys, monkeypatch, tmp_path):
    def boom(*args, **kwargs):
        raise AssertionError("the sweep ran")

    monkeypatch.setattr(lagrax._period, "sweep_periods", boom)
    missing = tmp_path / "no" / "such" / "dir" / "out.csv"
    rc, out, err = run(capsys, "sweep", "--out", str(missing))
    assert rc == 2 and "cannot write" in err
    rc, out, err = run(capsys, "sweep", "--plot", str(tmp_path))
    assert rc == 2


def test_sweep_writes_table_csv_and_chart(capsys, tmp_path):
    out_csv = tmp_path / "res.csv"
    chart = tmp_path / "chart.png"
    rc, out, err = run(
        capsys,
        "sweep",
        "pendulum",
        "--count",
        "40",
        "--chunk-size",
        "16",
        "--out",
        str(out_csv),
        "--plot",
        str(chart),
        "--rows",
        "5",
    )
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[0].split()[:3] == ["system", "amplitude", "period"]
    assert sum(line.startswith("pendulum ") for line in lines) == 5
    assert "max relative error" in out
    data = np.genfromtxt(out_csv, delimiter=",", names=True, dtype=None, encoding=None)
    assert len(data) == 40
    np.testing.assert_allclose(
        data["period"], pendulum.pendulum_period(data["amplitude"]), rtol=1e-12
    )
    assert np.all(data["status"] == 0)
    assert chart.read_bytes()[:4] == b"\x89PNG"
    assert not os.path.exists(str(out_csv) + ".partial")


def test_interrupted_sweep_leaves_no_file_and_resumes(capsys, monkeypatch, tmp_path):
    out_npz = tmp_path / "res.npz"
    argv = [
        "sweep",
        "pendulum",
        "--count",
        "100",
        "--chunk-size",
        "8",
        "--out",
        str(out_npz),
        "--quiet",
    ]
    real = lagrax._period.sweep_periods
    calls = []

    def interrupt_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(lagrax._period, "sweep_periods", interrupt_second)
    rc, out, err = run(capsys, *argv)
    assert rc == 130 and "resume" in err
    assert not out_npz.exists()
    assert sorted(os.listdir(str(out_npz) + ".partial")) == [
        "manifest.json",
        "pendulum-00000.npz",
    ]
    calls.clear()

    def count(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(lagrax._period, "sweep_periods", count)
    rc, out, err = run(capsys, *argv)
    assert rc == 0
    assert len(calls) == 3  # blocks of 32: 4 blocks, the first one resumed
    with np.load(out_npz) as f:
        assert len(f["period"]) == 100 and np.all(f["status"] == 0)
        np.testing.assert_allclose(
            f["period"], pendulum.pendulum_period(f["amplitude"]), rtol=1e-12
        )
    assert not os.path.exists(str(out_npz) + ".partial")
