"""Periods per second over a pendulum amplitude sweep, against the exact period.

4096 amplitudes 0.01–3.1 rad (g = r = 1), period by integration to the turning point,
float64, max relative error against the AGM period. Side by side in one run:

- scipy `solve_ivp` DOP853 + terminal event on θ̇, a Python loop (a subsample, timed and
  extrapolated to the whole sweep);
- a hand-written naive diffrax baseline: `-sin θ`, Dopri8, Event on θ̇ with Newton
  root finding on the dense output, one unsorted `jit(vmap(...))` batch of all 4096;
- `lagrax.sweep_periods`, method "half" (the same quantity as the others: T = 2 × time
  to the next turning point) and method "quarter" (T = 4 × time to maximum speed);
- heyoka.py: its `lagrangian()` and scalar Taylor integrator with a terminal event, a
  Python loop over the amplitudes.

Usage: `python benchmarks/sweep.py [--quick]`; writes benchmarks/results/sweep.json and
sweep.png.
"""

import argparse
import json
import os
import platform
import time

import jax


jax.config.update("jax_enable_x64", True)

import diffrax as dfx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402

import lagrax  # noqa: E402
from lagrax.systems import pendulum  # noqa: E402


HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")


def best_of(fn, repeats):
    times = []
    out = None
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return out, min(times), float(np.median(times))


def scipy_periods(a, rtol, atol):
    from scipy.integrate import solve_ivp

    def f(t, y):
        return [y[1], -np.sin(y[0])]

    def turning(t, y):
        return y[1]

    turning.terminal = True
    turning.direction = 1.0  # θ̇: 0 -> negative -> 0 at the far turning point
    T = np.empty_like(a)
    for i, x in enumerate(a):
        sol = solve_ivp(
            f,
            (0, 1e3),
            [x, 0.0],
            method="DOP853",
            rtol=rtol,
            atol=atol,
            events=turning,
        )
        T[i] = 2 * sol.t_events[0][0]
    return T


def naive_diffrax(rtol, atol):
    def f(t, y, args):
        return y[1], -jnp.sin(y[0])

    event = dfx.Event(
        lambda t, y, args, **kw: -y[1],
        root_finder=optx.Newton(rtol=1e-12, atol=1e-12),
        direction=False,
    )

    @jax.jit
    @jax.vmap
    def periods(x):
        sol = dfx.diffeqsolve(
            dfx.ODETerm(f),
            dfx.Dopri8(),
            0.0,
            1e3,
            None,
            (x, 0.0 * x),
            stepsize_controller=dfx.PIDController(rtol=rtol, atol=atol),
            event=event,
            max_steps=4096,
            throw=False,
        )
        return 2 * sol.ts[-1], sol.stats["num_steps"]

    return periods


def heyoka_periods(a):
    import heyoka as hy

    x, v = hy.make_vars("x", "v")
    system = hy.lagrangian(0.5 * v**2 + hy.cos(x), [x], [v])
    ev = hy.t_event(v, direction=hy.event_direction.positive)
    ta = hy.taylor_adaptive(system, [1.0, 0.0], t_events=[ev])

    def run():
        T = np.empty_like(a)
        for i in range(len(a)):
            ta.time = 0.0
            ta.state[:] = (a[i], 0.0)
            ta.propagate_until(1e3)
            T[i] = 2 * ta.time
        return T

    return run, hy.__version__


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true", help="small run")
    args = parser.parse_args()
    n = 512 if args.quick else 4096
    repeats = 2 if args.quick else 3
    a_np = np.linspace(0.01, 3.1, n)
    a = jnp.asarray(a_np)
    exact = np.asarray(pendulum.pendulum_period(a))
    rows = {}

    def record(name, T, best, median, compile_s=None, note="", **extra):
        err = float(np.max(np.abs(np.asarray(T) / exact[: len(T)] - 1)))
        rows[name] = dict(
            periods_per_s=len(T) / best if best else None,
            best_s=best,
            median_s=median,
            compile_s=compile_s,
            max_rel_error=err,
            n=len(T),
            note=note,
            **extra,
        )
        print(
            f"{name:<28} {len(T) / best:>12,.0f} periods/s  max rel err {err:.1e}"
            f"  {note}"
        )

    # scipy, a subsample, extrapolated.
    step = 32 if not args.quick else 16
    sub = a_np[::step]
    t = time.perf_counter()
    T_sc = scipy_periods(sub, 1e-13, 1e-13)
    dt = time.perf_counter() - t
    err = float(np.max(np.abs(T_sc / exact[::step] - 1)))
    rows["scipy DOP853 loop"] = dict(
        periods_per_s=len(sub) / dt,
        best_s=dt * n / len(sub),
        max_rel_error=err,
        n=len(sub),
        note=f"every {step}th amplitude timed, extrapolated; rtol=atol=1e-13",
    )
    print(
        f"{'scipy DOP853 loop':<28} {len(sub) / dt:>12,.0f} periods/s  max rel err "
        f"{err:.1e}  (subsample of {len(sub)}, extrapolated)"
    )

    # naive diffrax: one unsorted batch.
    for tol in (1e-13, 1e-14):
        fn = naive_diffrax(tol, tol)
        t = time.perf_counter()
        jax.block_until_ready(fn(a))
        comp = time.perf_counter() - t
        (T, steps), best, med = best_of(lambda: fn(a), repeats)
        useful = float(jnp.sum(steps) / (jnp.max(steps) * len(steps)))
        record(
            f"naive diffrax rtol={tol:g}",
            T,
            best,
            med,
            comp,
            note=f"one batch, useful lane-steps {useful:.0%}",
            useful_fraction=useful,
        )

    L = pendulum.lagrangian()
    for method, tol in (("half", 1e-14), ("quarter", 1e-13)):
        for chunk in (256, 512):
            run = lambda: lagrax.sweep_periods(
                L, a, method=method, rtol=tol, atol=tol, chunk_size=chunk
            )
            t = time.perf_counter()
            jax.block_until_ready(run())
            comp = time.perf_counter() - t
            res, best, med = best_of(run, repeats)
            record(
                f"lagrax {method} {tol:g} chunk {chunk}",
                res.periods,
                best,
                med,
                comp,
                note=f"useful lane-steps {float(res.useful_fraction):.0%}",
                useful_fraction=float(res.useful_fraction),
            )

    try:
        run, version = heyoka_periods(a_np)
        run()
        T, best, med = best_of(run, repeats)
        record(
            f"heyoka.py {version} (scalar)",
            T,
            best,
            med,
            note="scalar Taylor integrator, Python loop, one core",
        )
    except Exception as e:  # not installable here: say so, keep the others
        print(f"heyoka.py skipped: {e}")

    os.makedirs(RESULTS, exist_ok=True)
    meta = dict(
        machine=f"{platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores (shared, noisy)",
        jax=jax.__version__,
        n=n,
        quick=args.quick,
    )
    with open(os.path.join(RESULTS, "sweep.json"), "w") as f:
        json.dump(dict(meta=meta, results=rows), f, indent=2)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    names = list(rows)
    ax.barh(names, [rows[k]["periods_per_s"] for k in names])
    ax.set_xscale("log")
    ax.set_xlabel("periods per second (higher is better)")
    for i, k in enumerate(names):
        ax.text(
            rows[k]["periods_per_s"],
            i,
            f" {rows[k]['max_rel_error']:.0e}",
            va="center",
            fontsize=8,
        )
    ax.set_title(
        f"Pendulum sweep, {n} amplitudes 0.01–3.1 rad\n(bar label: max relative error)"
    )
    fig.tight_layout()
    fig.savefig(os.path.join(RESULTS, "sweep.png"), dpi=120)
    print("wrote", os.path.join(RESULTS, "sweep.json"), "and sweep.png")


if __name__ == "__main__":
    main()
