"""When the specialized program takes over: a job of repeated calls with a new
Lagrangian, on a machine that has run lagrax, the compile in a worker process on
an idle core against the ski rental alone.

A new Lagrangian runs on the compact tier (its program, compiled once per
machine, on disk); the program specialized to it runs several times faster but
compiles for seconds (a 1-DOF sweep) to tens of seconds (a chain). With the
defaults, where the process leaves a core idle, the second call starts that
compile in a worker process (`executables.compile_later`) and the specialized
program takes over once on disk; with `LAGRAX_BACKGROUND=0` (and on one core)
the compact tier runs until its time repays the compile, which then runs in the
call (the rental). Each job runs in a fresh process, unpinned, with a copy of a
disk cache that holds the compact programs only (filled first, `LAGRAX_COMPACT=2`),
the two modes alternated over `--rounds`. Per job: the calls' wall seconds, the
call at which the specialized program first ran and the seconds until then, the
whole job's seconds, and the median call before and after.

- `chain4`: `simulate_batch` of a chain of 4 unit pendulums (particle positions),
  256 releases in ±0.5 rad, t = 10, Taylor order 16, rtol = atol = 1e-12, a new
  gravity each job; `--calls` calls (default 40);
- `pendulum`: `sweep_periods` of 4096 amplitudes 0.01–3.1 rad at the defaults;
  `--sweeps` calls (default 150).

    python benchmarks/takeover.py [--jobs chain4 pendulum] [--rounds 2]

Run it on a quiet machine of at least two cores. Results: `results/takeover.json`.
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time


HERE = os.path.dirname(os.path.abspath(__file__))
MODES = (("idle core", {}), ("rental", {"LAGRAX_BACKGROUND": "0"}))


def _job(name, g):
    """The call of job `name` with gravity `g`, returning what to wait for."""
    import jax.numpy as jnp
    import numpy as np

    import lagrax

    if name == "pendulum":
        L = lambda q, qd, t: 0.5 * qd[0] ** 2 + g * jnp.cos(q[0])
        q0 = jnp.linspace(0.01, 3.1, 4096)
        return lambda: lagrax.sweep_periods(L, q0).periods

    def positions(q, t):
        return jnp.stack([jnp.cumsum(jnp.sin(q)), -jnp.cumsum(jnp.cos(q))], axis=1)

    L = lagrax.particle_lagrangian(
        jnp.ones(4), positions, lambda r, t: g * jnp.sum(r[:, 1])
    )
    q0 = np.random.default_rng(0).uniform(-0.5, 0.5, (256, 4))
    return lambda: lagrax.simulate_batch(
        L, q0, np.zeros_like(q0), 0.0, 10.0, solver=lagrax.Taylor(order=16),
        rtol=1e-12, atol=1e-12, max_steps=1 << 16,
    ).ys  # fmt: skip


def work(args):
    """One job in this process: `args.calls` calls, each timed, and which tier ran."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from lagrax._cache import executables
    from lagrax._trajectory import batch

    # (The specialized programs run through `cached_call`, the compact ones not.)
    ran = []
    real = executables.cached_call
    spy = lambda *a, **kw: ran.append(1) or real(*a, **kw)
    executables.cached_call = batch.cached_call = spy
    run = _job(args.job, args.g)
    times, specialized = [], []
    for _ in range(args.calls):
        ran.clear()
        start = time.perf_counter()
        jax.block_until_ready(run())
        times.append(time.perf_counter() - start)
        specialized.append(bool(ran))
    print(json.dumps(dict(times=times, specialized=specialized,
                          stats=dict(executables.STATS))))  # fmt: skip


def _spawn(job, g, calls, cache, env):
    cmd = [sys.executable, __file__, "--work", job, "--g", str(g)]
    cmd += ["--calls", str(calls)]
    env = dict(os.environ, LAGRAX_CACHE_DIR=cache, **env)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-3000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def _summary(row):
    times, spec = row["times"], row["specialized"]
    first = spec.index(True) if True in spec else None
    before = times[1:first] if first else times[1:]
    after = times[first + 1 :] if first is not None else []
    return dict(
        total_s=sum(times),
        first_call_s=times[0],
        takeover_call=first,
        takeover_s=None if first is None else sum(times[: first + 1]),
        compact_call_s=statistics.median(before) if before else None,
        specialized_call_s=statistics.median(after) if after else None,
    )


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--jobs", nargs="+", default=["chain4", "pendulum"])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--calls", type=int, default=40)
    parser.add_argument("--sweeps", type=int, default=150)
    parser.add_argument("--work")
    parser.add_argument("--g", type=float, default=9.81)
    args = parser.parse_args()
    if args.work:
        args.job = args.work
        return work(args)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        base = os.path.join(tmp, "compact")
        g = 9.0
        for job in args.jobs:
            _spawn(job, 9.81, 1, base, dict(LAGRAX_COMPACT="2"))  # (once per machine)
        for job in args.jobs:
            calls = args.sweeps if job == "pendulum" else args.calls
            for r in range(args.rounds):
                for mode, env in MODES:
                    g += 0.01
                    cache = os.path.join(tmp, f"run{len(rows)}")
                    shutil.copytree(base, cache)
                    row = dict(job=job, mode=mode, round=r, g=g, calls=calls)
                    row.update(_spawn(job, g, calls, cache, env))
                    row.update(_summary(row))
                    rows.append(row)
                    shutil.rmtree(cache)
                    print(
                        f"{job:9s} {mode:9s} round {r}: {calls} calls in "
                        f"{row['total_s']:.1f} s; first {row['first_call_s']:.2f} s; "
                        f"specialized from call {row['takeover_call']} at "
                        f"{row['takeover_s'] or float('nan'):.1f} s; a call "
                        f"{row['compact_call_s'] or float('nan'):.3f} s compact, "
                        f"{row['specialized_call_s'] or float('nan'):.3f} s after",
                        flush=True,
                    )
    sys.path.insert(0, HERE)
    out = dict(
        date=time.strftime("%Y-%m-%d"),
        commit=subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=HERE,
        ).stdout.strip(),  # fmt: skip
        cores=len(os.sched_getaffinity(0)),
        rows=rows,
    )
    with open(os.path.join(HERE, "results", "takeover.json"), "w") as fh:
        json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
