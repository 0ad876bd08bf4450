"""One process of the disk cache's two-process tests (`test_cache_processes.py`).

    python tests/cache_worker.py OUT.npz CASE [CASE ...]

runs each case (a public call of the library that compiles a program the disk cache
may keep) in this fresh process with the cache folder of `LAGRAX_CACHE_DIR`, and
writes every array each case returned to `OUT.npz`, and to `OUT.json` what the cache
did per case (`lagrax._cache.executables.STATS`: entries loaded, programs compiled,
written, or refused by the cache; `benchmarks/cache.py` adds the call's seconds through
`main`'s `run`). Run twice with one cache folder,
the second process loads what the first wrote: the test compares both outputs bit for
bit (and a crash shows as the exit status).
"""

import json
import sys


def _pendulum():
    import jax.numpy as jnp

    return lambda q, qd, t: 0.5 * qd[0] ** 2 + 9.81 * jnp.cos(q[0])


def _simulate(solver=None, n=1, **kwargs):
    import jax.numpy as jnp

    import lagrax

    if n == 1:
        L, q0, v0 = _pendulum(), jnp.array([1.2]), jnp.array([0.0])
    else:  # a particle in a well, its mass matrix constant: a Cholesky solve
        L = lambda q, qd, t: 0.5 * jnp.sum(qd**2) - 0.5 * jnp.sum(q**2) - q[0] ** 4
        q0 = jnp.linspace(0.3, 0.9, n)
        v0 = jnp.zeros(n).at[-1].set(0.2)
    if solver is not None:
        kwargs["solver"] = solver
    sol = lagrax.simulate(L, q0, v0, 0.0, 2.0, **kwargs)
    out = {"q": sol.ys[0], "qdot": sol.ys[1], "ts": sol.ts}
    out["steps"] = sol.stats["num_steps"]
    return out


def _cases():
    import diffrax as dfx
    import jax
    import jax.numpy as jnp

    import lagrax

    L = _pendulum()
    q0 = jnp.linspace(0.1, 3.0, 64)

    def sweep(**kw):
        res = lagrax.sweep_periods(L, q0, **kw)
        return {
            "periods": res.periods,
            "status": res.status,
            "estimate": res.error_estimate,
        }

    def dense():
        sol = lagrax.simulate(
            L,
            jnp.array([1.2]),
            jnp.array([0.0]),
            0.0,
            2.0,
            saveat=dfx.SaveAt(dense=True),
        )
        return {"dense": jax.vmap(sol.evaluate)(jnp.linspace(0.0, 2.0, 7))[0]}

    def event():
        cond = lambda t, y, args, **kw: y[0][0]
        sol = lagrax.simulate(
            L, jnp.array([1.2]), jnp.array([0.0]), 0.0, 5.0, event=dfx.Event(cond)
        )
        return {"t_event": sol.ts, "q": sol.ys[0]}

    def batch(solver=None):
        q = jnp.linspace(0.2, 2.0, 16)[:, None]
        kw = {} if solver is None else {"solver": solver}
        sol = lagrax.simulate_batch(L, q, jnp.zeros_like(q), 0.0, 3.0, **kw)
        return {"q": sol.ys[0], "qdot": sol.ys[1]}

    def grad_sweep():
        f = lambda g: jnp.mean(
            lagrax.sweep_periods(
                lambda q, qd, t: 0.5 * qd[0] ** 2 + g * jnp.cos(q[0]), q0[:16]
            ).periods
        )
        return {"dT_dg": jax.grad(f)(9.81)}

    def quadrature():
        res = lagrax.quadrature_period(L, q0[:8])
        return {"periods": res.periods, "status": res.status}

    def period(**kw):
        out = lagrax.period(L, 1.3, **kw)
        return {"period": out} if not isinstance(out, tuple) else dict(zip("te", out))

    ts = jnp.linspace(0.0, 2.0, 11)
    cases = {
        "simulate_tsit5": lambda: _simulate(),
        "simulate_dopri5": lambda: _simulate(dfx.Dopri5()),
        "simulate_dopri8": lambda: _simulate(dfx.Dopri8()),
        "simulate_kvaerno5": lambda: _simulate(dfx.Kvaerno5()),
        "simulate_taylor": lambda: _simulate(lagrax.Taylor()),
        "simulate_midpoint": lambda: _simulate(lagrax.VariationalMidpoint(), dt0=0.1),
        "simulate_gauss_legendre4": lambda: _simulate(lagrax.GaussLegendre4(), dt0=0.1),
        "simulate_gauss_legendre6": lambda: _simulate(lagrax.GaussLegendre6(), dt0=0.1),
        "simulate_three_coordinates": lambda: _simulate(n=3),
        "simulate_saveat_ts": lambda: _simulate(saveat=dfx.SaveAt(ts=ts)),
        "simulate_dense": dense,
        "simulate_event": event,
        "simulate_dt0": lambda: _simulate(dt0=0.01),
        "simulate_controller": lambda: _simulate(
            stepsize_controller=dfx.PIDController(rtol=1e-9, atol=1e-9)
        ),
        "simulate_progress_meter": lambda: _simulate(
            progress_meter=dfx.TextProgressMeter()
        ),
        "simulate_batch_taylor": batch,
        "simulate_batch_tsit5": lambda: batch(dfx.Tsit5()),
        "period": period,
        "period_quarter_estimate": lambda: period(
            method="quarter", error_estimate=True
        ),
        "quadrature_period": quadrature,
        "grad_sweep": grad_sweep,
    }
    for method in ("matched", "half", "full", "quarter"):
        for estimate in (True, False):
            name = f"sweep_{method}_{'estimate' if estimate else 'plain'}"
            cases[name] = lambda m=method, e=estimate: sweep(method=m, error_estimate=e)
    cases["sweep_dopri8"] = lambda: sweep(solver=dfx.Dopri8(), method="quarter")
    return cases


CASES = (
    "simulate_tsit5 simulate_dopri5 simulate_dopri8 simulate_kvaerno5 simulate_taylor "
    "simulate_midpoint simulate_gauss_legendre4 simulate_gauss_legendre6 "
    "simulate_three_coordinates simulate_saveat_ts simulate_dense simulate_event "
    "simulate_dt0 simulate_controller simulate_progress_meter simulate_batch_taylor "
    "simulate_batch_tsit5 period period_quarter_estimate quadrature_period grad_sweep "
    "sweep_matched_estimate sweep_matched_plain sweep_half_estimate sweep_half_plain "
    "sweep_full_estimate sweep_full_plain sweep_quarter_estimate sweep_quarter_plain "
    "sweep_dopri8"
).split()


def main(out, names, run=None):
    """`run(call) -> (result, extra)`: how each case is called, `extra` recorded
    beside the cache's figures (default: the call alone)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from lagrax._cache import executables

    cases = _cases()
    arrays, record = {}, {}
    for name in names:
        before = dict(executables.STATS)
        if run is None:
            result, extra = jax.block_until_ready(cases[name]()), {}
        else:
            result, extra = run(cases[name])
        for k, v in result.items():
            if v is not None:  # (a sweep without its estimate: None)
                arrays[f"{name}/{k}"] = np.asarray(v)
        stats = {k: v - before.get(k, 0) for k, v in executables.STATS.items()}
        record[name] = {**extra, **stats}
    np.savez(out, **arrays)
    with open(out.removesuffix(".npz") + ".json", "w") as fh:
        json.dump(record, fh, indent=1)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
