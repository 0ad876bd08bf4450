"""Faults: failing lanes, chunking, interrupted and killed sweeps, bad command lines.

What tests/test_period.py and tests/test_cli.py already cover is not repeated here
(a NaN and an equilibrium lane next to good ones; a KeyboardInterrupt between blocks of
a first run; bad arguments of the common kinds). Added here: every failure kind in one
batch with the others bit-identical, lane-count independence bit for bit (failures
included), an interrupted rerun that keeps the earlier complete output and computes a
damaged checkpoint again, an interrupt inside the final write, a sweep killed with
SIGKILL and resumed, failing amplitudes counted by the command line (exit 1), and the
remaining bad-argument kinds.
"""

import os
import signal
import subprocess
import sys
import time

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
import lagrax._period.period
from lagrax._cli import main as _cli
from lagrax._results import (
    MAX_STEPS,
    NONFINITE_INPUT,
    NOT_OSCILLATING,
    SINGULAR_MASS,
    SUCCESS,
)


def _pendulum_with_a_singular_point(q, qdot, t):
    # A pendulum whose mass 1 - exp(-100 (q - 10)²) vanishes at q = 10 only (it is
    # exactly 1 in float64 for |q - 10| > 2.8, so the lanes near 0 see a plain
    # pendulum).
    x = q[0]
    m = 1.0 - jnp.exp(-100.0 * (x - 10.0) ** 2)
    return 0.5 * m * qdot[0] ** 2 + jnp.cos(x)


L = _pendulum_with_a_singular_point
# One static configuration for every sweep below (compiled once per chunk size). The
# mix of failures is built on Dopri8's step counts: it needs > 64 steps up to the hump
# from π - 1e-9 (max_steps), where Taylor() needs 34 and then reports the energy drift
# that Dopri8 reports too when given more steps (measured). Taylor's own failing lanes:
# tests/test_taylor_solver.py.
OPTIONS = dict(rtol=1e-10, atol=1e-10, max_steps=64, solver=dfx.Dopri8())
# 12 good and 4 bad lanes: 16, the size of the pieces a sweep with `progress` runs in
# at lanes=4, so that every sweep below of 16 lanes at lanes=4 runs one
# compiled program.
GOOD = np.array([0.3, 1.0, 2.0, 2.9, 0.7, 1.5, -2.5, 0.1, -1.2, 2.5, -0.5, 1.8])
# Good lanes that take the BAD lanes' places in a sweep without failures.
MORE = np.array([0.4, -2.2, 1.1, 2.7])
BAD = {
    np.pi - 1e-9: MAX_STEPS,  # the slow approach to the hump takes > 64 steps
    10.0: SINGULAR_MASS,  # released where the mass vanishes
    0.0: NOT_OSCILLATING,  # released at the equilibrium
    np.nan: NONFINITE_INPUT,
}


def _mixed():
    """GOOD with the BAD lanes interleaved; returns the amplitudes and the masks."""
    q0, is_bad = [], []
    bad = list(BAD)
    for i, a in enumerate(GOOD):
        q0.append(a)
        is_bad.append(False)
        if i < len(bad):
            q0.append(bad[i])
            is_bad.append(True)
    return np.array(q0), np.array(is_bad)


def _arrays(res):
    return {k: np.asarray(getattr(res, k)) for k in ("periods", "status", "num_steps")}


@pytest.fixture(scope="module")
def mixed_sweep():
    q0, is_bad = _mixed()
    res = lagrax.sweep_periods(L, jnp.asarray(q0), lanes=4, **OPTIONS)
    return q0, is_bad, res


def test_failing_lanes_counted_and_the_others_bit_identical(mixed_sweep):
    q0, is_bad, mixed = mixed_sweep
    clean = lagrax.sweep_periods(
        L, jnp.asarray(np.concatenate([GOOD, MORE])), lanes=4, **OPTIONS
    )
    got = _arrays(mixed)
    assert list(got["status"][is_bad]) == list(BAD.values())
    assert int(np.sum(~np.asarray(mixed.ok))) == len(BAD)
    assert np.isnan(got["periods"][is_bad]).all()
    messages = [m for m, bad in zip(mixed.messages(), is_bad) if bad]
    assert "max_steps" in messages[0] and "singular" in messages[1]
    # The good lanes: exactly the numbers (and the work) of a sweep without the others.
    ref = {k: v[: len(GOOD)] for k, v in _arrays(clean).items()}
    assert np.all(np.asarray(clean.status) == SUCCESS)
    np.testing.assert_array_equal(got["periods"][~is_bad], ref["periods"])
    np.testing.assert_array_equal(got["num_steps"][~is_bad], ref["num_steps"])
    # And they are right: the same pendulum as lagrax.systems.pendulum.
    np.testing.assert_allclose(
        ref["periods"], lagrax.systems.pendulum.period(GOOD), rtol=1e-8
    )


def test_results_independent_of_lanes_and_order(mixed_sweep):
    q0, is_bad, ref = mixed_sweep
    ref = _arrays(ref)
    # Same chunk size, other order (so other chunk members): bit for bit.
    got = _arrays(
        lagrax.sweep_periods(L, jnp.asarray(q0), lanes=4, sort=False, **OPTIONS)
    )
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)
    # Another chunk size: see below.
    _check_other_lanes(q0, is_bad, ref, 3)


# One lane per chunk: a program of its own (chunk size 3 above, every time).
@pytest.mark.slow
def test_results_with_one_lane_per_chunk(mixed_sweep):
    q0, is_bad, ref = mixed_sweep
    _check_other_lanes(q0, is_bad, _arrays(ref), 1)


def _check_other_lanes(q0, is_bad, ref, lanes):
    # Other chunk sizes: the same statuses, the same periods to well within the
    # tolerance, but not bit for bit. XLA vectorizes a batch of 3 or 1 differently
    # from one of 4 (a few ulps in the vector field), and an adaptive solve can turn
    # that into one step more or less: measured 9 ulps at lanes=3 and 2e-12
    # relative (22 steps instead of 24) at lanes=1, with rtol=1e-10.
    got = _arrays(lagrax.sweep_periods(L, jnp.asarray(q0), lanes=lanes, **OPTIONS))
    np.testing.assert_array_equal(got["status"], ref["status"])
    np.testing.assert_allclose(
        got["periods"][~is_bad], ref["periods"][~is_bad], rtol=1e-10, atol=0
    )
    assert np.isnan(got["periods"][is_bad]).all()


def test_period_failures_raise_with_the_status(mixed_sweep):
    with pytest.raises(RuntimeError, match="status 2 \\(max_steps\\)") as info:
        lagrax.period(L, np.pi - 1e-9, **OPTIONS)
    assert not isinstance(info.value, ValueError)  # not the input's fault
    with pytest.raises(ValueError, match="`q0`.*singular_mass"):
        lagrax.period(L, 10.0, **OPTIONS)


class _Recorder(dfx.AbstractProgressMeter):
    """A progress meter that keeps what it is told: "init", fractions, "close"."""

    seen: list = eqx.field(static=True)

    def init(self):
        self.seen.append("init")

    def step(self, state, progress):
        self.seen.append(float(progress))

    def close(self, state):
        self.seen.append("close")


def test_progress_reported_as_the_sweep_goes(mixed_sweep):
    q0, _, ref = mixed_sweep
    seen = []
    res = lagrax.sweep_periods(
        L, jnp.asarray(q0), lanes=4, progress_meter=_Recorder(seen), **OPTIONS
    )
    assert seen == ["init", 1.0, "close"]
    np.testing.assert_array_equal(res.status, ref.status)
    # A bigger batch is reported in pieces, fractions increasing to 1 (pieces of
    # the size the call above ran in: its compiled program again).
    seen = []
    many = jnp.asarray(np.tile(q0, 12))
    res = lagrax.sweep_periods(
        L, many, lanes=4, progress_meter=_Recorder(seen), **OPTIONS
    )
    done = seen[1:-1]
    assert seen[0] == "init" and seen[-1] == "close"
    assert len(done) > 1 and done == sorted(done) and done[-1] == 1.0
    np.testing.assert_array_equal(res.status, np.tile(ref.status, 12))
    # Sorted over the whole sweep, run in pieces, returned in input order: bit for bit.
    np.testing.assert_array_equal(res.periods, np.tile(ref.periods, 12))


# ----------------------------------------------------------------- command line

# Four blocks of 32 amplitudes (four chunks of 8): one compiled shape.
ARGV = ["sweep", "pendulum", "--count", "128", "--lanes", "8", "--quiet"]


def _run(capsys, *argv):
    rc = _cli.main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def _load(path):
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


def _assert_same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run of ARGV: its output file's bytes and arrays."""
    path = tmp_path_factory.mktemp("reference") / "res.npz"
    assert _cli.main([*ARGV, "--out", str(path)]) == 0
    return path.read_bytes(), _load(path)


def _leftovers(directory):
    return [name for name in os.listdir(directory) if name.startswith(".lagrax-")]


def test_interrupted_rerun_keeps_the_earlier_complete_output(
    capsys, monkeypatch, tmp_path, reference
):
    ref_bytes, ref = reference
    out = tmp_path / "res.npz"
    out.write_bytes(ref_bytes)  # complete, from an earlier run
    real = lagrax.sweep_periods
    calls = []

    def interrupt_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(lagrax, "sweep_periods", interrupt_third)
    rc, _, err = _run(capsys, *ARGV, "--out", str(out))
    assert rc == 130 and "resume" in err
    assert out.read_bytes() == ref_bytes

    # Interrupted again, in the middle of writing a checkpoint, then of writing the
    # final file: each time the earlier output stays, and no temporary is left over.
    monkeypatch.setattr(lagrax, "sweep_periods", real)
    real_savez = np.savez
    partial = tmp_path / "res.npz.partial"
    for directory in (partial, tmp_path):

        def savez_then_interrupt(path, directory=directory, **arrays):
            if os.path.dirname(path) != str(directory):
                return real_savez(path, **arrays)
            real_savez(path, **{k: arrays[k] for k in list(arrays)[:2]})  # half
            raise KeyboardInterrupt

        monkeypatch.setattr(np, "savez", savez_then_interrupt)
        rc, _, _ = _run(capsys, *ARGV, "--out", str(out))
        monkeypatch.setattr(np, "savez", real_savez)
        assert rc == 130
        assert out.read_bytes() == ref_bytes
        assert _leftovers(tmp_path) == [] and _leftovers(partial) == []

    # A piece those runs wrote is damaged (bytes flipped in its middle): the rerun
    # names it, computes that block again and resumes the others from their
    # checkpoints; the result agrees bit for bit with an uninterrupted run.
    pieces = [f"pendulum-0000{b}.npz" for b in range(4)]
    assert sorted(os.listdir(partial)) == ["manifest.json", *pieces]
    piece = partial / "pendulum-00000.npz"
    data = bytearray(piece.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 8] = bytes(b ^ 0xFF for b in data[middle : middle + 8])
    piece.write_bytes(bytes(data))
    calls.clear()

    def count(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(lagrax, "sweep_periods", count)
    rc, _, err = _run(capsys, *ARGV, "--out", str(out))
    assert rc == 0 and len(calls) == 1, err
    assert f"checkpoint {piece} is damaged" in err and "Traceback" not in err
    _assert_same(_load(out), ref)
    assert not os.path.exists(str(out) + ".partial")


def test_interrupted_csv_write_leaves_no_partial_file(capsys, monkeypatch, tmp_path):
    out = tmp_path / "res.csv"

    class Interrupting(dict):
        reads = 0

        def __getitem__(self, key):
            Interrupting.reads += 1
            if Interrupting.reads == 10:  # after 9 rows of the file
                raise KeyboardInterrupt
            return super().__getitem__(key)

    monkeypatch.setattr(lagrax, "STATUS_CODES", Interrupting(lagrax.STATUS_CODES))
    rc, _, _ = _run(capsys, *ARGV, "--rows", "0", "--out", str(out))
    assert rc == 130 and Interrupting.reads == 10
    assert not out.exists()
    assert _leftovers(tmp_path) == []


_SLOW_SWEEP = """
import sys, time
import lagrax as p
real = p.sweep_periods
def slow(*args, **kwargs):
    time.sleep(0.5)  # time for the test to kill us between two blocks
    return real(*args, **kwargs)
p.sweep_periods = slow
from lagrax._cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def test_killed_sweep_leaves_no_output_and_resumes(capsys, tmp_path, reference):
    _, ref = reference
    out = tmp_path / "res.npz"
    first_block = tmp_path / "res.npz.partial" / "pendulum-00000.npz"
    proc = subprocess.Popen(
        [sys.executable, "-c", _SLOW_SWEEP, *ARGV, "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 300
        while not first_block.exists():
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "no checkpoint written"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists()
    # Resumed in this process: identical to the uninterrupted reference.
    rc, _, err = _run(capsys, *ARGV, "--out", str(out))
    assert rc == 0, err
    _assert_same(_load(out), ref)


def test_failing_amplitudes_counted_and_exit_1(
    capsys, monkeypatch, tmp_path, reference
):
    _, ref = reference
    real = lagrax.sweep_periods

    def spoil(L, q0, **kwargs):
        q0 = q0.at[::7].set(jnp.nan)  # every 7th amplitude of each block
        return real(L, q0, **kwargs)

    monkeypatch.setattr(lagrax, "sweep_periods", spoil)
    out = tmp_path / "res.npz"
    loud = [a for a in ARGV if a != "--quiet"]
    rc, stdout, err = _run(capsys, *loud, "--out", str(out))
    got = _load(out)
    failed = got["status"] != 0
    assert rc == 1
    assert f"{failed.sum()} amplitudes failed" in err
    assert f"{failed.sum()} failed" in stdout
    assert np.all(got["status"][failed] == NONFINITE_INPUT)
    assert np.isnan(got["period"][failed]).all()
    assert 0 < failed.sum() < len(failed)
    for k in ("period", "status", "steps"):
        np.testing.assert_array_equal(got[k][~failed], ref[k][~failed], err_msg=k)


@pytest.mark.parametrize(
    "argv",
    [
        ["sweep", "--lanes", "0"],
        ["sweep", "--rows", "-1"],
        ["sweep", "--atol", "nan"],
        ["sweep", "--rtol", "inf"],
        ["sweep", "--min", "nan"],
        ["sweep", "cycloid", "--max", "inf"],
        ["sweep", "--min", "0"],
        ["sweep", "--count", "1.5"],
        ["sweep", "--count"],
        ["sweep", "--bogus"],
        ["sweep", "--method", "eighth"],
        ["sweep", "--plot", "chart.txt"],
        ["frobnicate"],
    ],
)
def test_more_bad_arguments_exit_2_with_one_line(capsys, argv):
    rc, out, err = _run(capsys, *argv)
    assert rc == 2 and out == ""
    assert err.startswith("lagrax: error:") and err.count("\n") == 1
    assert "Traceback" not in err


def test_unwritable_outputs_fail_before_the_sweep(capsys, monkeypatch, tmp_path):
    def boom(*args, **kwargs):
        raise AssertionError("the sweep ran")

    monkeypatch.setattr(lagrax, "sweep_periods", boom)
    good = tmp_path / "res.npz"
    directory = tmp_path / "dir.csv"
    directory.mkdir()
    for argv in (
        ["--out", str(directory)],
        ["--out", str(good), "--plot", str(tmp_path / "nodir" / "c.png")],
        ["--out", "/proc/lagrax-test.csv"],  # not writable, even by root
    ):
        rc, out, err = _run(capsys, "sweep", "pendulum", *argv)
        assert rc == 2 and "cannot write" in err and err.count("\n") == 1, err
    # Nothing was created: no output, no checkpoint directory, no probe file.
    assert os.listdir(tmp_path) == ["dir.csv"] and os.listdir(directory) == []


def test_console_entry_point_exit_status():
    # The real process: `python -m lagrax` with a bad argument exits 2, one line.
    proc = subprocess.run(
        [sys.executable, "-m", "lagrax", "sweep", "--count", "-5"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.startswith("lagrax: error: --count")
    assert proc.stderr.count("\n") == 1
