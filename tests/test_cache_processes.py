"""What the disk cache keeps is run twice, in two fresh processes sharing one cache
folder: the second loads what the first wrote, must not crash, and must give the same
numbers bit for bit (`cache_worker.py` runs the calls).

In-process tests (`test_executables.py`) empty this process's table to stand for a
later process; only a real one shows what a new process lacks (an executable whose
LAPACK kernels were never set up there crashed it)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest


HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import cache_worker  # noqa: E402


# The default run: one process pair over the kinds that crashed a later process
# (LAPACK kernels in a variational solver's Newton iteration and in the mass-matrix
# solve of n >= 3 coordinates) and a sweep; every kind on its own pair with -m slow.
DEFAULT = ["simulate_gauss_legendre4", "simulate_three_coordinates", "simulate_tsit5"]
# Programs the cache refuses to write (a host callback: bound to its process): a
# progress meter's, and diffrax's checks of save times and of an adaptive solver's
# `dt0`.
REFUSED = {"simulate_progress_meter", "simulate_saveat_ts", "simulate_dt0"}
# Calls that compile nothing the cache keeps (they run op by op or under the caller's
# trace): still run twice, for the crash and the numbers. (`period` runs the sweep's
# programs, which the cache keeps.)
UNCACHED = {"simulate_batch_tsit5", "quadrature_period"}


def _run(cache, out, cases):
    env = dict(os.environ, LAGRAX_CACHE_DIR=str(cache), PYTHONFAULTHANDLER="1")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    proc = subprocess.run(
        [sys.executable, os.path.join(HERE, "cache_worker.py"), str(out), *cases],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, (
        f"exit status {proc.returncode} running {cases}:\n{proc.stderr[-4000:]}"
    )
    with open(str(out).removesuffix(".npz") + ".json") as fh:
        record = json.load(fh)
    with np.load(out) as data:
        return {k: data[k] for k in data.files}, record


def _two_processes(tmp_path, cases):
    cache = tmp_path / "cache"
    first, record1 = _run(cache, tmp_path / "first.npz", cases)
    second, record2 = _run(cache, tmp_path / "second.npz", cases)
    assert sorted(first) == sorted(second) and first
    for name in first:
        np.testing.assert_array_equal(second[name], first[name], err_msg=name)
    for case in cases:
        one, two = record1[case], record2[case]
        if case in REFUSED:
            # (Its start check has no callback: written; the solve refused.)
            assert one.get("compiled", 0) >= 1 and one.get("refused", 0) >= 1, one
            assert two.get("compiled", 0) >= 1, two
        elif case in UNCACHED:
            assert two.get("loaded", 0) == 0 and two.get("written", 0) == 0, two
        else:
            assert one.get("written", 0) >= 1, (case, one)
            assert two.get("loaded", 0) >= 1 and two.get("compiled", 0) == 0, (
                case,
                two,
            )


def test_the_kinds_that_crashed_run_twice(tmp_path):
    _two_processes(tmp_path, DEFAULT)


@pytest.mark.slow
@pytest.mark.parametrize("case", [c for c in cache_worker.CASES if c not in DEFAULT])
def test_every_kind_runs_twice(tmp_path, case):
    _two_processes(tmp_path, [case])


def test_the_case_lists_agree():
    assert set(DEFAULT) | REFUSED | UNCACHED <= set(cache_worker.CASES)
    assert len(set(cache_worker.CASES)) == len(cache_worker.CASES)


def _cli_twice(tmp_path, *args):
    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path / "home"))
    env.pop("LAGRAX_CACHE_DIR")  # (the command's default folder, under the home)
    outs = []
    for run in ("first", "second"):
        out = tmp_path / f"{run}.csv"
        proc = subprocess.run(
            [sys.executable, "-m", "lagrax", "sweep", *args, "--out", str(out)],
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert proc.returncode == 0, f"{run} run:\n{proc.stderr[-4000:]}"
        outs.append(out.read_text())
    assert outs[0] == outs[1]
    cache = tmp_path / "home" / "lagrax" / "executables"
    return sorted(p.name for p in cache.iterdir())


def test_the_command_line_runs_twice_on_one_cache(tmp_path):
    names = _cli_twice(tmp_path, "pendulum", "--count", "64", "--solver", "tsit5")
    assert any(n.endswith(".bin") for n in names)


@pytest.mark.slow
def test_the_default_job_runs_twice_on_one_cache(tmp_path):
    names = _cli_twice(tmp_path, "--count", "256")
    assert any(n.endswith(".bin") for n in names)


# A program made by `executables.program`, in a process whose XLA splits loops
# (`PJRT_NPROC=2`): compiled apart (loops whole), written, loaded by the next.
_APART = """
import json, sys
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from lagrax._cache import executables

def fun(x, y):
    return jax.lax.fori_loop(0, 3, lambda i, x: jnp.sin(x) * 1.0001 + y * x, x)

options = {"xla_cpu_use_fusion_emitters": False}
x, y = jnp.linspace(0.0, 1.0, 500_000), jnp.linspace(1.0, 0.0, 500_000)
f = executables.program(fun, options, loop_bytes=1 << 62)
out = executables.call(f, "apart", jax.tree.structure(x), x, y)
here = jax.jit(fun, compiler_options=options).lower(x, y).compile()
((compiled, _),) = executables._LOADED.values()
parts = [c.as_text().count('outer_dimension_partitions":["') for c in (here, compiled)]
whole = [c.as_text().count('xla_cpu_small_call="true"') for c in (here, compiled)]
np.save(sys.argv[1], np.asarray(out))
same = bool(np.array_equal(out, here(x, y)))
stats = dict(executables.STATS)
print(json.dumps(dict(stats=stats, parts=parts, whole=whole, same=same)))
"""


def test_a_program_compiled_apart_runs_twice_on_one_cache(tmp_path):
    env = dict(os.environ, LAGRAX_CACHE_DIR=str(tmp_path / "cache"), PJRT_NPROC="2")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    runs = []
    for run in ("first", "second"):
        proc = subprocess.run(
            [sys.executable, "-c", _APART, str(tmp_path / f"{run}.npy")],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert proc.returncode == 0, f"{run} run:\n{proc.stderr[-4000:]}"
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    first, second = runs
    assert first["stats"] == {"compiled apart": 1, "written": 1}, first
    assert second["stats"] == {"loaded": 1}, second
    # Split where compiled in the process, whole where compiled apart, its loop one
    # function there (`_compat.whole_loop_environment`), not here.
    assert first["parts"][0] >= 1 and first["parts"][1] == 0 and second["parts"][1] == 0
    assert first["whole"][0] == 0 and first["whole"][1] >= 1 and second["whole"][1] >= 1
    assert first["same"] and second["same"]
    np.testing.assert_array_equal(
        np.load(tmp_path / "first.npy"), np.load(tmp_path / "second.npy")
    )


# `executables.compile_later`: a `simulate_batch` call's specialized program compiled
# by a worker process (the first process waits for it, or exits at once), loaded by
# the next from the entry it wrote.
_LATER = """
import json, os, sys
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import lagrax
from lagrax._cache import executables
from lagrax._trajectory import batch

mode, out = sys.argv[1], sys.argv[2]
seen = []
real = batch.cached_call
batch.cached_call = lambda *a, **kw: seen.append((a, kw)) or real(*a, **kw)
executables._usable_cores = lambda: 2

def L(q, qdot, t):
    return 0.5 * jnp.sum(qdot**2) - 0.5 * jnp.sum(q**2) - 0.1 * jnp.sum(q**4)

q0 = jnp.linspace(-1.0, 1.0, 12).reshape(6, 2)
sol = lagrax.simulate_batch(
    L, q0, jnp.zeros_like(q0), 0.0, 3.0, solver=lagrax.Taylor(order=8),
    rtol=1e-12, atol=1e-12,
)
np.save(out, np.asarray(sol.ys[0]))
if mode != "load":
    ((jitted, options, cfg, shape, *rest), kw) = seen[0]
    os.environ["LAGRAX_CACHE_DIR"] = sys.argv[3]
    plain = batch._plain(cfg, shape, *kw["origin"][1:])
    executables.compile_later(plain, jitted, options, cfg, shape, *rest, **kw)
    ((job),) = executables._LATER.values()
    if mode == "exit":
        while job.worker is None:
            job.thread.join(0.01)
        print(json.dumps(dict(worker=job.worker.pid)))
        sys.exit(0)
    job.thread.join(300)
    print(json.dumps(dict(state=job.state, stats=dict(executables.STATS))))
else:
    print(json.dumps(dict(stats=dict(executables.STATS))))
"""


def _later(tmp_path, mode, cache):
    env = dict(os.environ, PYTHONFAULTHANDLER="1", LAGRAX_BACKGROUND="1")
    env["LAGRAX_CACHE_DIR"] = str(cache) if mode == "load" else ""
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    proc = subprocess.run(
        [sys.executable, "-c", _LATER, mode, str(tmp_path / f"{mode}.npy"), str(cache)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, f"{mode}:\n{proc.stderr[-4000:]}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_program_compiled_later_runs_twice_on_one_cache(tmp_path):
    cache = tmp_path / "cache"
    first = _later(tmp_path, "wait", cache)
    assert first == {"state": "done", "stats": {"written": 1, "compiled later": 1}}
    second = _later(tmp_path, "load", cache)
    assert second["stats"] == {"loaded": 1}, second
    np.testing.assert_array_equal(
        np.load(tmp_path / "wait.npy"), np.load(tmp_path / "load.npy")
    )


def test_a_process_that_exits_stops_its_compile_later(tmp_path):
    """A process that exits while its worker compiles exits cleanly, and takes its
    worker with it."""
    import time

    pid = _later(tmp_path, "exit", tmp_path / "cache")["worker"]
    for _ in range(100):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail(f"the worker {pid} outlived its process")
    assert not (tmp_path / "cache").exists() or not any(
        p.suffix == ".bin" for p in (tmp_path / "cache").iterdir()
    )
