"""Time to first result: a fresh process, lagrax beside heyoka.py, one pinned core.

What a user meets before any steady state: the import, the trace, the XLA compile and
the run of a first call. Every measurement runs in its own fresh process pinned to
one core (`taskset`), with no persistent JAX compile cache (the variables that would
enable one are removed from the workers' environment), float64:

- the pendulum period sweep (`sweep_periods`, defaults: "matched", Taylor, the error
  estimate, rtol = atol = 1e-13) of 10^3 … 10^6 amplitudes 0.01–3.1 rad: import of
  jax + lagrax, the first call (split by `jax.monitoring` into the lowering to MLIR,
  XLA's backend compile, and the rest: tracing, Python, the run), the second call
  (the steady state), and the max relative error against the exact period; beside it
  heyoka.py: import, building the integrator with its event, and the run (its
  scalar integrator with a terminal event in a Python loop, the script a user
  writes, tol = eps). The break-even size is where lagrax's whole script (import +
  first call) takes as long as heyoka.py's, from the fixed costs and steady rates.
- a rebuilt Lagrangian: `pendulum.lagrangian(g=2.0)`, a new closure with the same
  body and a new parameter value, swept after the first one in the same process.
- the first `jax.grad` of the mean period of a 1000-amplitude sweep (w.r.t. q0).
- the first `simulate` of a double pendulum (from particle positions, 256 releases
  from rest, θ1, θ2 ∈ [−1, 1], t = 10, Dopri8 at rtol = atol = 1e-12) under
  `jax.jit(jax.vmap(...))`, beside heyoka.py's build of the same system (its
  `lagrangian()`, batch mode, tol 1e-12) and its run.
- the CLI's default job (`python -m lagrax sweep --quiet`) from an empty cache.
- a script run again: the sweep of 4096 amplitudes in three processes sharing the
  library's disk cache of executables (empty, then filled; the third with another
  g); `simulate_batch` of 256 double pendulums (Taylor-16, t = 10) likewise, the
  first process also with a rebuilt `L` (another g). Every other measurement runs
  with that cache off (`LAGRAX_CACHE_DIR=""`),
  except the CLI's, which runs with an empty home (its own caches empty).
- an eager `simulate` (no `jit`) of the pendulum (q0 = 1) and of the double pendulum
  (q0 = (1, -0.5)), from rest to t = 10 at rtol = atol = 1e-10, with Tsit5, Dopri8
  and `Taylor()`, saved at t = 10 (and with Tsit5 also at 101 times,
  `SaveAt(ts=jnp.linspace(0, 10, 101))`): the first call, a rebuilt `L` (another
  g) in the same process, and a later process (a third g) sharing the first one's
  disk cache of executables (empty at the start).
- the tiers (`--only tier` alone): a new Lagrangian (a new g each) in fresh
  processes sharing the library's disk cache: its compact programs compiled once
  (`LAGRAX_COMPACT=2`, the cache empty: "once per machine"), then with the
  defaults on that machine (the compact tier: its tapes, the executable's load,
  the run), its steady state beside the specialized program's and the two
  compared; the first `jax.grad` of a 1000-amplitude sweep likewise; the first
  `lagrax.period` of a new `L` in a process and in a later one; sweeps of 2000
  then 2001 amplitudes in one process (one size class).

    python benchmarks/first_result.py [--quick] [--core 1] [--only eager|tier|chains]

`--quick`: 10^3 and 4096 amplitudes only, the gradient of 64, no CLI run, the eager
`simulate` rows with Tsit5 only. `--only eager`: the eager `simulate` rows alone.
Writes `benchmarks/results/first_result.json` (or `first_result_quick.json`,
`first_result_eager.json`, `first_result_tier.json`, `first_result_chains.json`).
`--only jit [--against CHECKOUT]`: `jit_rows` (the plain `jit(vmap(simulate(...,
solver=Taylor())))`), another checkout's lagrax alternated; `first_result_jit.json`.
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time


T_START = time.perf_counter()
HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")
# The environment variables through which a persistent JAX compile cache could be
# enabled, removed from the workers' environment.
_CACHE_VARS = (
    "LAGRAX_COMPACT",
    "JAX_COMPILATION_CACHE_DIR",
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
    "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES",
)


def _amplitudes(n):
    import numpy as np

    return np.linspace(0.01, 3.1, n)


def _exact(a, g=1.0):
    """The pendulum's exact period, 2π sqrt(1/g) / AGM(1, cos(θ0/2)), in NumPy (no
    import of jax in heyoka.py's process)."""
    import numpy as np

    x, y = np.ones_like(a), np.cos(np.asarray(a) / 2)
    for _ in range(12):
        x, y = 0.5 * (x + y), np.sqrt(x * y)
    return 2 * np.pi / np.sqrt(g) / (0.5 * (x + y))


def _max_error(T, exact):
    import numpy as np

    T = np.asarray(T)
    ok = np.isfinite(T)
    err = float(np.max(np.abs(T[ok] / exact[ok] - 1))) if ok.any() else None
    return err, int((~ok).sum())


# ------------------------------------------------------------------------ workers


def _clock():
    """Wall and process CPU time (on a shared machine the CPU time is the steadier
    figure: a pinned worker also waits for its core)."""
    return time.perf_counter(), time.process_time()


def _since(start, name):
    """`{name}_s`, `{name}_cpu_s`: the wall and CPU seconds since `start`."""
    w, c = _clock()
    return {f"{name}_s": w - start[0], f"{name}_cpu_s": c - start[1]}


def _jax_import():
    """Imports jax and lagrax (timed from the start of the process), float64 on, and
    a listener summing `jax.monitoring`'s compile-stage durations."""
    import collections

    import jax

    jax.config.update("jax_enable_x64", True)
    import lagrax

    row = _since((T_START, 0.0), "import")
    stages = collections.defaultdict(float)

    def listen(event, seconds, **kw):
        stages[event] += seconds

    jax.monitoring.register_event_duration_secs_listener(listen)
    return jax, lagrax, row, stages


def _timed(jax, fn, name, stages=None):
    """`fn()` and its times; with `stages`, also the lowering and XLA's backend
    compile inside it (from `jax.monitoring`)."""
    if stages is not None:
        stages.clear()
    start = _clock()
    out = jax.block_until_ready(fn())
    row = _since(start, name)
    if stages is not None:
        lower = stages.get("/jax/core/compile/jaxpr_to_mlir_module_duration", 0.0)
        backend = stages.get("/jax/core/compile/backend_compile_duration", 0.0)
        row[f"{name}_lower_s"] = lower
        row[f"{name}_compile_s"] = backend
        row[f"{name}_other_s"] = row[f"{name}_s"] - lower - backend
    return out, row


def work_sweep(args):
    jax, lagrax, row, stages = _jax_import()
    from lagrax.systems import pendulum

    a = _amplitudes(args.n)
    q0 = jax.numpy.asarray(a)
    g = {} if args.g is None else dict(g=args.g)
    L = pendulum.lagrangian(**g)
    r, times = _timed(jax, lambda: lagrax.sweep_periods(L, q0), "first", stages)
    row.update(times)
    r, times = _timed(jax, lambda: lagrax.sweep_periods(L, q0), "steady")
    row.update(times)
    err, failed = _max_error(r.periods, _exact(a, **g))
    row.update(n=args.n, max_rel_error=err, failed=failed)
    if args.rebuilt:
        L2 = pendulum.lagrangian(g=2.0)
        r2, times = _timed(jax, lambda: lagrax.sweep_periods(L2, q0), "rebuilt", stages)
        err2, failed2 = _max_error(r2.periods, _exact(a, g=2.0))
        row.update(times, rebuilt_max_rel_error=err2, rebuilt_failed=failed2)
    return row


def _tier_timers(jax):
    """Timers of the compact tier's parts in this process: the tapes' building,
    the executables' loads, and the compact calls (load or compile, and run)."""
    from jax.experimental import serialize_executable

    from lagrax._period import tier

    spent = dict(tapes_s=0.0, load_s=0.0, compact_s=0.0)

    def timed(fn, name):
        def wrapped(*a, **kw):
            start = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                spent[name] += time.perf_counter() - start

        return wrapped

    tier._build = timed(tier._build, "tapes_s")
    serialize_executable.deserialize_and_load = timed(
        serialize_executable.deserialize_and_load, "load_s"
    )
    run = tier.Compact.run

    def ran(self, kind, specialized):
        # The compact call's time, its compile included where it compiles (the
        # tier does not record that one); none where the specialized program ran.
        took = []

        def spec():
            took.append(True)
            return specialized()

        start = time.perf_counter()
        out = run(self, kind, spec)
        if not took:
            spent["compact_s"] += time.perf_counter() - start
        return out

    tier.Compact.run = ran
    return spent


def work_tier(args):
    """A new Lagrangian's first sweep as the tiers take it (`LAGRAX_COMPACT`, the
    disk cache of the environment), then its steady state; with `--repeat` also
    the specialized program's in the same process, and the two compared."""
    jax, lagrax, row, stages = _jax_import()
    import numpy as np

    from lagrax._cache import executables

    spent = _tier_timers(jax)
    from lagrax.systems import pendulum

    a = _amplitudes(args.n)
    q0 = jax.numpy.asarray(a)
    g = 1.3 if args.g is None else args.g
    L = pendulum.lagrangian(g=g)
    r, times = _timed(jax, lambda: lagrax.sweep_periods(L, q0), "first", stages)
    row.update(times, **{f"first_{k}": v for k, v in spent.items()})
    row["first_tier"] = "compact" if spent["compact_s"] else "specialized"
    row.update(stats=dict(executables.STATS))
    err, failed = _max_error(r.periods, _exact(a, g=g))
    row.update(n=args.n, max_rel_error=err, failed=failed)
    _, times = _timed(jax, lambda: lagrax.sweep_periods(L, q0), "steady")
    row.update(times)
    if args.repeat:
        os.environ["LAGRAX_COMPACT"] = "0"
        r2, times = _timed(jax, lambda: lagrax.sweep_periods(L, q0), "spec_first")
        row.update(times)
        r2, times = _timed(jax, lambda: lagrax.sweep_periods(L, q0), "spec_steady")
        row.update(times)
        ok = np.asarray(r2.ok)
        diff = np.abs(np.asarray(r.periods) / np.asarray(r2.periods) - 1)
        ratio = np.asarray(r.error_estimate)[ok] / np.asarray(r2.error_estimate)[ok]
        row.update(
            compact_vs_specialized=float(np.nanmax(diff)),
            same_status=bool((np.asarray(r.status) == np.asarray(r2.status)).all()),
            estimate_ratio=[float(ratio.min()), float(ratio.max())],
        )
    return row


def work_sizes(args):
    """A sweep of `n` amplitudes, then of `n + 1` (one size class) in one process."""
    jax, lagrax, row, stages = _jax_import()
    from lagrax.systems import pendulum

    L = pendulum.lagrangian()
    for name, n in (("first", args.n), ("plus_one", args.n + 1)):
        q0 = jax.numpy.asarray(_amplitudes(n))
        r, times = _timed(jax, lambda: lagrax.sweep_periods(L, q0), name, stages)
        err, failed = _max_error(r.periods, _exact(_amplitudes(n)))
        row.update(times, **{f"{name}_max_rel_error": err, f"{name}_failed": failed})
    return row


def work_period(args):
    """`lagrax.period` (one amplitude, its defaults) of a new Lagrangian."""
    jax, lagrax, row, stages = _jax_import()
    from lagrax.systems import pendulum

    g = 1.0 if args.g is None else args.g
    L = pendulum.lagrangian(g=g)
    T, times = _timed(jax, lambda: lagrax.period(L, 1.0), "first", stages)
    row.update(times, rel_error=float(T / _exact([1.0], g=g)[0] - 1))
    return row


def work_grad(args):
    jax, lagrax, row, stages = _jax_import()
    from lagrax.systems import pendulum

    spent = _tier_timers(jax)
    q0 = jax.numpy.asarray(_amplitudes(args.n))
    g = 1.0 if args.g is None else args.g
    L = pendulum.lagrangian(g=g)
    mean_period = lambda q: lagrax.sweep_periods(L, q).periods.mean()
    d, times = _timed(jax, lambda: jax.grad(mean_period)(q0), "first", stages)
    row.update(times, **{f"first_{k}": v for k, v in spent.items()})
    row["first_tier"] = "compact" if spent["compact_s"] else "specialized"
    if args.repeat:
        d, times = _timed(jax, lambda: jax.grad(mean_period)(q0), "second", stages)
        row.update(times)
    # dT/dq0 of the mean, against the derivative of the exact period.
    exact = jax.grad(lambda q: pendulum.period(q, g=g).mean())(q0)
    rel = float(jax.numpy.max(jax.numpy.abs(d / exact - 1)))
    row.update(n=args.n, max_rel_error=rel)
    return row


def _releases(n):
    import numpy as np

    rng = np.random.default_rng(0)
    return rng.uniform(-1.0, 1.0, (n, 2))


def work_simulate(args):
    jax, lagrax, row, stages = _jax_import()
    import diffrax as dfx
    import jax.numpy as jnp

    from lagrax.systems import double_pendulum

    L = double_pendulum.lagrangian()

    def one(q0):
        sol = lagrax.simulate(
            L,
            q0,
            jnp.zeros(2),
            0.0,
            10.0,
            solver=dfx.Dopri8(),
            rtol=1e-12,
            atol=1e-12,
            saveat=dfx.SaveAt(t1=True),
            throw=False,
        )
        return sol.ys[0][-1]

    q0 = jnp.asarray(_releases(args.n))
    # (`--elemental`: the compile option simulate's docstring suggests on a CPU.)
    options = {"xla_cpu_use_fusion_emitters": False} if args.elemental else None
    f = jax.jit(jax.vmap(one), compiler_options=options)
    out, times = _timed(jax, lambda: f(q0), "first", stages)
    row.update(times)
    out, times = _timed(jax, lambda: f(q0), "steady")
    row.update(times, n=args.n)
    return row


def work_eager(args):
    """An eager `simulate` (Tsit5, Dopri8 or Taylor; pendulum or double pendulum):
    the first call and, with `--rebuilt`, the same body with another g."""
    jax, lagrax, row, stages = _jax_import()
    import diffrax as dfx
    import jax.numpy as jnp
    import numpy as np

    from lagrax import systems

    system = getattr(systems, args.system)
    solver = dict(tsit5=dfx.Tsit5, dopri8=dfx.Dopri8, taylor=lagrax.Taylor)
    solver = solver[args.solver]()
    q0 = jnp.asarray([1.0, -0.5][: 1 if args.system == "pendulum" else 2])

    saveat = dfx.SaveAt(ts=jnp.linspace(0.0, 10.0, args.ts)) if args.ts else None

    def run(g):
        sol = lagrax.simulate(
            system.lagrangian(g=g),
            q0,
            jnp.zeros_like(q0),
            0.0,
            10.0,
            solver=solver,
            saveat=saveat,
            rtol=1e-10,
            atol=1e-10,
        )
        return sol.ys[0][-1]

    g = 1.0 if args.g is None else args.g
    out, times = _timed(jax, lambda: run(g), "first", stages)
    row.update(times, q_end=np.asarray(out).tolist())
    if args.rebuilt:
        other, times = _timed(jax, lambda: run(g + 1.0), "rebuilt", stages)
        row.update(times, rebuilt_differs=bool(not np.allclose(other, out)))
    return row


def work_batch(args):
    """`simulate_batch` of `n` double pendulums (Taylor-16, t = 10): the first call,
    a steady one, and with `--rebuilt` the same body with another g."""
    jax, lagrax, row, stages = _jax_import()
    import diffrax as dfx
    import jax.numpy as jnp
    import numpy as np

    from lagrax.systems import double_pendulum

    q0 = jnp.asarray(_releases(args.n))

    def run(g):
        sol = lagrax.simulate_batch(
            double_pendulum.lagrangian(g=g),
            q0,
            jnp.zeros_like(q0),
            0.0,
            10.0,
            solver=solver,
            rtol=3e-11,
            atol=3e-11,
            throw=False,
        )
        return sol.ys[0][:, -1]

    # (`--batch-solver tsit5` or `dopri8`: `simulate_batch`'s vmap of `simulate`.)
    solver = dict(taylor=lambda: lagrax.Taylor(order=16), tsit5=dfx.Tsit5)
    solver = dict(solver, dopri8=dfx.Dopri8)[args.batch_solver]()
    g = 1.0 if args.g is None else args.g
    out, times = _timed(jax, lambda: run(g), "first", stages)
    row.update(times)
    out, times = _timed(jax, lambda: run(g), "steady")
    row.update(
        times, n=args.n, failed=int((~np.isfinite(np.asarray(out))).any(1).sum())
    )
    if args.rebuilt:
        other, times = _timed(jax, lambda: run(g + 1.0), "rebuilt", stages)
        row.update(times, rebuilt_differs=bool(not np.allclose(other, out)))
    return row


def work_heyoka(args):
    import heyoka as hy
    import numpy as np

    row = _since((T_START, 0.0), "import")
    if args.system == "pendulum":
        a = _amplitudes(args.n)
        start = _clock()
        x, v = hy.make_vars("x", "v")
        system = hy.lagrangian(0.5 * v**2 + hy.cos(x), [x], [v])
        ev = hy.t_event(x, direction=hy.event_direction.negative)
        ta = hy.taylor_adaptive(system, [1.0, 0.0], t_events=[ev])
        row.update(_since(start, "build"))
        start = _clock()
        T = np.empty_like(a)
        for i, a0 in enumerate(a):
            ta.time = 0.0
            ta.state[:] = (a0, 0.0)
            ta.propagate_until(1e3)
            T[i] = 4 * ta.time
        row.update(_since(start, "run"))
        err, failed = _max_error(T, _exact(a))
        row.update(n=args.n, max_rel_error=err, failed=failed)
        return row
    # The double pendulum from particle positions (unit masses and rods, g = 1).
    start = _clock()
    x1, x2, v1, v2 = hy.make_vars("x1", "x2", "v1", "v2")
    vx1, vy1 = hy.cos(x1) * v1, hy.sin(x1) * v1
    vx2, vy2 = vx1 + hy.cos(x2) * v2, vy1 + hy.sin(x2) * v2
    y1 = -hy.cos(x1)
    y2 = y1 - hy.cos(x2)
    Lh = 0.5 * (vx1**2 + vy1**2) + 0.5 * (vx2**2 + vy2**2) - (y1 + y2)
    system = hy.lagrangian(Lh, [x1, x2], [v1, v2])
    B = hy.recommended_simd_size()
    ta = hy.taylor_adaptive_batch(system, np.zeros((4, B)), tol=1e-12)
    row.update(_since(start, "build"))
    q0 = _releases(args.n)
    start = _clock()
    for i in range(0, args.n, B):
        k = min(B, args.n - i)
        ta.set_time(0.0)
        ta.state[:2, :] = np.resize(q0[i : i + k].T, (2, B))
        ta.state[2:, :] = 0.0
        ta.propagate_until(10.0)
    row.update(_since(start, "run"), n=args.n, simd=B)
    return row


def _chain(n, hy=False):
    """A chain of n unit pendulums from particle positions (as trajectories.py);
    heyoka.py's `lagrangian()` of the same T - V with `hy`."""
    if hy:
        import heyoka as h

        qs = list(h.make_vars(*[f"q{i}" for i in range(n)]))
        ws = list(h.make_vars(*[f"w{i}" for i in range(n)]))
        y = vx = vy = 0.0
        T = V = 0.0
        for q, w in zip(qs, ws):
            y, vx, vy = y - h.cos(q), vx + h.cos(q) * w, vy + h.sin(q) * w
            T, V = T + 0.5 * (vx**2 + vy**2), V + 9.81 * y
        return h.lagrangian(T - V, qs, ws)
    import jax.numpy as jnp

    import lagrax

    def positions(q, t):
        return jnp.stack([jnp.cumsum(jnp.sin(q)), -jnp.cumsum(jnp.cos(q))], axis=1)

    return lagrax.particle_lagrangian(
        jnp.ones(n), positions, lambda r, t: 9.81 * jnp.sum(r[:, 1])
    )


def _chain_releases(n, count=256):
    import numpy as np

    q0 = np.random.default_rng(0).uniform(-0.5, 0.5, (count, n))
    return q0, np.zeros_like(q0)


def _chain_error(ys, path):
    import numpy as np

    if not path:
        return None
    return float(np.max(np.abs(np.asarray(ys) - np.load(path))))


def work_chain(args):
    """`simulate_batch` of a chain (`--n` links, 256 releases, t = 10, Taylor-16
    at rtol = atol = `--tol`), `LAGRAX_COMPACT` choosing the tier: import, the
    first call, then the best of three (wall and CPU seconds)."""
    jax, lagrax, row, _ = _jax_import()
    import_s = row["import_s"]
    L = _chain(args.links)
    q0, v0 = _chain_releases(args.links)
    run = lambda: lagrax.simulate_batch(
        L, q0, v0, 0.0, 10.0, solver=lagrax.Taylor(order=16), rtol=args.tol,
        atol=args.tol, max_steps=1 << 16,
    )  # fmt: skip
    (sol, first, first_cpu), times = _clocked(lambda: jax.block_until_ready(run()))
    best, best_cpu = (min(x) for x in zip(*times))
    import numpy as np

    ys = np.concatenate([np.asarray(sol.ys[0][:, -1]), np.asarray(sol.ys[1][:, -1])], 1)
    return dict(
        links=args.links, tol=args.tol, import_s=import_s, first_s=first,
        first_cpu_s=first_cpu, steady_s=best, steady_cpu_s=best_cpu,
        steps=float(np.mean(np.asarray(sol.stats["num_steps"]))),
        max_error=_chain_error(ys, args.reference),
    )  # fmt: skip


def _clocked(fn, repeats=3):
    """`(out, wall, cpu)` of a first call of `fn`, then `repeats` more calls'
    `(wall, cpu)` seconds."""
    start, cpu = time.perf_counter(), time.process_time()
    out = fn()
    first = (out, time.perf_counter() - start, time.process_time() - cpu)
    times = []
    for _ in range(repeats):
        start, cpu = time.perf_counter(), time.process_time()
        fn()
        times.append((time.perf_counter() - start, time.process_time() - cpu))
    return first, times


def work_chain_heyoka(args):
    """heyoka.py's `taylor_adaptive_batch` (SIMD width, `--tol`, compact mode with
    `--compact`) on the same releases, its code caches off: import, build, the
    first run and the best of three."""
    t0 = time.perf_counter()
    import heyoka as hy
    import numpy as np

    import_s = time.perf_counter() - t0
    hy.llvm_state.set_diskcache_enabled(False)
    n = args.links
    q0, v0 = _chain_releases(n)
    y0 = np.concatenate([q0, v0], 1)
    B = hy.recommended_simd_size()
    t, cpu = time.perf_counter(), time.process_time()
    tb = hy.taylor_adaptive_batch(
        _chain(n, hy=True), np.zeros((2 * n, B)), tol=args.tol,
        compact_mode=args.compact,
    )  # fmt: skip
    build, build_cpu = time.perf_counter() - t, time.process_time() - cpu

    def run():
        out = np.empty_like(y0)
        for i in range(0, len(y0), B):
            idx = np.resize(np.arange(i, min(i + B, len(y0))), B)
            tb.set_time(0.0)
            tb.state[:] = y0[idx].T
            tb.propagate_until(10.0)
            out[i : i + B] = tb.state.T[: min(B, len(y0) - i)]
        return out

    (ys, first, first_cpu), times = _clocked(run)
    best, best_cpu = (min(x) for x in zip(*times))
    if args.save:
        np.save(args.save, ys)
    return dict(
        links=n, tol=args.tol, compact=args.compact, import_s=import_s,
        build_s=build, build_cpu_s=build_cpu, first_run_s=first,
        first_run_cpu_s=first_cpu, steady_s=best, steady_cpu_s=best_cpu,
        order=tb.order, max_error=_chain_error(ys, args.reference),
    )  # fmt: skip


def _jit_system(name, n):
    """`(L, q0, qdot0)` of `--only jit`: the double pendulum (releases from rest,
    θ1, θ2 ∈ [−1, 1]) or a chain of 3 links (`chain3`, releases in ±0.5 rad)."""
    import numpy as np

    if name == "double_pendulum":
        from lagrax.systems import double_pendulum

        q0 = _releases(n)
        return double_pendulum.lagrangian(), q0, np.zeros_like(q0)
    links = int(name.removeprefix("chain"))
    return (_chain(links), *_chain_releases(links, n))


def work_jit(args):
    """The plain idiom `jax.jit(jax.vmap(lambda q0: simulate(L, q0, ...,
    solver=lagrax.Taylor())))`, no compiler options, t = 10, rtol = atol = `--tol`:
    the first call split into tracing, lowering to MLIR, XLA's compile and the
    run (wall and CPU seconds), then the best of three calls; the end states'
    largest error against Dopri8 at rtol = atol = 1e-14 (compiled after, with
    XLA's elemental emitters)."""
    jax, lagrax, row, _ = _jax_import()
    import diffrax as dfx
    import jax.numpy as jnp
    import numpy as np

    L, q0, v0 = _jit_system(args.system, args.n)
    solver = lagrax.Taylor(order=args.order or None)

    def solve(q0, v0, solver, tol, max_steps):
        sol = lagrax.simulate(
            L, q0, v0, 0.0, 10.0, solver=solver, rtol=tol, atol=tol,
            max_steps=max_steps, throw=False,
        )  # fmt: skip
        ok = sol.result == dfx.RESULTS.successful
        return sol.ys[0][-1], sol.ys[1][-1], sol.stats["num_steps"], ok

    f = jax.jit(jax.vmap(lambda q, v: solve(q, v, solver, args.tol, 16384)))
    q0, v0 = jnp.asarray(q0), jnp.asarray(v0)
    # (The first call's stages one by one, through jit's ahead-of-time methods:
    # the work `f(q0, v0)` does on its first call.)
    start = _clock()
    traced = f.trace(q0, v0)
    row.update(_since(start, "trace"))
    step = _clock()
    lowered = traced.lower()
    row.update(_since(step, "lower"))
    step = _clock()
    compiled = lowered.compile()
    row.update(_since(step, "compile"))
    step = _clock()
    out = jax.block_until_ready(compiled(q0, v0))
    row.update(_since(step, "run"), **_since(start, "first"))
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        out = jax.block_until_ready(compiled(q0, v0))
        best = min(best, time.perf_counter() - t)
    ref = jax.jit(
        jax.vmap(lambda q, v: solve(q, v, dfx.Dopri8(), 1e-14, 1 << 18)),
        compiler_options={"xla_cpu_use_fusion_emitters": False},
    )(q0, v0)
    ys = np.concatenate([np.asarray(out[0]), np.asarray(out[1])], 1)
    ys_ref = np.concatenate([np.asarray(ref[0]), np.asarray(ref[1])], 1)
    ok = np.asarray(out[3])
    return dict(
        row, system=args.system, tol=args.tol, n=args.n, order=solver.order,
        steady_s=best, steps=float(np.mean(np.asarray(out[2]))),
        failed=int((~ok).sum()), reference_failed=int((~np.asarray(ref[3])).sum()),
        max_error=float(np.max(np.abs(ys[ok] - ys_ref[ok]))) if ok.any() else None,
    )  # fmt: skip


WORKERS = dict(
    chain=work_chain,
    chain_heyoka=work_chain_heyoka,
    sweep=work_sweep,
    tier=work_tier,
    sizes=work_sizes,
    period=work_period,
    grad=work_grad,
    simulate=work_simulate,
    batch=work_batch,
    eager=work_eager,
    heyoka=work_heyoka,
    jit=work_jit,
)


# ------------------------------------------------------------------------ driver


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if k not in _CACHE_VARS}
    # Cold: the library's disk cache of executables off unless a row asks for one.
    env["LAGRAX_CACHE_DIR"] = ""
    env.update(extra)
    repo = os.path.dirname(HERE)
    env["PYTHONPATH"] = repo + os.pathsep + env.get("PYTHONPATH", "")
    return env


def spawn(core, kind, env=None, **kw):
    cmd = ["taskset", "-c", str(core), sys.executable, __file__, "--worker", kind]
    for k, v in kw.items():
        if v is True:
            cmd += [f"--{k}"]
        elif v is not False:
            cmd += [f"--{k}", str(v)]
    t = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=_env(**(env or {})))
    wall = time.perf_counter() - t
    if out.returncode != 0:
        print(out.stderr[-3000:], file=sys.stderr)
        return None
    row = json.loads(out.stdout.strip().splitlines()[-1])
    row["process_s"] = wall
    return row


def cli_default_job(core):
    """`python -m lagrax sweep --quiet` with an empty cache directory, pinned."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(_env(), XDG_CACHE_HOME=cache)
        del env["LAGRAX_CACHE_DIR"]  # (the command's own caches, in the empty home)
        cmd = ["taskset", "-c", str(core), sys.executable, "-m", "lagrax", "sweep"]
        t = time.perf_counter()
        out = subprocess.run(cmd + ["--quiet"], capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t
    if out.returncode != 0:
        print(out.stderr[-3000:], file=sys.stderr)
        return None
    return dict(process_s=wall)


def break_even(lx, hy, cpu=""):
    """The sweep size at which lagrax's whole script (import + first call) takes as
    long as heyoka.py's (import + build + run), from the fixed costs and steady
    per-amplitude times of the largest size measured (`cpu="_cpu"`: from the CPU
    times instead of the wall times)."""
    per_l = lx[f"steady{cpu}_s"] / lx["n"]
    per_h = hy[f"run{cpu}_s"] / hy["n"]
    fixed_l = lx[f"import{cpu}_s"] + lx[f"first{cpu}_s"] - lx[f"steady{cpu}_s"]
    fixed_h = hy[f"import{cpu}_s"] + hy[f"build{cpu}_s"]
    if per_h <= per_l:
        return None  # never
    return max(0.0, (fixed_l - fixed_h) / (per_h - per_l))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--quick", action="store_true")
    p.add_argument("--core", type=int, default=1, help="the core to pin workers to")
    p.add_argument("--worker")
    p.add_argument("--n", type=int, default=4096)
    p.add_argument("--rebuilt", action="store_true")
    p.add_argument("--g", type=float, default=None, help="sweep: the pendulum's g")
    p.add_argument("--repeat", action="store_true", help="grad: a second call too")
    p.add_argument("--system", default="pendulum")
    p.add_argument("--solver", default="tsit5", help="eager: tsit5, dopri8, taylor")
    p.add_argument("--ts", type=int, default=0, help="eager: save at n times")
    only = ("all", "eager", "tier", "chains", "jit")
    p.add_argument("--only", choices=only, default="all")
    p.add_argument(
        "--elemental", action="store_true", help="simulate: XLA's elemental emitters"
    )
    p.add_argument(
        "--batch-solver", default="taylor", help="batch: taylor, tsit5, dopri8"
    )
    p.add_argument("--links", type=int, default=4, help="chain: its links")
    p.add_argument("--order", type=int, default=0, help="jit: Taylor's (0: None)")
    p.add_argument("--against", default="", help="--only jit: another checkout")
    p.add_argument("--tol", type=float, default=1e-12, help="chain: the tolerance")
    p.add_argument("--compact", action="store_true", help="chain_heyoka: compact")
    p.add_argument("--reference", default="", help="chain: the reference states")
    p.add_argument("--save", default="", help="chain_heyoka: save the end states")
    p.add_argument(
        "--chains", type=int, nargs="+", default=[4, 6, 8],
        help="--only chains: the links of each chain",
    )  # fmt: skip
    args = p.parse_args()
    if args.worker:
        print(json.dumps(WORKERS[args.worker](args)))
        return
    if args.only == "eager":
        out = dict(eager=eager_rows(args.core, quick=args.quick))
        _write_results(args, out, "first_result_eager.json")
        return
    if args.only == "tier":
        _write_results(args, tier_rows(args.core), "first_result_tier.json")
        return
    if args.only == "jit":
        _write_results(args, jit_rows(args.core, args.against), "first_result_jit.json")
        return
    if args.only == "chains":
        out = chain_rows(args.core, args.chains)
        _write_results(args, out, "first_result_chains.json")
        return
    sizes = [1000, 4096] if args.quick else [1000, 4096, 10_000, 100_000, 1_000_000]
    c = args.core
    out = dict(sweep=[], heyoka=[])
    for n in sizes:
        hy = spawn(c, "heyoka", n=n)
        lx = spawn(c, "sweep", n=n, rebuilt=(n == 4096))
        out["heyoka"].append(hy)
        out["sweep"].append(lx)
        print(f"n={n:8d}  lagrax {json.dumps(lx)}\n{'':11s} heyoka {json.dumps(hy)}")
    last = out["sweep"][-1], out["heyoka"][-1]
    out["break_even_amplitudes"] = break_even(*last)
    out["break_even_amplitudes_cpu"] = break_even(*last, cpu="_cpu")
    out["grad"] = spawn(c, "grad", n=64 if args.quick else 1000)
    print("grad", json.dumps(out["grad"]))
    out["simulate"] = spawn(c, "simulate", n=256)
    out["simulate_heyoka"] = spawn(c, "heyoka", n=256, system="double_pendulum")
    print("simulate", json.dumps(out["simulate"]))
    print("heyoka double pendulum", json.dumps(out["simulate_heyoka"]))
    # A script run again: the library's disk cache empty, then filled by the first
    # run; then the same body with another g in a third process.
    with tempfile.TemporaryDirectory() as cache:
        env = dict(LAGRAX_CACHE_DIR=cache)
        out["rerun"] = [
            spawn(c, "sweep", env=env, n=4096),
            spawn(c, "sweep", env=env, n=4096),
            spawn(c, "sweep", env=env, n=4096, g=2.0),
        ]
    for name, row in zip(("empty", "filled", "filled, new g"), out["rerun"]):
        print(f"rerun, cache {name}", json.dumps(row))
    # `simulate_batch` of 256 double pendulums likewise, with a rebuilt L (another
    # g) in the first process.
    with tempfile.TemporaryDirectory() as cache:
        env = dict(LAGRAX_CACHE_DIR=cache)
        out["batch_rerun"] = [
            spawn(c, "batch", env=env, n=256, rebuilt=True),
            spawn(c, "batch", env=env, n=256),
            spawn(c, "batch", env=env, n=256, g=2.0),
        ]
    for name, row in zip(("empty", "filled", "filled, new g"), out["batch_rerun"]):
        print(f"simulate_batch, cache {name}", json.dumps(row))
    out["eager"] = eager_rows(c, quick=args.quick)
    out["tier"] = tier_rows(c)
    if not args.quick:
        out["cli"] = cli_default_job(c)
        print("cli", json.dumps(out["cli"]))
    print(
        "break-even amplitudes",
        out["break_even_amplitudes"],
        "(wall),",
        out["break_even_amplitudes_cpu"],
        "(CPU)",
    )
    name = "first_result_quick.json" if args.quick else "first_result.json"
    _write_results(args, out, name)


def eager_rows(core, quick=False):
    """Eager `simulate` per system and solver: a first process (first call, then a
    rebuilt `L`) and a later one (another g), sharing a disk cache of executables
    empty at the start."""
    rows = []
    solvers = ("tsit5",) if quick else ("tsit5", "dopri8", "taylor")
    # (Saved at t1 only, each solver; and at 101 times, `SaveAt(ts=...)`, Tsit5.)
    cases = [(solver, 0) for solver in solvers] + [("tsit5", 101)]
    for system in ("pendulum", "double_pendulum"):
        for solver, ts in cases:
            with tempfile.TemporaryDirectory() as cache:
                env = dict(LAGRAX_CACHE_DIR=cache)
                kw = dict(env=env, system=system, solver=solver, ts=ts)
                first = spawn(core, "eager", rebuilt=True, **kw)
                later = spawn(core, "eager", g=1.5, **kw)
            rows.append(
                dict(system=system, solver=solver, ts=ts, first=first, later=later)
            )
            secs = lambda row, key: "failed" if row is None else f"{row[key]:.3g} s"
            saved = f", SaveAt(ts) of {ts}" if ts else ""
            print(
                f"eager simulate, {system}, {solver}{saved}: first "
                f"{secs(first, 'first_s')}, rebuilt {secs(first, 'rebuilt_s')}, "
                f"later process {secs(later, 'first_s')}"
            )
    return rows


def tier_rows(core):
    """A new Lagrangian's first sweep, first `jax.grad` and first `lagrax.period`
    through the tiers, beside heyoka.py's script and the specialized program's
    first call; and a count one past a size class."""
    out = dict(heyoka=spawn(core, "heyoka", n=4096))
    print("heyoka.py, 4096", json.dumps(out["heyoka"]), flush=True)
    # Today's first call: the specialized program, the disk cache off.
    out["specialized"] = spawn(core, "sweep", n=4096)
    out["grad_specialized"] = spawn(core, "grad", n=1000)
    print("specialized", json.dumps(out["specialized"]), flush=True)
    print("grad, specialized", json.dumps(out["grad_specialized"]), flush=True)
    with tempfile.TemporaryDirectory() as cache:
        # Once per machine: the compact programs compiled (`LAGRAX_COMPACT=2`).
        once = dict(LAGRAX_CACHE_DIR=cache, LAGRAX_COMPACT="2")
        out["compact_cold"] = spawn(core, "tier", env=once, n=4096, g=1.3)
        out["grad_compact_cold"] = spawn(core, "grad", env=once, n=1000, g=1.3)
        print("compact, cold", json.dumps(out["compact_cold"]), flush=True)
        print("grad, compact, cold", json.dumps(out["grad_compact_cold"]), flush=True)
        # A machine that has run lagrax: the defaults, a new Lagrangian each.
        env = dict(LAGRAX_CACHE_DIR=cache)
        out["warm"] = [
            spawn(core, "tier", env=env, n=4096, g=g, repeat=(g == 1.4))
            for g in (1.4, 1.5, 1.6)
        ]
        for row in out["warm"]:
            print("compact, warm", json.dumps(row), flush=True)
        out["grad_warm"] = [
            spawn(core, "grad", env=env, n=1000, g=g) for g in (1.4, 1.5)
        ]
        for row in out["grad_warm"]:
            print("grad, warm", json.dumps(row), flush=True)
        out["executables"] = {
            name: os.path.getsize(os.path.join(cache, name))
            for name in os.listdir(cache)
            if name.endswith(".bin")
        }
    with tempfile.TemporaryDirectory() as cache:
        env = dict(LAGRAX_CACHE_DIR=cache)
        out["period"] = [spawn(core, "period", env=env, g=g) for g in (1.0, 1.3)]
    for row in out["period"]:
        print("period", json.dumps(row), flush=True)
    out["sizes"] = spawn(core, "sizes", n=2000)
    print("sizes 2000, 2001", json.dumps(out["sizes"]), flush=True)
    return out


def chain_rows(core, links, rounds=3):
    """Chains of `links` links, 256 releases, t = 10, error against heyoka.py at
    tol 1e-15: heyoka.py in compact and default mode (tol 1e-11), lagrax's
    compact tier (its disk cache empty, then filled: a machine that has run
    lagrax) and its specialized program (Taylor-16, rtol = atol = 1e-12); each a
    fresh process pinned to `core`, heyoka.py's compact mode and lagrax's filled
    cache alternated `rounds` times (a shared machine's load then weighs on both
    alike)."""
    rows = []
    for n in links:
        with tempfile.TemporaryDirectory() as folder:
            ref = os.path.join(folder, "ref.npy")
            spawn(core, "chain_heyoka", links=n, tol=1e-15, compact=True, save=ref)
            common = dict(links=n, reference=ref)
            if n <= 6:  # (heyoka.py's default build runs for minutes beyond)
                row = spawn(core, "chain_heyoka", tol=1e-11, compact=False, **common)
                rows.append(dict(name="heyoka.py batch, compact=False", **row))
                print(json.dumps(rows[-1]), flush=True)
            cache = os.path.join(folder, "cache")
            env = dict(LAGRAX_COMPACT="2", LAGRAX_CACHE_DIR=cache)
            row = spawn(core, "chain", env=env, **common)
            rows.append(
                dict(name="lagrax simulate_batch, compact tier, empty cache", **row)
            )
            print(json.dumps(rows[-1]), flush=True)
            for _ in range(rounds):
                row = spawn(core, "chain_heyoka", tol=1e-11, compact=True, **common)
                rows.append(dict(name="heyoka.py batch, compact=True", **row))
                print(json.dumps(rows[-1]), flush=True)
                row = spawn(core, "chain", env=env, **common)
                rows.append(
                    dict(
                        name="lagrax simulate_batch, compact tier, filled cache", **row
                    )
                )
                print(json.dumps(rows[-1]), flush=True)
            if n <= 4:
                env = dict(LAGRAX_COMPACT="0")
                row = spawn(core, "chain", env=env, **common)
                rows.append(dict(name="lagrax simulate_batch, specialized", **row))
                print(json.dumps(rows[-1]), flush=True)
    return dict(rows=rows)


def jit_rows(core, against=""):
    """The plain `jax.jit(jax.vmap(simulate(..., solver=lagrax.Taylor())))` of the
    double pendulum and a 3-link chain, 16 releases, at rtol = atol = 1e-10 and
    1e-13, each a fresh process pinned to `core`; with `against` (another
    checkout's root), its lagrax run alternately in the same places."""
    trees = [os.path.dirname(HERE)] + ([os.path.abspath(against)] if against else [])
    rows = []
    for system in ("double_pendulum", "chain3"):
        for tol in (1e-10, 1e-13):
            for tree in trees:
                cmd = ["taskset", "-c", str(core), sys.executable, __file__]
                cmd += ["--worker", "jit", "--system", system, "--n", "16"]
                env = dict(_env(), PYTHONPATH=tree)
                out = subprocess.run(
                    cmd + ["--tol", str(tol)], capture_output=True, text=True, env=env
                )
                if out.returncode != 0:
                    print(out.stderr[-3000:], file=sys.stderr)
                    continue
                row = json.loads(out.stdout.strip().splitlines()[-1])
                rows.append(dict(row, tree=tree))
                print(
                    f"{system} tol {tol:g} ({tree}): first {row['first_s']:.2f} s "
                    f"(CPU {row['first_cpu_s']:.2f}: trace {row['trace_cpu_s']:.2f}, "
                    f"lower {row['lower_cpu_s']:.2f}, compile "
                    f"{row['compile_cpu_s']:.2f}), order {row['order']}, steady "
                    f"{row['steady_s'] * 1e3:.1f} ms, error {row['max_error']:.2g}",
                    flush=True,
                )
    return dict(rows=rows)


def _write_results(args, out, name):
    meta = dict(
        date=time.strftime("%Y-%m-%d"),
        machine=platform.processor() or platform.machine(),
        python=platform.python_version(),
        core=args.core,
        commit=subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=HERE,
        ).stdout.strip(),
    )
    os.makedirs(RESULTS, exist_ok=True)
    with open(os.path.join(RESULTS, name), "w") as fh:
        json.dump(dict(meta=meta, **out), fh, indent=2)
    print("wrote", os.path.join(RESULTS, name))


if __name__ == "__main__":
    main()
