r"""Trajectories per second at a given accuracy: lagrax against heyoka.py.

Systems (float64; g = 9.81, unit masses and lengths; released from rest, integrated
from t = 0 to t = 10):

- `double_pendulum`: the double pendulum written as a plain closed-form
  $L(q, \dot q, t) = \dot\theta_1^2 + \frac12\dot\theta_2^2
  + \dot\theta_1\dot\theta_2\cos(\theta_1 - \theta_2) + 2g\cos\theta_1 + g\cos\theta_2$,
  1024 releases with $\theta_1, \theta_2$ uniform in $[-1, 1]$ rad;
- `chain2`, `chain4`, `chain6`, `chain8`: chains of n unit pendulums written from
  particle positions (cumulative sums of sines and cosines, through
  `lagrax.particle_lagrangian`; heyoka.py gets the same $T - V$ as an expression),
  256 releases within $\pm 0.5$ rad.

Error: the largest absolute error of $(q, \dot q)$ at $t = 10$ over all releases,
against heyoka.py in 80-bit long double at tol 1e-18 (cached, see `--cache`). For
each accuracy bound (1e-9 and 1e-12; 1e-9 and 1e-10 for the chains from 4 links,
which no float64 method integrates to 1e-12) every method runs at the loosest
tolerance of a half-decade grid (1 and 3 per decade) whose error stays under the
bound; trajectories/s is the best of `--repeats` calls (at least one second of calls) at
that tolerance. Compile or build time is the first call (lagrax: one `jax.jit`
compile, tolerances are arrays so the tolerance scan does not recompile; heyoka.py:
building the integrator at the chosen tolerance with its code caches off and
emptied, which it does per tolerance). Energy drift: $|E(10) - E(0)| / |E(0)|$ per
trajectory ($E = T + V$ in closed form, float64), the largest and the median.

Methods, each group in a fresh worker process:

- heyoka.py (`lagrangian()`, its own derivation of the equations): the scalar
  integrator in a Python loop; batch mode at `recommended_simd_size()` over chunks;
  on the whole machine `ensemble_propagate_until` with threads (one batch integrator
  per chunk, as its tutorial does) and plain Python threads each looping its own
  batch integrator over half the chunks.
- lagrax `simulate` under `jax.jit(jax.vmap(...))` with `diffrax.Tsit5()` (its
  default), `diffrax.Dopri8()` and `lagrax.Taylor(order=K)` (that `jit` with the
  compile option `lagrax.Taylor` asks for on a CPU), rtol = atol = tol; on the whole
  machine the batch is split over one JAX CPU device per core with `jax.shard_map`.
- `lagrax.simulate_batch` with `lagrax.Taylor(order=K)`: its own compiled loop over
  refilling lanes (one per device on the whole machine), on the tier a new `L`'s
  calls take (a chain: the compact program) and, for the chains, on the specialized
  program (`LAGRAX_COMPACT=0`).

"1 core" rows run under `taskset -c 1` (the whole worker process, both libraries);
"whole machine" rows unpinned. A work-precision chart (seconds per trajectory
against error, every tolerance of each scan) per system goes to
`results/trajectories[_quick].png`; all rows to `results/trajectories[_quick].json`
(a run over some systems replaces those systems' rows and keeps the others).

    python benchmarks/trajectories.py [--quick] [--systems double_pendulum chain4]
        [--where core machine] [--repeats 3]
    python benchmarks/trajectories.py --gpu   # 1e4-1e6 trajectories, default backend
"""

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time


# Cold compiles, as measured: the library's disk cache of executables off.
os.environ["LAGRAX_CACHE_DIR"] = ""


HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")
G = 9.81
T1 = 10.0
BOUNDS = (1e-9, 1e-12)
SYSTEMS = {
    "double_pendulum": dict(n=2, count=1024, spread=1.0, kind="closed"),
    "chain2": dict(n=2, count=256, spread=0.5, kind="chain"),
    "chain3": dict(n=3, count=256, spread=0.5, kind="chain", bounds=(1e-9, 1e-10)),
    # From chain4 on, no float64 method comes under 1e-12 on these releases
    # (heyoka.py at tol 1e-15: 1.4e-11 on chain4): the tight bound is 1e-10.
    "chain4": dict(n=4, count=256, spread=0.5, kind="chain", bounds=(1e-9, 1e-10)),
    "chain6": dict(n=6, count=256, spread=0.5, kind="chain", bounds=(1e-9, 1e-10)),
    "chain8": dict(n=8, count=256, spread=0.5, kind="chain", bounds=(1e-9, 1e-10)),
}
QUICK_COUNT = {"double_pendulum": 256}  # others: 64 releases with --quick
REFERENCE_TOL = 1e-18
TAYLOR_ORDERS = dict(simulate=(12, 20), simulate_batch=(16, 20))
# The most coordinates an order runs at: `simulate` with Taylor-20 under `vmap`
# compiles for minutes on a chain; `simulate_batch` with Taylor-20 compiles for
# minutes from chain4 on (its orders unrolled).
TAYLOR_MAX_N = dict(simulate={20: 2}, simulate_batch={20: 2})


def _initial(system, quick):
    import numpy as np

    spec = SYSTEMS[system]
    count = (QUICK_COUNT.get(system, 64)) if quick else spec["count"]
    rng = np.random.default_rng(20261125)
    q0 = rng.uniform(-spec["spread"], spec["spread"], (count, spec["n"]))
    return q0, np.zeros_like(q0)


def _energy(system, q, qdot):
    """E = T + V in closed form, float64 (per row of q, qdot)."""
    import numpy as np

    q, qdot = np.asarray(q, np.float64), np.asarray(qdot, np.float64)
    if SYSTEMS[system]["kind"] == "closed":
        t1, t2, w1, w2 = q[:, 0], q[:, 1], qdot[:, 0], qdot[:, 1]
        T = w1**2 + 0.5 * w2**2 + w1 * w2 * np.cos(t1 - t2)
        return T - 2 * G * np.cos(t1) - G * np.cos(t2)
    vx = np.cumsum(np.cos(q) * qdot, axis=1)
    vy = np.cumsum(np.sin(q) * qdot, axis=1)
    y = -np.cumsum(np.cos(q), axis=1)
    return 0.5 * np.sum(vx**2 + vy**2, axis=1) + G * np.sum(y, axis=1)


def _best(fn, repeats, min_seconds=1.0):
    """The output and the shortest time of at least `repeats` calls, and of as many
    as fill `min_seconds`."""
    times, out = [], None
    start = time.perf_counter()
    while len(times) < repeats or time.perf_counter() - start < min_seconds:
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, min(times)


def _tolerances(bound, start=None):
    """A half-decade grid, loosest first: bound x 100 (or `start`, the pick for a
    looser bound, if tighter) down to 1e-15 (a decade grid can leave either side's
    pick a decade short of its loosest passing tolerance)."""
    first = 2 * (int(round(-math.log10(bound))) - 2)
    if start is not None:
        first = max(first, int(round(-2 * math.log10(start))))
    return [float(f"{10.0 ** (-e / 2):.1g}") for e in range(first, 31)]


def _bounds(system):
    return SYSTEMS[system].get("bounds", BOUNDS)


# ----------------------------------------------------------------------- heyoka.py


def _heyoka_system(system):
    import heyoka as hy

    spec = SYSTEMS[system]
    n = spec["n"]
    qs = list(hy.make_vars(*[f"q{i}" for i in range(n)]))
    ws = list(hy.make_vars(*[f"w{i}" for i in range(n)]))
    if spec["kind"] == "closed":
        (t1, t2), (w1, w2) = qs, ws
        L = w1**2 + 0.5 * w2**2 + w1 * w2 * hy.cos(t1 - t2)
        L = L + 2 * G * hy.cos(t1) + G * hy.cos(t2)
    else:
        y = vx = vy = 0.0
        T = V = 0.0
        for q, w in zip(qs, ws):
            y = y - hy.cos(q)
            vx = vx + hy.cos(q) * w
            vy = vy + hy.sin(q) * w
            T = T + 0.5 * (vx**2 + vy**2)
            V = V + G * y
        L = T - V
    return hy.lagrangian(L, qs, ws)


def work_reference(args):
    """heyoka.py's scalar integrator in 80-bit long double at tol 1e-18."""
    import heyoka as hy
    import numpy as np

    q0, v0 = _initial(args.system, args.quick)
    n = q0.shape[1]
    ld = np.longdouble
    t = time.perf_counter()
    ta = hy.taylor_adaptive(
        _heyoka_system(args.system),
        np.zeros(2 * n, ld),
        tol=ld(REFERENCE_TOL),
        fp_type=ld,
        compact_mode=True,
    )
    build = time.perf_counter() - t
    out = np.empty((len(q0), 2 * n), ld)
    for i in range(len(q0)):
        ta.time = ld(0.0)
        ta.state[:] = np.concatenate([q0[i], v0[i]]).astype(ld)
        res = ta.propagate_until(ld(T1))
        if str(res[0]) != "taylor_outcome.time_limit":
            raise RuntimeError(f"reference failed on release {i}: {res[0]}")
        out[i] = ta.state
    # Rounded to float64 here: every compared method works in float64.
    return dict(ys=out.astype(np.float64).tolist(), build_s=build, order=ta.order)


def work_heyoka(args):
    import heyoka as hy
    import numpy as np

    q0, v0 = _initial(args.system, args.quick)
    ref = np.asarray(json.loads(args.reference_json))
    n = q0.shape[1]
    y0 = np.concatenate([q0, v0], axis=1)
    B = hy.recommended_simd_size()
    # Build times are cold: no compiled code from earlier runs (its disk cache) or
    # from the scan (its memory cache, cleared before each timed build).
    hy.llvm_state.set_diskcache_enabled(False)
    sys_ = _heyoka_system(args.system)
    chunks = [np.arange(i, min(i + B, len(y0))) for i in range(0, len(y0), B)]

    def build_batch(tol):
        return hy.taylor_adaptive_batch(sys_, np.zeros((2 * n, B)), tol=tol)

    def batch_loop(tb, idx_chunks, out):
        for idx in idx_chunks:
            tb.set_time(0.0)
            tb.state[:] = y0[np.resize(idx, B)].T
            tb.propagate_until(T1)
            out[idx] = tb.state[:, : len(idx)].T

    def run_batch(tb):
        out = np.full_like(y0, np.nan)
        batch_loop(tb, chunks, out)
        return out

    def error(ys):
        return float(np.max(np.abs(ys - ref)))

    def scan(bound, start):
        """The loosest tolerance of the grid whose batch-mode error is under bound;
        every point of the scan for the work-precision chart."""
        points = []
        for tol in _tolerances(bound, start):
            t = time.perf_counter()
            tb = build_batch(tol)
            build = time.perf_counter() - t
            run_batch(tb)  # (warm)
            t = time.perf_counter()
            ys = run_batch(tb)
            sec = time.perf_counter() - t
            err = error(ys)
            points.append(dict(tol=tol, max_error=err, seconds=sec, build_s=build))
            if err <= bound:
                return tol, tb, build, points
        return None, None, None, points

    rows, curves = [], {}
    start = None
    for bound in _bounds(args.system):
        tol, tb, build, points = scan(bound, start)
        curves.setdefault(f"heyoka.py batch (SIMD {B})", []).extend(points)
        if tol is None:
            continue
        start = tol
        hy.llvm_state.clear_memcache()
        t = time.perf_counter()
        tb = build_batch(tol)
        build = time.perf_counter() - t
        ys_b, sec_b = _best(lambda: run_batch(tb), args.repeats)
        common = dict(bound=bound, tol=tol, n=len(y0))
        if args.where == "core":
            rows.append(
                _row(
                    f"heyoka.py {hy.__version__} batch (SIMD {B})",
                    args,
                    ys_b,
                    ref,
                    sec_b,
                    build_s=build,
                    order=tb.order,
                    **common,
                )
            )
            hy.llvm_state.clear_memcache()
            t = time.perf_counter()
            ta = hy.taylor_adaptive(sys_, np.zeros(2 * n), tol=tol)
            build_s = time.perf_counter() - t

            def scalar():
                out = np.empty_like(y0)
                for i in range(len(y0)):
                    ta.time = 0.0
                    ta.state[:] = y0[i]
                    ta.propagate_until(T1)
                    out[i] = ta.state
                return out

            ys, sec = _best(scalar, args.repeats)
            rows.append(
                _row(
                    "heyoka.py scalar loop",
                    args,
                    ys,
                    ref,
                    sec,
                    build_s=build_s,
                    order=ta.order,
                    **common,
                )
            )
        else:
            workers = os.cpu_count()

            def gen(ta_copy, i):
                ta_copy.set_time(0.0)
                ta_copy.state[:] = y0[np.resize(chunks[i], B)].T
                return ta_copy

            def ensemble():
                res = hy.ensemble_propagate_until(
                    tb, T1, len(chunks), gen, algorithm="thread", max_workers=workers
                )
                out = np.empty_like(y0)
                for idx, r in zip(chunks, res):
                    out[idx] = r[0].state[:, : len(idx)].T
                return out

            ys, sec = _best(ensemble, args.repeats)
            rows.append(
                _row(
                    f"heyoka.py ensemble_propagate_until (threads, SIMD {B})",
                    args,
                    ys,
                    ref,
                    sec,
                    build_s=build,
                    **common,
                )
            )
            integrators = [tb] + [build_batch(tol) for _ in range(workers - 1)]
            shares = [chunks[i::workers] for i in range(workers)]

            def threads():
                out = np.empty_like(y0)
                ts = [
                    threading.Thread(target=batch_loop, args=(ti, share, out))
                    for ti, share in zip(integrators, shares)
                ]
                for th in ts:
                    th.start()
                for th in ts:
                    th.join()
                return out

            ys, sec = _best(threads, args.repeats)
            rows.append(
                _row(
                    f"heyoka.py batch (SIMD {B}), {workers} threads",
                    args,
                    ys,
                    ref,
                    sec,
                    build_s=build,
                    **common,
                )
            )
    return dict(rows=rows, curves=curves)


def work_floor(args):
    """Where float64 stops converging: heyoka.py's batch mode at tight tolerances,
    plain and with `high_accuracy=True` (compensated summation of its Taylor
    polynomials), per-release errors; and how much each release amplifies a
    perturbation of its release state by +-1e-11 over t = 10 (tol 1e-15)."""
    import heyoka as hy
    import numpy as np

    q0, v0 = _initial(args.system, args.quick)
    ref = np.asarray(json.loads(args.reference_json))
    y0 = np.concatenate([q0, v0], axis=1)
    n, B = q0.shape[1], hy.recommended_simd_size()
    sys_ = _heyoka_system(args.system)

    def run(tol, high_accuracy, y0=y0):
        tb = hy.taylor_adaptive_batch(
            sys_, np.zeros((2 * n, B)), tol=tol, high_accuracy=high_accuracy
        )
        out = np.empty_like(y0)
        for i in range(0, len(y0), B):
            idx = np.arange(i, min(i + B, len(y0)))
            tb.set_time(0.0)
            tb.state[:] = y0[np.resize(idx, B)].T
            tb.propagate_until(T1)
            out[idx] = tb.state[:, : len(idx)].T
        return out, tb.order

    rows = []
    for high_accuracy in (False, True):
        for tol in args.floor_tols:
            ys, order = run(tol, high_accuracy)
            err = np.abs(ys - ref).max(axis=1)
            rows.append(
                dict(
                    name=f"heyoka.py batch (SIMD {B})"
                    + (", high_accuracy" if high_accuracy else ""),
                    tol=tol,
                    order=order,
                    max_error=float(err.max()),
                    median_error=float(np.median(err)),
                    worst=np.argsort(err)[::-1][:5].tolist(),
                )
            )
            print(rows[-1], file=sys.stderr, flush=True)
    delta = 1e-11
    signs = np.random.default_rng(1).choice([-1.0, 1.0], y0.shape)
    a, _ = run(1e-15, False)
    b, _ = run(1e-15, False, y0 + delta * signs)
    amp = np.abs(a - b).max(axis=1) / delta
    amplification = dict(
        delta=delta,
        max=float(amp.max()),
        median=float(np.median(amp)),
        worst=np.argsort(amp)[::-1][:5].tolist(),
    )
    print(amplification, file=sys.stderr, flush=True)
    return dict(rows=rows, amplification=amplification)


# --------------------------------------------------------------------------- lagrax


def _lagrax_lagrangian(system):
    import jax.numpy as jnp

    import lagrax

    spec = SYSTEMS[system]
    if spec["kind"] == "closed":

        def L(q, qdot, t):
            t1, t2, w1, w2 = q[0], q[1], qdot[0], qdot[1]
            T = w1**2 + 0.5 * w2**2 + w1 * w2 * jnp.cos(t1 - t2)
            return T + 2 * G * jnp.cos(t1) + G * jnp.cos(t2)

        return L

    def positions(q, t):
        return jnp.stack([jnp.cumsum(jnp.sin(q)), -jnp.cumsum(jnp.cos(q))], axis=1)

    masses = jnp.ones(spec["n"])
    return lagrax.particle_lagrangian(
        masses, positions, lambda r, t: G * jnp.sum(r[:, 1])
    )


def _lagrax_methods(quick, n=2, width=256):
    """name -> a function `(L, q0, qdot0, tol) -> (q1, qdot1, steps)` for one
    trajectory (vmapped and jitted by the caller); `simulate_batch` over `width`
    lanes."""
    import diffrax as dfx

    import lagrax

    def simulate(solver):
        def run(L, q0, qdot0, tol):
            sol = lagrax.simulate(
                L,
                q0,
                qdot0,
                0.0,
                T1,
                solver=solver,
                rtol=tol,
                atol=tol,
                max_steps=1 << 16,
                throw=False,
            )
            ok = sol.result == dfx.RESULTS.successful
            q1, qdot1 = (x[-1] for x in sol.ys)
            nan = float("nan")
            return (
                _where(ok, q1, nan),
                _where(ok, qdot1, nan),
                sol.stats["num_steps"],
            )

        run.taylor = isinstance(solver, lagrax.Taylor)
        return run

    def batch(order, tier=None):
        def run(L, q0, qdot0, tol):
            # `tier` "0": the specialized program from the first call (by default a
            # chain's calls here, each at its own tolerance, stay on the compact one).
            saved = os.environ.get("LAGRAX_COMPACT")
            if tier is not None:
                os.environ["LAGRAX_COMPACT"] = tier
            try:
                return _batch_run(order, L, q0, qdot0, tol)
            finally:
                if saved is None:
                    os.environ.pop("LAGRAX_COMPACT", None)
                else:
                    os.environ["LAGRAX_COMPACT"] = saved

        def _batch_run(order, L, q0, qdot0, tol):
            sol = lagrax.simulate_batch(
                L,
                q0,
                qdot0,
                0.0,
                T1,
                solver=lagrax.Taylor(order=order),
                rtol=tol,
                atol=tol,
                max_steps=1 << 16,
                throw=False,
                lanes=width,
            )
            q1, qdot1 = (x[:, -1] for x in sol.ys)
            return q1, qdot1, sol.stats["num_steps"]

        run.batched = True
        return run

    return {
        "lagrax simulate Tsit5": simulate(dfx.Tsit5()),
        "lagrax simulate Dopri8": simulate(dfx.Dopri8()),
        **{
            f"lagrax simulate Taylor-{k}": simulate(lagrax.Taylor(order=k))
            for k in TAYLOR_ORDERS["simulate"]
            if n <= TAYLOR_MAX_N["simulate"].get(k, n)
        },
        **{
            f"lagrax simulate_batch Taylor-{k}": batch(k)
            for k in TAYLOR_ORDERS["simulate_batch"]
            if n <= TAYLOR_MAX_N["simulate_batch"].get(k, n)
        },
        # (The double pendulum's specialized compile is short enough to be the
        # default's first tier.)
        **(
            {"lagrax simulate_batch Taylor-16, specialized": batch(16, "0")}
            if n > 2
            else {}
        ),
    }


def _where(ok, x, fill):
    import jax.numpy as jnp

    return jnp.where(ok, x, fill)


def work_lagrax(args):
    import jax

    if args.where == "machine":
        jax.config.update("jax_num_cpu_devices", os.cpu_count())
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    q0_np, v0_np = _initial(args.system, args.quick)
    ref = np.asarray(json.loads(args.reference_json))
    L = _lagrax_lagrangian(args.system)
    q0, v0 = jnp.asarray(q0_np), jnp.asarray(v0_np)
    methods = _lagrax_methods(args.quick, SYSTEMS[args.system]["n"])
    rows, curves = [], {}
    devices = jax.devices()
    for name, one in methods.items():
        if args.methods and not any(m in name for m in args.methods):
            continue
        if getattr(one, "batched", False):
            # Compiled by itself, sharded over the devices (no enclosing jit).
            fn = lambda q, v, tol, one=one: one(L, q, v, tol)
        else:
            fn = _vmapped(one, L, devices)

        def call(tol, fn=fn):
            out = fn(q0, v0, jnp.asarray(tol))
            return jax.block_until_ready(out)

        t = time.perf_counter()
        call(1e-9)
        compile_s = time.perf_counter() - t
        print(f"    {name}: first call {compile_s:.1f} s", file=sys.stderr, flush=True)

        def ys_of(out):
            q1, v1, steps = (np.asarray(x) for x in out)
            return np.concatenate([q1, v1], axis=1), steps

        start = None
        for bound in _bounds(args.system):
            chosen = None
            for tol in _tolerances(bound, start):
                t = time.perf_counter()
                out = call(tol)
                sec = time.perf_counter() - t
                ys, steps = ys_of(out)
                err = float(np.max(np.abs(ys - ref))) if np.isfinite(ys).all() else None
                curves.setdefault(name, []).append(
                    dict(tol=tol, max_error=err, seconds=sec)
                )
                print(
                    f"      tol {tol:.0e}: error {err}, {sec:.2f} s",
                    file=sys.stderr,
                    flush=True,
                )
                if err is not None and err <= bound:
                    chosen = tol
                    break
            if chosen is None:
                continue
            start = chosen
            out, sec = _best(lambda: call(chosen), args.repeats)
            ys, steps = ys_of(out)
            rows.append(
                _row(
                    name,
                    args,
                    ys,
                    ref,
                    sec,
                    bound=bound,
                    tol=chosen,
                    n=len(ys),
                    compile_s=compile_s,
                    steps_per_trajectory=float(np.mean(steps)),
                    ns_per_step=sec / float(np.sum(steps)) * 1e9 * len(devices),
                )
            )
    return dict(rows=rows, curves=curves)


def _vmapped(one, L, devices):
    """`jit(vmap(one))` over the releases; over several devices each device runs
    its share (`jax.shard_map`)."""
    import jax
    import numpy as np
    from jax.sharding import Mesh, PartitionSpec as P

    batched = jax.vmap(lambda q, v, tol: one(L, q, v, tol), (0, 0, None))
    if len(devices) > 1:
        mesh = Mesh(np.array(devices), ("lanes",))
        batched = jax.shard_map(
            batched,
            mesh=mesh,
            in_specs=(P("lanes"), P("lanes"), P()),
            out_specs=P("lanes"),
            check_vma=False,
        )
    # As `lagrax.Taylor`'s docstring asks of a jit of one's own on a CPU: XLA's
    # elemental emitters (its fusion emitters recompute parts of the Taylor program).
    taylor = getattr(one, "taylor", False) and jax.default_backend() == "cpu"
    options = {"xla_cpu_use_fusion_emitters": False} if taylor else None
    return jax.jit(batched, compiler_options=options)


def _row(name, args, ys, ref, seconds, **extra):
    import numpy as np

    ys = np.asarray(ys)
    n = ys.shape[1] // 2
    ok = np.isfinite(ys).all(axis=1)
    E0 = _energy(args.system, *_initial(args.system, args.quick))
    E1 = _energy(args.system, ys[:, :n], ys[:, n:])
    drift = np.abs(E1 - E0) / np.abs(E0)
    return dict(
        name=name,
        trajectories_per_s=len(ys) / seconds,
        seconds=seconds,
        max_error=float(np.max(np.abs(ys - ref))) if ok.all() else None,
        failed=int((~ok).sum()),
        energy_drift_max=float(np.max(drift[ok])) if ok.any() else None,
        energy_drift_median=float(np.median(drift[ok])) if ok.any() else None,
        **extra,
    )


# ------------------------------------------------------------------- accelerations


def work_accelerations(args):
    """`lagrax.accelerations` inside a user's own vector field, `lagrax.vector_field`
    and a hand-written closed form, each in one fixed-step Tsit5 solve (dt 0.01, 200
    steps, 1024 lanes, `jit(vmap)`): medians of interleaved rounds."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import diffrax as dfx
    import jax.numpy as jnp
    import numpy as np

    import lagrax
    from lagrax.systems import double_pendulum, pendulum

    systems = {
        "pendulum": (
            pendulum.lagrangian(g=G),
            lambda q, v: -G * jnp.sin(q),
            1,
        ),
        "double pendulum (particles)": (
            double_pendulum.lagrangian(g=G),
            lambda q, v: double_pendulum.acceleration(q, v, g=G),
            2,
        ),
    }
    rows = []
    for name, (L, hand, n) in systems.items():
        fields = {
            "hand-written": lambda t, y, a, hand=hand: (y[1], hand(*y)),
            "lagrax.vector_field": lagrax.vector_field(L),
            "lagrax.accelerations in the user's field": (
                lambda t, y, a, L=L: (y[1], lagrax.accelerations(L, y[0], y[1], t))
            ),
        }
        rng = np.random.default_rng(0)
        q0 = jnp.asarray(rng.uniform(-1, 1, (1024, n)))
        v0 = jnp.zeros_like(q0)
        fns = {}
        for label, f in fields.items():

            def solve(q, v, f=f):
                return dfx.diffeqsolve(
                    dfx.ODETerm(f), dfx.Tsit5(), 0.0, 2.0, 0.01, (q, v),
                    stepsize_controller=dfx.ConstantStepSize(), max_steps=256,
                ).ys  # fmt: skip

            fns[label] = jax.jit(jax.vmap(solve))
            jax.block_until_ready(fns[label](q0, v0))
        times = {label: [] for label in fns}
        for r in range(max(args.repeats, 5)):
            for label in list(fns)[r % 3 :] + list(fns)[: r % 3]:
                t = time.perf_counter()
                jax.block_until_ready(fns[label](q0, v0))
                times[label].append(time.perf_counter() - t)
        base = float(np.median(times["hand-written"]))
        for label, ts in times.items():
            rows.append(
                dict(
                    system=name,
                    field=label,
                    median_s=float(np.median(ts)),
                    vs_hand_written=float(np.median(ts)) / base,
                )
            )
            print(f"{name:28s} {label:42s} {rows[-1]['vs_hand_written']:.2f}x")
    return dict(rows=rows)


# ------------------------------------------------------------------------------ GPU


def work_gpu(args):
    """lagrax alone on the default backend (a GPU; heyoka.py is not there): the
    double pendulum's releases (the first 1024 are the CPU run's, so their error is
    measured against its 80-bit reference), each method at the tolerances the
    committed CPU run chose per bound (`results/trajectories.json`, one core); the
    first call (compile), trajectories/s (best of `--repeats`), the error of the first
    1024. Rows printed as measured; rows skipped once `--budget` seconds have passed."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    system = "double_pendulum"
    args.system = system
    spec = SYSTEMS[system]
    ref = np.asarray(json.loads(args.reference_json)) if args.reference_json else None
    with open(os.path.join(RESULTS, "trajectories.json")) as fh:
        cpu = json.load(fh)["systems"][system]["rows"]
    chosen = {}
    for row in cpu:
        if row["where"] == "1 core" and row["name"].startswith("lagrax"):
            chosen.setdefault(row["name"], {})[row["bound"]] = row["tol"]
    L = _lagrax_lagrangian(system)
    device = str(jax.devices()[0].device_kind)
    rows, start = [], time.perf_counter()
    for count in args.gpu_sizes:
        rng = np.random.default_rng(20261125)  # as `_initial`: the same first rows
        q0_np = rng.uniform(-spec["spread"], spec["spread"], (count, spec["n"]))
        q0 = jnp.asarray(q0_np)
        v0 = jnp.zeros_like(q0)
        width = min(count, args.gpu_width)
        methods = _lagrax_methods(False, spec["n"], width=width)
        for name, one in methods.items():
            if name not in chosen or (
                args.methods and not any(m in name for m in args.methods)
            ):
                continue
            if time.perf_counter() - start > args.budget:
                print(f"budget spent: {name} n={count} skipped", file=sys.stderr)
                continue
            if getattr(one, "batched", False):
                fn = lambda q, v, tol, one=one: one(L, q, v, tol)
            else:
                fn = _vmapped(one, L, jax.devices()[:1])
            call = lambda tol, fn=fn: jax.block_until_ready(
                fn(q0, v0, jnp.asarray(tol))
            )
            t = time.perf_counter()
            call(1e-9)
            compile_s = time.perf_counter() - t
            for bound, tol in sorted(chosen[name].items(), reverse=True):
                out, sec = _best(lambda: call(tol), args.repeats)
                q1, v1, steps = (np.asarray(x) for x in out)
                ys = np.concatenate([q1, v1], axis=1)
                head = ys[: len(ref)] if ref is not None else None
                err = (
                    float(np.max(np.abs(head - ref)))
                    if head is not None and np.isfinite(head).all()
                    else None
                )
                rows.append(
                    dict(
                        name=f"{name} n={count} on {device}",
                        trajectories_per_s=count / sec,
                        seconds=sec,
                        compile_s=compile_s,
                        bound=bound,
                        tol=tol,
                        max_error_first_1024=err,
                        failed=int((~np.isfinite(ys).all(axis=1)).sum()),
                        steps_per_trajectory=float(np.mean(steps)),
                        width=width if getattr(one, "batched", False) else None,
                    )
                )
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    return dict(rows=rows, curves={}, device=device, date=time.strftime("%Y-%m-%d"))


# ----------------------------------------------------------------------------- main


def spawn(kind, args, system, where, reference=None, extra=()):
    cmd = [sys.executable, __file__, "--worker", kind, "--system", system]
    cmd += ["--where", where, "--repeats", str(args.repeats)]
    cmd += ["--quick"] if args.quick else []
    cmd += list(extra)
    env = dict(os.environ)
    if reference is not None:
        path = os.path.join(tempfile.mkdtemp(), "ref.json")
        with open(path, "w") as fh:
            json.dump(reference, fh)
        cmd += ["--reference-file", path]
    if where == "core":
        cmd = ["taskset", "-c", str(args.core)] + cmd
    t = time.perf_counter()
    # The worker's stderr (its progress lines) goes straight through.
    out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=env)
    if out.returncode != 0:
        print(f"  ({kind} {system} {where} failed)", file=sys.stderr)
        return None
    print(f"  ({kind} {system} {where}: {time.perf_counter() - t:.0f} s)", flush=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def reference(args, system):
    """The long-double reference, cached in `--cache` by system and releases."""
    os.makedirs(args.cache, exist_ok=True)
    tag = f"{system}{'_quick' if args.quick else ''}_tol{REFERENCE_TOL:g}.json"
    path = os.path.join(args.cache, tag)
    if os.path.exists(path):
        with open(path) as fh:
            return json.load(fh)
    out = spawn("reference", args, system, "machine")
    with open(path, "w") as fh:
        json.dump(out, fh)
    return out


def _ratios(rows):
    """Each row against heyoka.py's best at the same bound on the same resources."""
    for row in rows:
        best = max(
            (
                x["trajectories_per_s"]
                for x in rows
                if x["name"].startswith("heyoka")
                and x["bound"] == row["bound"]
                and x["where"] == row["where"]
            ),
            default=None,
        )
        row["vs_heyoka_best"] = row["trajectories_per_s"] / best if best else None


def plot(report, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    systems = [s for s in SYSTEMS if s in report["systems"]]
    fig, axes = plt.subplots(1, len(systems), figsize=(5 * len(systems), 4.2))
    axes = [axes] if len(systems) == 1 else list(axes)
    for ax, system in zip(axes, systems):
        data = report["systems"][system]
        for name, points in sorted(data.get("curves", {}).items()):
            pts = sorted(
                (p for p in points if p["max_error"] is not None),
                key=lambda p: p["tol"],
            )
            if not pts:
                continue
            style = "--" if name.startswith("heyoka") else "-"
            ax.loglog(
                [p["max_error"] for p in pts],
                [p["seconds"] / data["count"] * 1e6 for p in pts],
                style + "o",
                ms=3,
                label=name,
            )
        for bound in _bounds(system):
            ax.axvline(bound, color="0.8", lw=0.8)
        ax.set_title(f"{system} ({data['count']} releases, 1 core)")
        ax.set_xlabel("max abs error of (q, q̇) at t = 10")
        ax.set_ylabel("µs per trajectory")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--quick", action="store_true")
    p.add_argument("--gpu", action="store_true")
    p.add_argument(
        "--gpu-sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000]
    )
    p.add_argument(
        "--gpu-width", type=int, default=1 << 17, help="simulate_batch lanes"
    )
    p.add_argument(
        "--budget", type=float, default=float("inf"), help="--gpu: seconds, then stop"
    )
    p.add_argument("--systems", nargs="+", default=None, choices=list(SYSTEMS))
    p.add_argument("--where", nargs="+", default=["core", "machine"])
    p.add_argument(
        "--methods",
        nargs="*",
        default=None,
        help="only lagrax methods whose name contains one of these",
    )
    p.add_argument("--no-heyoka", action="store_true")
    p.add_argument(
        "--accelerations",
        action="store_true",
        help="only lagrax.accelerations inside a user's solve against vector_field "
        "and a hand-written EOM (results/trajectories_accelerations.json)",
    )
    p.add_argument(
        "--floor",
        action="store_true",
        help="only heyoka.py's error floor (plain and high_accuracy) at --floor-tols "
        "and each release's amplification of a 1e-11 perturbation "
        "(results/trajectories_floor.json)",
    )
    p.add_argument("--floor-tols", type=float, nargs="+", default=[1e-14, 1e-16])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--core", type=int, default=1)
    p.add_argument(
        "--cache",
        default=os.path.join(tempfile.gettempdir(), "lagrax_trajectories_reference"),
    )
    p.add_argument("--worker")
    p.add_argument("--system")
    p.add_argument("--reference-file")
    args = p.parse_args()
    if args.worker:
        args.where = args.where[0]
        args.reference_json = None
        if args.reference_file:
            with open(args.reference_file) as fh:
                args.reference_json = json.dumps(json.load(fh)["ys"])
        fn = dict(
            accelerations=work_accelerations,
            reference=work_reference,
            heyoka=work_heyoka,
            lagrax=work_lagrax,
            gpu=work_gpu,
            floor=work_floor,
        )[args.worker]
        print(json.dumps(fn(args)))
        return
    os.makedirs(RESULTS, exist_ok=True)
    if args.gpu:
        extra = ["--gpu-sizes", *map(str, args.gpu_sizes)]
        extra += ["--gpu-width", str(args.gpu_width), "--budget", str(args.budget)]
        extra += ["--methods", *args.methods] if args.methods else []
        path = os.path.join(args.cache, f"double_pendulum_tol{REFERENCE_TOL:g}.json")
        ref = None
        if os.path.exists(path):  # the CPU run's 80-bit reference, where it is here
            with open(path) as fh:
                ref = json.load(fh)
        out = spawn("gpu", args, "double_pendulum", "machine", ref, extra)
        with open(os.path.join(RESULTS, "trajectories_gpu.json"), "w") as fh:
            json.dump(out, fh, indent=1)
        return
    if args.accelerations:
        out = spawn("accelerations", args, "double_pendulum", "core")
        for row in out["rows"]:
            print(
                f"{row['system']:28s} {row['field']:42s} {row['vs_hand_written']:.2f}x"
            )
        with open(os.path.join(RESULTS, "trajectories_accelerations.json"), "w") as fh:
            json.dump(out, fh, indent=1)
        return
    if args.floor:
        path = os.path.join(RESULTS, "trajectories_floor.json")
        report = {}
        if os.path.exists(path):
            with open(path) as fh:
                report = json.load(fh)
        tols = ["--floor-tols", *map(str, args.floor_tols)]
        for system in args.systems or ["chain6"]:
            ref = reference(args, system)
            out = spawn("floor", args, system, "core", ref, tols)
            report[system] = dict(date=time.strftime("%Y-%m-%d"), **out)
        with open(path, "w") as fh:
            json.dump(report, fh, indent=1)
        print(f"wrote {path}")
        return
    suffix = "_quick" if args.quick else ""
    path = os.path.join(RESULTS, f"trajectories{suffix}.json")
    report = dict(systems={})
    if os.path.exists(path):
        with open(path) as fh:
            report = json.load(fh)
    systems = args.systems or (
        ["double_pendulum", "chain2", "chain4"] if args.quick else list(SYSTEMS)
    )
    extra = ["--methods", *args.methods] if args.methods else []
    for system in systems:
        print(f"{system}:", flush=True)
        ref = reference(args, system)
        rows, curves = [], {}
        for where in args.where:
            parts = [] if args.no_heyoka else ["heyoka"]
            for kind in parts + ["lagrax"]:
                out = spawn(kind, args, system, where, ref, extra)
                if out is None:
                    continue
                for row in out["rows"]:
                    row["where"] = "1 core" if where == "core" else "whole machine"
                    rows.append(row)
                if where == "core":
                    curves.update(out["curves"])
        _ratios(rows)
        old = report["systems"].get(system, {})
        if args.methods or args.no_heyoka:
            # A partial run: keep the other rows of this system.
            names = {(r["name"], r["where"]) for r in rows}
            keep = [
                r for r in old.get("rows", []) if (r["name"], r["where"]) not in names
            ]
            rows = keep + rows
            curves = {**old.get("curves", {}), **curves}
            _ratios(rows)
        report["systems"][system] = dict(
            count=len(ref["ys"]),
            reference=dict(
                build_s=ref["build_s"],
                order=ref["order"],
                tol=REFERENCE_TOL,
                fp="80-bit long double",
            ),
            rows=rows,
            curves=curves,
        )
        _print(system, rows)
    report["meta"] = dict(
        machine=platform.processor() or platform.machine(),
        cores=os.cpu_count(),
        python=platform.python_version(),
        date=time.strftime("%Y-%m-%d"),
        quick=args.quick,
    )
    with open(path, "w") as fh:
        json.dump(report, fh, indent=1)
    print(f"wrote {path}")
    plot(report, os.path.join(RESULTS, f"trajectories{suffix}.png"))


def _print(system, rows):
    head = (
        f"{'':52s} {'where':>13s} {'bound':>6s} {'tol':>6s} {'traj/s':>9s} "
        f"{'vs hy':>6s} {'max err':>8s} {'build/compile s':>15s} {'E drift':>8s}"
    )
    print(head)
    for r in sorted(rows, key=lambda r: (r["where"], r["bound"], r["name"])):
        ratio = r["vs_heyoka_best"]
        build = r.get("build_s", r.get("compile_s"))
        print(
            f"{r['name'][:52]:52s} {r['where']:>13s} {r['bound']:6.0e} {r['tol']:6.0e} "
            f"{r['trajectories_per_s']:9.0f} "
            f"{ratio if ratio is not None else float('nan'):6.2f} "
            f"{r['max_error'] if r['max_error'] is not None else float('nan'):8.1e} "
            f"{build if build is not None else float('nan'):15.2f} "
            f"{r['energy_drift_max'] or float('nan'):8.1e}"
        )


if __name__ == "__main__":
    main()
