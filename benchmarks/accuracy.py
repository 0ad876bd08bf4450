r"""What a tolerance buys: the error each solver reaches at a requested tolerance.

At the same `rtol = atol = tol`, a user who moves from one solver to another should
get an answer at least as good. This script integrates batches of releases with each
solver at tol = 1e-8 … 1e-14 and prints, per system, solver and tolerance, the error
reached (the largest and the median over the releases of the max-norm error of
$(q, \dot q)$ at $t_1$), its ratio to Dopri8's at the same tol, the steps per release
(of which rejected) and the wall time of the compiled call (best of `--repeats`).

Systems (float64, released at $t = 0$):

- `double_pendulum`: $L = \dot\theta_1^2 + \frac12\dot\theta_2^2 + \dot\theta_1
  \dot\theta_2\cos(\theta_1 - \theta_2) + 2g\cos\theta_1 + g\cos\theta_2$, g = 9.81,
  1024 releases from rest, $\theta_i$ uniform in $[-1, 1]$, $t_1 = 10$;
- `chain4`: a chain of 4 unit pendulums written from particle positions
  (`lagrax.particle_lagrangian`), 256 releases from rest within $\pm 0.5$ rad,
  $t_1 = 10$;
- `kepler`: $L = \frac12|\dot r|^2 + 1/|r|$ on an orbit of eccentricity 0.9 and
  semi-major axis 1 (period $2\pi$, pericentre 0.1, speed there $\sqrt{19}$), 64
  releases at mean anomalies $2\pi i/64$, $t_1 = 10$ (every release passes the
  pericentre at least once);
- `separatrix`: the pendulum $L = \frac12\dot\theta^2 + \cos\theta$ released from
  rest at $\theta_0 = \pi - 10^{-u}$, 64 values of $u$ evenly in $[1, 3]$,
  $t_1 = 20$.

Reference: heyoka.py's scalar Taylor integrator in 80-bit long double at tol 1e-18
from the same float64 release states (cached in `--cache`).

Solvers: `Dopri8` and `Tsit5` (`lagrax.simulate` under `jax.jit(jax.vmap(...))`,
diffrax's `PIDController`), `lagrax.simulate_batch` with its default solver
`lagrax.Taylor()` (order 20; order 16 for `chain4`, whose order-20 program compiles
for minutes), `lagrax.simulate(..., solver=lagrax.Taylor(order=12))` (the diffrax
solver, under `jit(vmap)` with the compile option its docstring gives) and heyoka.py
in float64 (`taylor_adaptive_batch` at its tol, SIMD width `recommended_simd_size()`).

    python benchmarks/accuracy.py [--quick] [--systems kepler] [--tols 1e-10 1e-12]

Writes `results/accuracy[_quick].json`.

With `--periods`: the period sweeps' per-lane error estimates instead
(`sweep_periods`, every method with `Taylor()`, `Dopri8`, `Tsit5` and `Dopri5`; the
pendulum's 2047 amplitudes 0.01 .. pi - 1e-3 and the asymmetric well's 256 releases
to 0.99 of its hump, against 40-digit periods from `tests/exact_periods.py`): per
system, method, stepper and rtol the lanes' statuses, the true errors, and the
estimate over the true error (median, 5th percentile, smallest, lanes below the
truth).

    python benchmarks/accuracy.py --periods [--tols 1e-13 1e-10] \
        [--period-methods half] [--period-solvers Dopri8 Tsit5]

Writes `results/accuracy_periods[_quick].json`.
"""

import argparse
import json
import os
import pathlib
import platform
import sys
import tempfile
import time

import jax


jax.config.update("jax_enable_x64", True)

import diffrax as dfx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lagrax  # noqa: E402


sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "tests"))
import exact_periods  # noqa: E402


RESULTS = pathlib.Path(__file__).parent / "results"
G = 9.81
REFERENCE_TOL = 1e-18
TOLS = [10.0**-k for k in range(8, 15)]
ELEMENTAL = {"xla_cpu_use_fusion_emitters": False}


# --------------------------------------------------------------------------- systems


def _releases(system, quick):
    """`(q0, qdot0, t1)`: float64 release states (rows) and the end time."""
    rng = np.random.default_rng(20261128)
    if system == "double_pendulum":
        count = 128 if quick else 1024
        q0 = rng.uniform(-1.0, 1.0, (count, 2))
        return q0, np.zeros_like(q0), 10.0
    if system == "chain4":
        count = 32 if quick else 256
        q0 = rng.uniform(-0.5, 0.5, (count, 4))
        return q0, np.zeros_like(q0), 10.0
    if system == "kepler":
        count = 16 if quick else 64
        e = 0.9
        M = 2 * np.pi * np.arange(count) / count
        E = M.copy()
        for _ in range(60):  # Kepler's equation M = E - e sin E, by Newton
            E = E - (E - e * np.sin(E) - M) / (1 - e * np.cos(E))
        q0 = np.stack([np.cos(E) - e, np.sqrt(1 - e**2) * np.sin(E)], axis=1)
        rate = 1.0 / (1 - e * np.cos(E))  # dE/dt for a = GM = 1
        v0 = np.stack([-np.sin(E) * rate, np.sqrt(1 - e**2) * np.cos(E) * rate], axis=1)
        return q0, v0, 10.0
    if system == "separatrix":
        count = 16 if quick else 64
        q0 = (np.pi - 10.0 ** -np.linspace(1.0, 3.0, count))[:, None]
        return q0, np.zeros_like(q0), 20.0
    raise ValueError(system)


def _lagrangian(system):
    if system == "double_pendulum":

        def L(q, qdot, t):
            t1, t2, w1, w2 = q[0], q[1], qdot[0], qdot[1]
            T = w1**2 + 0.5 * w2**2 + w1 * w2 * jnp.cos(t1 - t2)
            return T + 2 * G * jnp.cos(t1) + G * jnp.cos(t2)

        return L
    if system == "chain4":

        def positions(q, t):
            return jnp.stack([jnp.cumsum(jnp.sin(q)), -jnp.cumsum(jnp.cos(q))], axis=1)

        return lagrax.particle_lagrangian(
            jnp.ones(4), positions, lambda r, t: G * jnp.sum(r[:, 1])
        )
    if system == "kepler":
        return lambda q, qdot, t: 0.5 * jnp.sum(qdot**2) + 1 / jnp.sqrt(jnp.sum(q**2))
    if system == "separatrix":
        return lambda q, qdot, t: 0.5 * qdot[0] ** 2 + jnp.cos(q[0])
    raise ValueError(system)


def _heyoka_system(system, n):
    import heyoka as hy

    qs = [hy.expression(f"q{i}") for i in range(n)]
    ws = [hy.expression(f"w{i}") for i in range(n)]
    if system == "double_pendulum":
        (t1, t2), (w1, w2) = qs, ws
        L = w1**2 + 0.5 * w2**2 + w1 * w2 * hy.cos(t1 - t2)
        L = L + 2 * G * hy.cos(t1) + G * hy.cos(t2)
    elif system == "chain4":
        y = vx = vy = L = 0.0
        for q, w in zip(qs, ws):
            y = y - hy.cos(q)
            vx = vx + hy.cos(q) * w
            vy = vy + hy.sin(q) * w
            L = L + 0.5 * (vx**2 + vy**2) - G * y
    elif system == "kepler":
        (x, y), (vx, vy) = qs, ws
        L = 0.5 * (vx**2 + vy**2) + 1.0 / hy.sqrt(x**2 + y**2)
    elif system == "separatrix":
        L = 0.5 * ws[0] ** 2 + hy.cos(qs[0])
    return hy.lagrangian(L, qs, ws)


def reference(system, quick, cache):
    """heyoka.py in 80-bit long double at tol 1e-18, rounded to float64 (cached)."""
    path = pathlib.Path(cache) / f"{system}{'_quick' if quick else ''}.npy"
    q0, v0, t1 = _releases(system, quick)
    if path.exists():
        return np.load(path)
    import heyoka as hy

    n = q0.shape[1]
    ld = np.longdouble
    ta = hy.taylor_adaptive(
        _heyoka_system(system, n),
        np.zeros(2 * n, ld),
        tol=ld(REFERENCE_TOL),
        fp_type=ld,
        compact_mode=True,
    )
    out = np.empty((len(q0), 2 * n))
    for i in range(len(q0)):
        ta.time = ld(0.0)
        ta.state[:] = np.concatenate([q0[i], v0[i]]).astype(ld)
        res = ta.propagate_until(ld(t1))
        if str(res[0]) != "taylor_outcome.time_limit":
            raise RuntimeError(f"reference failed on release {i}: {res[0]}")
        out[i] = ta.state.astype(np.float64)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, out)
    return out


# --------------------------------------------------------------------------- solvers


def _best(fn, repeats):
    out = jax.block_until_ready(fn())  # (compile)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return out, min(times)


def lagrax_methods(system, n):
    """name -> `run(L, q0, v0, t1, tol) -> (ys (B, 2n), steps (B,))`, compiled on its
    first call (the tolerance an argument: a scan does not recompile)."""

    def vmapped(solver, options=None):
        def one(L, q0, v0, t1, tol):
            sol = lagrax.simulate(
                L, q0, v0, 0.0, t1, solver=solver, rtol=tol, atol=tol,
                max_steps=1 << 17, throw=False,
            )  # fmt: skip
            ok = sol.result == dfx.RESULTS.successful
            y = jnp.concatenate([sol.ys[0][-1], sol.ys[1][-1]])
            counts = (sol.stats["num_steps"], sol.stats["num_rejected_steps"])
            return jnp.where(ok, y, jnp.nan), counts

        cache = {}

        def run(L, q0, v0, t1, tol):
            if "fn" not in cache:
                cache["fn"] = jax.jit(
                    jax.vmap(lambda q, v, t, r: one(L, q, v, t, r), (0, 0, None, None)),
                    compiler_options=options,
                )
            return cache["fn"](q0, v0, t1, tol)

        return run

    def batch(order):
        def run(L, q0, v0, t1, tol):
            sol = lagrax.simulate_batch(
                L, q0, v0, 0.0, t1, solver=lagrax.Taylor(order=order), rtol=tol,
                atol=tol, max_steps=1 << 17, throw=False,
            )  # fmt: skip
            ys = jnp.concatenate([sol.ys[0][:, -1], sol.ys[1][:, -1]], axis=1)
            return ys, (sol.stats["num_steps"], sol.stats["num_rejected_steps"])

        return run

    order = 16 if n > 2 else 20
    out = {
        "Dopri8": vmapped(dfx.Dopri8()),
        "Tsit5": vmapped(dfx.Tsit5()),
        f"simulate_batch Taylor-{order}": batch(order),
    }
    if n <= 2:
        out["simulate Taylor-12"] = vmapped(lagrax.Taylor(order=12), ELEMENTAL)
    return out


def heyoka_method(system, n):
    import heyoka as hy

    built = {}

    def run(q0, v0, t1, tol):
        if tol not in built:
            simd = hy.recommended_simd_size()
            ta = hy.taylor_adaptive_batch(
                _heyoka_system(system, n), np.zeros((2 * n, simd)), tol=tol
            )
            built[tol] = (ta, simd)
        ta, simd = built[tol]
        B = len(q0)
        pad = -B % simd
        y0 = np.concatenate([q0, v0], axis=1)
        y0 = np.concatenate([y0, np.repeat(y0[-1:], pad, 0)])
        out = np.empty_like(y0)
        steps = np.zeros(len(y0))
        for start in range(0, len(y0), simd):
            ta.set_time(0.0)
            ta.state[:] = y0[start : start + simd].T
            ta.propagate_until(t1)
            out[start : start + simd] = ta.state.T
            steps[start : start + simd] = [r[3] for r in ta.propagate_res]
        return out[:B], (steps[:B], np.zeros(B))

    return run


# ------------------------------------------------------------------- period estimate


def period_cases(quick, cache):
    """name -> (L, q0, exact periods): the pendulum over 0.01 .. pi - 1e-3 and the
    asymmetric well to 0.99 of its hump, references to 40 digits (cached)."""
    from lagrax.systems import asymmetric_well, pendulum

    out = {}
    for name, L, q0, exact in [
        (
            "pendulum",
            pendulum.lagrangian(),
            np.linspace(0.01, np.pi - 1e-3, 256 if quick else 2047),
            exact_periods.pendulum_period,
        ),
        (
            "asymmetric_well",
            asymmetric_well.lagrangian(),
            exact_periods.hump_releases(64 if quick else 256),
            exact_periods.well_period,
        ),
    ]:
        path = pathlib.Path(cache) / f"periods_{name}_{len(q0)}.npy"
        if path.exists():
            T = np.load(path)
        else:
            T = np.array([exact(x) for x in q0])
            path.parent.mkdir(parents=True, exist_ok=True)
            np.save(path, T)
        out[name] = (L, q0, T)
    return out


def run_periods(quick, cache, rtols, methods=None, solvers=None):
    """Per system, method, solver and rtol: the true relative error of each period and
    its estimate over it (median, 5th percentile, smallest), the lanes reported
    `tolerance_not_met` and those returned with an estimate below their true
    error."""
    rows = []
    steppers = {
        "Taylor": lagrax.Taylor(),
        "Dopri8": dfx.Dopri8(),
        "Tsit5": dfx.Tsit5(),
        "Dopri5": dfx.Dopri5(),
    }
    for system, (L, q0, T) in period_cases(quick, cache).items():
        for method in ("matched", "half", "full", "quarter"):
            if methods and method not in methods:
                continue
            if method == "quarter" and system != "pendulum":
                continue  # (not mirror-symmetric: refused)
            for sname, solver in steppers.items():
                if solvers and sname not in solvers:
                    continue
                for rtol in rtols:
                    res = lagrax.sweep_periods(
                        L, jnp.asarray(q0), solver=solver, method=method,
                        rtol=rtol, atol=rtol,
                    )  # fmt: skip
                    status = np.asarray(res.status)
                    ok = status == 0
                    true = np.abs(np.asarray(res.periods)[ok] / T[ok] - 1)
                    est = np.asarray(res.error_estimate)[ok]
                    ratio = est / np.maximum(true, 1e-300)
                    rows.append(
                        dict(
                            system=system, method=method, solver=sname, rtol=rtol,
                            lanes=len(q0), success=int(ok.sum()),
                            tolerance_not_met=int((status == 12).sum()),
                            other_failures=int((~ok & (status != 12)).sum()),
                            max_error=float(true.max()),
                            median_error=float(np.median(true)),
                            median_ratio=float(np.median(ratio)),
                            p5_ratio=float(np.percentile(ratio, 5)),
                            min_ratio=float(ratio.min()),
                            below=int((est < true).sum()),
                            median_estimate=float(np.median(est)),
                        )
                    )  # fmt: skip
                    print(_fmt_period(rows[-1]), flush=True)
    return rows


def _fmt_period(r):
    return (
        f"{r['system']:15s} {r['method']:8s} {r['solver']:7s} rtol={r['rtol']:.0e} "
        f"ok {r['success']}/{r['lanes']} unmet {r['tolerance_not_met']} "
        f"max err {r['max_error']:.1e} med err {r['median_error']:.1e} | "
        f"est/true median {r['median_ratio']:7.1f} p5 {r['p5_ratio']:6.2f} "
        f"min {r['min_ratio']:6.2f} below {r['below']}"
    )


# ------------------------------------------------------------------------------ main


def errors(ys, ref):
    err = np.max(np.abs(np.asarray(ys) - ref), axis=1)
    err = np.where(np.isfinite(err), err, np.inf)
    return float(np.max(err)), float(np.median(err))


def run_system(system, tols, quick, repeats, cache, methods=None):
    q0, v0, t1 = _releases(system, quick)
    n = q0.shape[1]
    t = time.perf_counter()
    ref = reference(system, quick, cache)
    print(f"{system}: {len(q0)} releases, reference {time.perf_counter() - t:.1f} s")
    L = _lagrangian(system)
    rows = []
    todo = dict(lagrax_methods(system, n))
    todo["heyoka.py"] = None
    heyoka = heyoka_method(system, n)
    for name, run in todo.items():
        if methods and not any(m in name for m in methods):
            continue
        compile_s = None
        for tol in tols:
            if run is None:
                start = time.perf_counter()
                ys, steps = heyoka(q0, v0, t1, tol)
                build = time.perf_counter() - start
                (ys, steps), seconds = _best(lambda: heyoka(q0, v0, t1, tol), repeats)
                compile_s = build - seconds
            else:
                args = (jnp.asarray(q0), jnp.asarray(v0), jnp.asarray(t1))
                tol_ = jnp.asarray(tol)
                start = time.perf_counter()
                if compile_s is None:
                    jax.block_until_ready(run(L, *args, tol_))
                    compile_s = time.perf_counter() - start
                (ys, steps), seconds = _best(lambda: run(L, *args, tol_), repeats)
            worst, median = errors(ys, ref)
            steps, rejected = (float(np.nanmean(np.asarray(c))) for c in steps)
            rows.append(
                dict(
                    system=system, method=name, tol=tol, max_error=worst,
                    median_error=median, steps=steps, rejected=rejected,
                    seconds=seconds, compile_seconds=compile_s,
                )
            )  # fmt: skip
    dopri = {r["tol"]: r["max_error"] for r in rows if r["method"] == "Dopri8"}
    for r in rows:
        r["vs_dopri8"] = r["max_error"] / dopri[r["tol"]] if r["tol"] in dopri else None
        print(_fmt(r), flush=True)
    return rows


def _fmt(r):
    vs = f"{r['vs_dopri8']:7.2f}" if r["vs_dopri8"] is not None else "       "
    return (
        f"{r['system']:15s} {r['method']:26s} tol={r['tol']:.0e} "
        f"max={r['max_error']:.2e} median={r['median_error']:.2e} "
        f"vs Dopri8 {vs}  steps={r['steps']:8.1f} (rejected {r['rejected']:6.1f}) "
        f"t={r['seconds'] * 1e3:9.2f} ms"
    )


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument(
        "--systems", nargs="*",
        default=["double_pendulum", "chain4", "kepler", "separatrix"],
    )  # fmt: skip
    p.add_argument("--methods", nargs="*", default=None, help="name substrings")
    p.add_argument("--tols", nargs="*", type=float, default=None)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument(
        "--cache",
        default=os.path.join(tempfile.gettempdir(), "lagrax_accuracy_reference"),
    )
    p.add_argument("--out", default=None)
    p.add_argument(
        "--periods", action="store_true",
        help="the period sweeps' error estimates instead (sweep_periods)",
    )  # fmt: skip
    p.add_argument("--period-methods", nargs="*", default=None)
    p.add_argument("--period-solvers", nargs="*", default=None)
    args = p.parse_args()
    if args.periods:
        rtols = args.tols or [1e-13, 1e-10]
        rows = run_periods(
            args.quick, args.cache, rtols, args.period_methods, args.period_solvers
        )
        name = f"accuracy_periods{'_quick' if args.quick else ''}.json"
        out = args.out or RESULTS / name
        with open(out, "w") as f:
            json.dump(dict(rows=rows), f, indent=1)
        print(f"wrote {out}")
        return
    tols = args.tols or TOLS
    rows = []
    for system in args.systems:
        rows += run_system(
            system, tols, args.quick, args.repeats, args.cache, args.methods
        )
    meta = dict(
        machine=f"{platform.machine()} {platform.processor()} {os.cpu_count()} cores",
        jax=jax.__version__,
        quick=args.quick,
        error="max-norm of (q, qdot) at t1 against heyoka.py in long double",
    )
    out = args.out or RESULTS / f"accuracy{'_quick' if args.quick else ''}.json"
    with open(out, "w") as f:
        json.dump(dict(meta=meta, rows=rows), f, indent=1)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
