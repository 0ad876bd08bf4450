"""`sweep_periods` and `lagrax sweep --distributed` over several local processes.

Each case starts real processes (`subprocess`) that meet through `jax.distributed` on a
free port of 127.0.0.1 with gloo collectives: JAX's own multi-controller runtime, as on
a cluster, with no network beyond this machine.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HANG = 240  # seconds: a guard against a hang, far above a normal run's duration


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def env(devices=1, cache=None):
    e = dict(os.environ)
    e["PYTHONPATH"] = ROOT + os.pathsep + e.get("PYTHONPATH", "")
    e["JAX_PLATFORMS"] = "cpu"
    e.pop("XLA_FLAGS", None)
    e["LAGRAX_TEST_DEVICES"] = str(devices)
    if cache is not None:
        e["XDG_CACHE_HOME"] = str(cache)
    return e


# Pendulum amplitudes with two failing lanes: q0 = 0 (at equilibrium: sorted first) and
# NaN (sorted last). Whether the sweep hands out lanes by contiguous slices or
# round-robin, with an even count the two ends fall on different processes.
SWEEP = textwrap.dedent(
    """
    import os, sys
    import jax
    jax.config.update("jax_num_cpu_devices", int(os.environ["LAGRAX_TEST_DEVICES"]))
    jax.config.update("jax_enable_x64", True)
    nproc, pid, port, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
    if nproc > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(
            coordinator_address=f"127.0.0.1:{port}", num_processes=nproc,
            process_id=pid, initialization_timeout=60, heartbeat_timeout_seconds=10,
        )
    import jax.numpy as jnp
    import numpy as np
    import lagrax
    from lagrax.systems import pendulum

    amplitude = np.linspace(0.05, 3.0, 30)
    q0 = np.concatenate([[0.0], amplitude, [np.nan]])
    res = lagrax.sweep_periods(
        pendulum.lagrangian(), jnp.asarray(q0), method="quarter", lanes=4
    )
    fields = dict(
        periods=np.asarray(res.periods),  # fully addressable on every process
        status=np.asarray(res.status),
        num_steps=np.asarray(res.num_steps),
        devices=np.asarray([len(jax.devices()), len(jax.local_devices())]),
    )
    if hasattr(res, "error_estimate"):
        fields["error_estimate"] = np.asarray(res.error_estimate)
    np.savez(out, **fields)
    print("done", pid, flush=True)
    """
)


def start(script, *args, devices=1, cache=None):
    return subprocess.Popen(
        [sys.executable, "-c", script, *map(str, args)],
        env=env(devices, cache),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(proc, timeout=HANG):
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"process hung for {timeout} s; stderr: {err[-2000:]}")
    return proc.returncode, out, err


# Three processes; the command line's distributed run below checks two processes'
# results every time, and tests/test_sharding.py two devices against one bit for bit.
@pytest.mark.slow
def test_two_processes_each_get_the_one_process_result_bit_for_bit(tmp_path):
    port = free_port()
    files = [tmp_path / f"p{i}.npz" for i in range(2)]
    single = tmp_path / "single.npz"
    # Two processes of one device each, and one process of two devices: the same
    # global devices, the same lanes.
    procs = [start(SWEEP, 2, i, port, files[i]) for i in range(2)]
    procs.append(start(SWEEP, 1, 0, 0, single, devices=2))
    for proc in procs:
        rc, out, err = finish(proc)
        assert rc == 0, err[-3000:]
    with np.load(single) as f:
        one = dict(f)
    assert list(one["devices"]) == [2, 2]
    for path in files:
        with np.load(path) as f:
            got = dict(f)
        assert list(got["devices"]) == [2, 1]
        assert got.keys() == one.keys()
        for key in one:
            if key != "devices":
                np.testing.assert_array_equal(got[key], one[key], err_msg=key)
    # The failing lanes, one on each process, are in the gathered statuses.
    status = one["status"]
    assert status[0] != 0 and status[-1] != 0 and np.all(status[1:-1] == 0)
    assert np.isnan(one["periods"][0]) and np.isnan(one["periods"][-1])
    from lagrax.systems import pendulum

    np.testing.assert_allclose(
        one["periods"][1:-1],
        np.asarray(pendulum.period(np.linspace(0.05, 3.0, 30))),
        rtol=1e-12,
    )


FOREVER = textwrap.dedent(
    """
    import sys
    import jax
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    pid, port = int(sys.argv[1]), sys.argv[2]
    jax.distributed.initialize(
        coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=pid,
        initialization_timeout=60, heartbeat_timeout_seconds=5,
    )
    import jax.numpy as jnp
    import lagrax
    from lagrax.systems import pendulum

    L = pendulum.lagrangian()
    q0 = jnp.linspace(0.05, 3.0, 64)
    while True:  # until the other process is gone
        lagrax.sweep_periods(L, q0, method="quarter", lanes=4)
        print("swept", flush=True)
    """
)


# Two processes that sweep until one is killed: JAX's heartbeat is what ends the
# survivor; the processes' agreement runs every time in the test above.
@pytest.mark.slow
@pytest.mark.parametrize("victim", [1, pytest.param(0, id="coordinator")])
def test_a_killed_process_makes_the_other_exit_with_an_error(victim):
    port = free_port()
    procs = [start(FOREVER, i, port) for i in range(2)]
    # Both have swept at least once together before one is killed.
    for proc in procs:
        # (gloo may announce its connection on stdout first)
        while (line := proc.stdout.readline()) and line.strip() != "swept":
            pass
        assert line.strip() == "swept", "the process ended before its first sweep"
    procs[victim].send_signal(signal.SIGKILL)
    procs[victim].wait()
    survivor = procs[1 - victim]
    rc, _, err = finish(survivor, timeout=120)  # heartbeat timeout 5 s
    assert rc != 0
    assert (
        "heartbeat" in err
        or "another task died" in err
        or "unavailable" in (err.lower())
    ), err[-3000:]


def cli(port, pid, out, cache, *extra):
    return [
        "-m", "lagrax", "sweep", "pendulum", "--count", "400", "--lanes", "2",
        "--devices", "1", "--distributed", "--coordinator", f"127.0.0.1:{port}",
        "--num-processes", "2", "--process-id", str(pid), "--timeout", "20",
        "--out", str(out), *extra,
    ]  # fmt: skip


def start_cli(port, pid, out, cache):
    return subprocess.Popen(
        [sys.executable, *cli(port, pid, out, cache)],
        env=env(1, cache),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_cli_distributed_writes_one_file_and_resumes(tmp_path):
    out = tmp_path / "res.csv"
    partial = tmp_path / "res.csv.partial"
    cache = tmp_path / "cache"
    # First run: stopped (both processes killed) once a block is checkpointed.
    port = free_port()
    procs = [start_cli(port, i, out, cache) for i in range(2)]
    deadline = time.monotonic() + HANG
    # A finished block is one whose checksum the manifest holds: the piece is written
    # first, and a piece killed before its checksum is in is computed again.
    done = lambda: _checksummed(partial)
    while not done():
        assert all(p.poll() is None for p in procs), procs[0].communicate()[1][-3000:]
        assert time.monotonic() < deadline, "no checkpoint was written"
        time.sleep(0.05)
    for p in procs:
        p.kill()
        p.wait()
    assert not out.exists()
    assert done() and "manifest.json" in _listdir(partial)
    # Second run: the same command resumes, and process 0 alone writes the result.
    port = free_port()
    procs = [start_cli(port, i, out, cache) for i in range(2)]
    (rc0, out0, err0), (rc1, out1, err1) = finish(procs[0]), finish(procs[1])
    assert rc0 == 0 and rc1 == 0, err0[-3000:] + err1[-3000:]
    assert "resuming" in err0 and "resuming" not in err1
    assert "max relative error" in out0 and out1 == ""
    assert sorted(os.listdir(tmp_path)) == ["cache", "res.csv"]  # no partial, no tmp
    data = np.genfromtxt(out, delimiter=",", names=True, dtype=None, encoding=None)
    assert len(data) == 400 and np.all(data["status"] == 0)
    from lagrax.systems import pendulum

    np.testing.assert_allclose(
        data["period"], np.asarray(pendulum.period(data["amplitude"])),
        rtol=1e-12,
    )  # fmt: skip


def _checksummed(partial):
    """The pieces the checkpoint's manifest vouches for (written atomically)."""
    try:
        with open(partial / "manifest.json") as f:
            return list(json.load(f)["pieces"])
    except FileNotFoundError:
        return []


def _listdir(path):
    try:
        return os.listdir(path)
    except FileNotFoundError:
        return []
