r"""Where methods fail: long horizons, stiffness, coordinate singularities, float32.

Four experiments, each reporting failures through diffrax's `result` (or, where the
solver says "successful" with a wrong answer, through a check of the physics):

1. *Long horizons.* For $10^5$ periods ($10^3$ with `--quick`, or `--periods N`):
   the pendulum $L = \frac12\dot\theta^2 + \cos\theta$ released at 2.5 rad, the
   double pendulum from rest at (0.5, -0.3) rad, and the spherical pendulum (whose
   azimuth is cyclic: Noether momentum $p_\phi$). Energy (and $p_\phi$) error against
   time for `lagrax.VariationalMidpoint`, `lagrax.GaussLegendre4` and
   `lagrax.GaussLegendre6` at the same step $h = T/40$, Tsit5 at $T/20$ (about
   the midpoint rule's evaluations: ~3 Newton iterations per midpoint step, 6 stages
   per Tsit5 step), and for the pendulum Tsit5 adaptive at rtol = atol = 1e-8.
2. *Stiffness.* A pendulum on a very stiff spring ($k = 10^8$: spring frequency $10^4$
   against ~1), $t_1 = 10$, rtol = atol = 1e-6 and `max_steps` = 4096: explicit Tsit5,
   Dopri5, Dopri8 against implicit Kvaerno5 and the variational integrator ($h=0.01$,
   which steps over the spring's period: it is stable there, not accurate in the fast
   mode). Status, steps, step-size history and energy error.
3. *Coordinate singularity.* Huygens' cycloid in the seed's $\theta$ (mass
   $2mR^2(1-\cos\theta)$, zero at the cusps $\theta = 0, 2\pi$) released from rest at
   $\theta_0 = 10^{-2}, 10^{-5}, 10^{-8}$, and at the cusp, over one period
   $4\pi$ (exact: back at $\theta_0$), Tsit5 at 1e-10 through `lagrax.simulate`;
   against the same pendulum in $u = \cos(\theta/2)$ (`cycloid.lagrangian_u`), a
   harmonic oscillator. Reported: status, steps, final error, and the physics check
   that catches a "successful" garbage run (θ leaving the arch $[0, 2\pi]$).
4. *float32 against float64.* The pendulum over one exact period with Tsit5 at
   rtol = atol = 1e-3 … 1e-12 (and the variational integrator over step sizes), in
   each dtype: where float32 stops giving more accuracy.

Usage: `python benchmarks/stability.py [--quick] [--periods N]`. Writes
`benchmarks/results/stability.json` and `stability_{long,stiff,cusp,float32}.png`
(`*_quick*` with `--quick`).
"""

import argparse
import json
import os
import pathlib
import platform
import time
import warnings

import jax


jax.config.update("jax_enable_x64", True)

import diffrax as dfx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lagrax  # noqa: E402
from lagrax.systems import cycloid, pendulum  # noqa: E402


# Cold compiles, as measured: the library's disk cache of executables off.
os.environ["LAGRAX_CACHE_DIR"] = ""


RESULTS = pathlib.Path(__file__).parent / "results"
PENDULUM = pendulum.lagrangian()
AMPLITUDE = 2.5


def _status(sol):
    return str(dfx.RESULTS[sol.result]) or "successful"


def elastic_lagrangian(k):
    def L(q, qdot, t):
        r, theta = q
        kinetic = 0.5 * (qdot[0] ** 2 + r**2 * qdot[1] ** 2)
        return kinetic - 0.5 * k * (r - 1.0) ** 2 + r * jnp.cos(theta)

    return L


def elastic_start(k):
    return (jnp.array([1.0 + np.cos(1.0) / k, 1.0]), jnp.array([0.0, 0.0]))


def _energies(L, qs, qdots):
    return np.asarray(jax.vmap(lambda q, v: lagrax.energy(L, q, v, 0.0))(qs, qdots))


def _run_long(L, y0, solver, dt, tol, t1, ts, windows, invariants):
    """One long solve, sampled at `ts`; the invariants' errors there.

    `windows` maps a name to a boolean mask over `ts` (the first and the last periods,
    sampled at every step): the maxima over those windows are what is compared, so
    that early and late errors are both maxima over many phases of the motion.
    """
    if tol is None:
        controller = dfx.ConstantStepSize()
    else:
        controller = dfx.PIDController(rtol=tol, atol=tol)
    start = time.perf_counter()
    sol = dfx.diffeqsolve(
        lagrax.LagrangianTerm(L),
        solver,
        0.0,
        t1,
        dt,
        y0,
        saveat=dfx.SaveAt(ts=ts),
        stepsize_controller=controller,
        max_steps=None,
        throw=False,
    )
    jax.block_until_ready(sol)
    seconds = time.perf_counter() - start
    t = np.asarray(sol.ts)
    # For the chart: every sample outside the dense windows, ~1000 inside each.
    keep = np.ones(len(t), bool)
    for mask in windows.values():
        idx = np.flatnonzero(mask)
        keep[idx] = False
        keep[idx[:: max(len(idx) // 1000, 1)]] = True
    out = dict(
        status=_status(sol),
        steps=int(sol.stats["num_steps"]),
        seconds_including_compile=seconds,
        t=t[keep].tolist(),
    )
    for name, f in invariants.items():
        values = np.asarray(jax.vmap(lambda q, v: f(L, q, v, 0.0))(*sol.ys))
        err = np.abs(values - float(f(L, *y0, 0.0)))
        out[f"{name}_error"] = err[keep].tolist()
        for window, mask in windows.items():
            out[f"{name}_error_max_{window}"] = float(err[mask].max())
        out[f"{name}_error_max"] = float(err.max())
    return out


def _energy(L, q, qdot, t):
    return lagrax.energy(L, q, qdot, t)


def _p_phi(L, q, qdot, t):
    return lagrax.momenta(L, q, qdot, t)[1]


def long_horizon(periods, samples=4000, only=None):
    """Energy (and, for the spherical pendulum, Noether momentum) over `periods`.

    `only`: names of the systems to run (default all three).

    Three systems: the pendulum at 2.5 rad (period T exact), the double pendulum from
    rest at (0.5, -0.3) rad (T: the slow normal mode's period, 8.2), the spherical
    pendulum from θ = 1, θ̇ = 0.2, φ̇ = 1.3 (T: 2π/φ̇₀; φ is cyclic, so p_φ is
    conserved exactly by a variational integrator). Fixed steps T/40 (midpoint,
    Gauss–Legendre 4 and 6), T/20 (Tsit5); adaptive Tsit5 at 1e-8 for the pendulum.
    Compared: the largest error over every step of the first 100 periods against
    that over the last 100.
    """
    from lagrax.systems import double_pendulum, spherical_pendulum

    T_pend = float(pendulum.period(AMPLITUDE))
    T_dp = float(2 * np.pi / double_pendulum.normal_mode_frequencies()[0])
    T_sph = 2 * np.pi / 1.3
    systems = {
        "pendulum": (PENDULUM, (jnp.array([AMPLITUDE]), jnp.array([0.0])), T_pend,
                     dict(energy=_energy)),
        "double_pendulum": (double_pendulum.lagrangian(),
                            (jnp.array([0.5, -0.3]), jnp.array([0.0, 0.0])), T_dp,
                            dict(energy=_energy)),
        "spherical_pendulum": (spherical_pendulum.lagrangian(),
                               (jnp.array([1.0, 0.0]), jnp.array([0.2, 1.3])), T_sph,
                               dict(energy=_energy, p_phi=_p_phi)),
    }  # fmt: skip
    if only is not None:
        systems = {k: v for k, v in systems.items() if k in only}
    out = {}
    for sysname, (L, y0, T, invariants) in systems.items():
        h = T / 40
        runs = {
            "VariationalMidpoint h=T/40": (lagrax.VariationalMidpoint(), h, None),
            "GaussLegendre4 h=T/40": (lagrax.GaussLegendre4(), h, None),
            "GaussLegendre6 h=T/40": (lagrax.GaussLegendre6(), h, None),
            "Tsit5 h=T/20": (dfx.Tsit5(), 2 * h, None),
        }
        if sysname == "pendulum":
            runs["Tsit5 adaptive 1e-8"] = (dfx.Tsit5(), None, 1e-8)
        t1 = 40 * periods * h
        rows = {}
        for name, (solver, dt, tol) in runs.items():
            # Every step of the first and of the last `dense` periods, log-spaced
            # steps in between (on the step grid: between steps the output would be
            # the linear interpolant, whose error is not the integrator's; adaptive
            # Tsit5 is sampled on the T/40 grid).
            per = round(T / (dt or h))
            total = per * periods
            dense = min(100, periods // 10) * per
            k = np.unique(np.concatenate([
                np.arange(1, dense + 1),
                np.round(np.geomspace(dense, total - dense, samples)).astype(int),
                np.arange(total - dense, total + 1),
            ]))  # fmt: skip
            ts = jnp.asarray(k * (dt or h))
            windows = {
                "first_periods": k <= dense,
                "last_periods": k >= total - dense,
            }
            row = _run_long(L, y0, solver, dt, tol, t1, ts, windows, invariants)
            rows[name] = row
            extra = (
                f", max|dp_phi| {row['p_phi_error_max']:.2e}"
                if "p_phi" in invariants
                else ""
            )
            print(
                f"long horizon {periods} periods, {sysname}, {name:28s} "
                f"{row['status']}, {row['steps']} steps, "
                f"{row['seconds_including_compile']:.0f} s, |dE| max over the first "
                f"{dense // per} periods {row['energy_error_max_first_periods']:.2e}, "
                f"over the last {row['energy_error_max_last_periods']:.2e}{extra}",
                flush=True,
            )
        out[sysname] = dict(period=T, y0=[np.asarray(x).tolist() for x in y0],
                            window_periods=dense // per, runs=rows)  # fmt: skip
    return dict(periods=periods, systems=out)


def stiffness(k=1e8, t1=10.0, max_steps=4096):
    L = elastic_lagrangian(k)
    y0 = elastic_start(k)
    E0 = float(lagrax.energy(L, *y0))
    out = {}
    runs = {
        "Tsit5": dfx.Tsit5(),
        "Dopri5": dfx.Dopri5(),
        "Dopri8": dfx.Dopri8(),
        "Kvaerno5": dfx.Kvaerno5(),
        "VariationalMidpoint h=0.01": lagrax.VariationalMidpoint(),
        "GaussLegendre4 h=0.01": lagrax.GaussLegendre4(),
    }
    for name, solver in runs.items():
        fixed = name.endswith("h=0.01")
        start = time.perf_counter()
        sol = dfx.diffeqsolve(
            lagrax.LagrangianTerm(L),
            solver,
            0.0,
            t1,
            0.01 if fixed else None,
            y0,
            saveat=dfx.SaveAt(steps=True),
            stepsize_controller=dfx.ConstantStepSize()
            if fixed
            else dfx.PIDController(rtol=1e-6, atol=1e-6),
            max_steps=max_steps,
            throw=False,
        )
        jax.block_until_ready(sol)
        seconds = time.perf_counter() - start
        ts = np.asarray(sol.ts)
        keep = np.isfinite(ts)
        qs, qdots = (np.asarray(x)[keep] for x in sol.ys)
        err = np.abs(_energies(L, jnp.asarray(qs), jnp.asarray(qdots)) - E0)
        out[name] = dict(
            status=_status(sol),
            steps=int(sol.stats["num_steps"]),
            reached_t=float(ts[keep][-1]),
            seconds_including_compile=seconds,
            dt=np.diff(np.concatenate([[0.0], ts[keep]])).tolist(),
            t=ts[keep].tolist(),
            energy_error_max=float(err.max()),
        )
        print(
            f"stiff k={k:g}: {name:28s} {out[name]['status'][:40]:40s} "
            f"steps={out[name]['steps']:5d} reached t={out[name]['reached_t']:.3g} "
            f"max|dE|={err.max():.2e}",
            flush=True,
        )
    return dict(k=k, t1=t1, max_steps=max_steps, runs=out)


def cusp_check(theta):
    """The physics check: on one arch, theta stays in [0, 2π]."""
    theta = np.asarray(theta)
    return bool(np.all((theta >= 0) & (theta <= 2 * np.pi)))


def coordinate_singularity(starts=(1e-2, 1e-5, 1e-8, 0.0)):
    t1 = 4 * np.pi  # one period, for every amplitude
    ts = jnp.linspace(0.0, t1, 401)
    Lt, Lu = cycloid.lagrangian(), cycloid.lagrangian_u()
    out = []
    for theta0 in starts:
        row = dict(theta0=theta0)
        try:
            sol = lagrax.simulate(
                Lt,
                jnp.array([theta0]),
                jnp.array([0.0]),
                0.0,
                t1,
                rtol=1e-10,
                atol=1e-10,
                saveat=dfx.SaveAt(ts=ts),
                max_steps=100_000,
                throw=False,
            )
            theta = np.asarray(sol.ys[0][:, 0])
            ok = np.isfinite(theta)
            row["theta_form"] = dict(
                status=_status(sol),
                steps=int(sol.stats["num_steps"]),
                final_error=float(abs(theta[ok][-1] - theta0)) if ok.any() else None,
                stays_on_arch=cusp_check(theta[ok]),
                theta=np.where(ok, theta, np.nan).tolist(),
            )
        except ValueError as e:  # an eager call refuses a singular start
            row["theta_form"] = dict(status=f"ValueError: {str(e).splitlines()[0]}")
        u0 = np.cos(theta0 / 2)
        sol = lagrax.simulate(
            Lu,
            jnp.array([u0]),
            jnp.array([0.0]),
            0.0,
            t1,
            rtol=1e-10,
            atol=1e-10,
            saveat=dfx.SaveAt(ts=ts),
            throw=False,
        )
        u = np.asarray(sol.ys[0][:, 0])
        exact = u0 * np.cos(np.asarray(ts) / 2)
        theta_u = np.asarray(cycloid.theta_from_u(jnp.asarray(u)))
        row["u_form"] = dict(
            status=_status(sol),
            steps=int(sol.stats["num_steps"]),
            max_error_in_u=float(np.max(np.abs(u - exact))),
            theta=theta_u.tolist(),
        )
        th = row["theta_form"]
        print(
            f"cusp theta0={theta0:g}: theta form {th['status'][:60]}, "
            f"steps={th.get('steps')}, final error={th.get('final_error')}, "
            f"stays on arch={th.get('stays_on_arch')}; u form "
            f"{row['u_form']['status']}, steps={row['u_form']['steps']}, "
            f"max error {row['u_form']['max_error_in_u']:.1e}",
            flush=True,
        )
        out.append(row)
    return dict(t=np.asarray(ts).tolist(), runs=out)


def float32_vs_float64(tols, steps):
    T = float(pendulum.period(AMPLITUDE))
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        name = jnp.dtype(dtype).name
        y0 = (jnp.array([AMPLITUDE], dtype), jnp.array([0.0], dtype))
        t0, t1 = jnp.asarray(0.0, dtype), jnp.asarray(T, dtype)
        rows = []
        for tol in tols:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # rtol below float32's epsilon
                sol = lagrax.simulate(
                    PENDULUM,
                    *y0,
                    t0,
                    t1,
                    rtol=tol,
                    atol=tol,
                    max_steps=100_000,
                    throw=False,
                )
            q, v = (float(x[-1, 0]) for x in sol.ys)
            err = max(abs(q - AMPLITUDE), abs(v))
            rows.append(
                dict(
                    solver="Tsit5",
                    tol=tol,
                    status=_status(sol),
                    dtype=str(sol.ys[0].dtype),
                    error=err,
                    steps=int(sol.stats["num_steps"]),
                )
            )
        for N in steps:
            sol = dfx.diffeqsolve(
                lagrax.LagrangianTerm(PENDULUM),
                lagrax.VariationalMidpoint(),
                t0,
                t1,
                t1 / N,
                y0,
                stepsize_controller=dfx.ConstantStepSize(),
                max_steps=N + 1,
                throw=False,
            )
            q, v = (float(x[-1, 0]) for x in sol.ys)
            rows.append(
                dict(
                    solver="VariationalMidpoint",
                    h=T / N,
                    status=_status(sol),
                    dtype=str(sol.ys[0].dtype),
                    error=max(abs(q - AMPLITUDE), abs(v)),
                    steps=int(sol.stats["num_steps"]),
                )
            )
        out[name] = rows
        for r in rows:
            setting = f"tol={r['tol']:.0e}" if "tol" in r else f"h={r['h']:.1e}"
            print(
                f"{name} {r['solver']:20s} {setting:10s} {r['status'][:30]:12s} "
                f"error={r['error']:.2e} steps={r['steps']}",
                flush=True,
            )
    return out


def _plt():
    import matplotlib.pyplot as plt

    return plt


def figure_long(long):
    plt = _plt()
    systems = long["systems"]
    panels = [(name, "energy") for name in systems] + [
        (name, "p_phi") for name, sysrow in systems.items()
        if any("p_phi_error" in r for r in sysrow["runs"].values())
    ]  # fmt: skip
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.2))
    for ax, (sysname, what) in zip(axes, panels):
        sysrow = systems[sysname]
        for name, run in sysrow["runs"].items():
            t = np.asarray(run["t"]) / sysrow["period"]
            err = np.maximum(run[f"{what}_error"], 1e-17)
            ax.loglog(t, err, lw=0.7, label=name)
        ax.set_xlabel("time [periods]")
        ax.set_ylabel("|E(t) - E(0)|" if what == "energy" else "|p_φ(t) - p_φ(0)|")
        ax.set_title(f"{sysname}: {what}", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=6)
    fig.suptitle(
        f"Invariants over {long['periods']:g} periods (fixed steps per period)"
    )
    fig.tight_layout()
    return fig


def figure_stiff(stiff):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, run in stiff["runs"].items():
        label = f"{name}: {run['status'][:28]} ({run['steps']} steps)"
        ax.semilogy(run["t"], np.maximum(run["dt"], 1e-17), lw=0.8, label=label)
    ax.set_xlabel("t")
    ax.set_ylabel("step size")
    ax.set_title(
        f"Stiff spring k={stiff['k']:g}: step sizes (max_steps={stiff['max_steps']})"
    )
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return fig


def figure_cusp(cusp):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    t = np.asarray(cusp["t"])
    for i, row in enumerate(cusp["runs"]):
        color = f"C{i}"
        if "theta" in row["theta_form"]:
            ax.plot(
                t, row["theta_form"]["theta"], color=color, lw=1.2,
                label=f"θ form, θ0={row['theta0']:g}",
            )  # fmt: skip
        ax.plot(
            t, row["u_form"]["theta"], color=color, ls="--", lw=1.0,
            label=f"u form, θ0={row['theta0']:g}",
        )  # fmt: skip
    ax.axhline(2 * np.pi, color="k", lw=0.5)
    ax.set_xlabel("t")
    ax.set_ylabel("θ (cusps at 0 and 2π)")
    ax.set_title("Cycloid near the cusp: θ coordinate against u = cos(θ/2)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def figure_float32(f32):
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4.2))
    for name, rows in f32.items():
        good = [r for r in rows if r["status"] == "successful"]
        rk = [r for r in good if r["solver"] == "Tsit5"]
        vi = [r for r in good if r["solver"] != "Tsit5"]
        a1.loglog([r["tol"] for r in rk], [max(r["error"], 1e-17) for r in rk], "o-",
                  label=name)  # fmt: skip
        a2.loglog([r["h"] for r in vi], [max(r["error"], 1e-17) for r in vi], "o-",
                  label=name)  # fmt: skip
    a1.invert_xaxis()
    a1.set_xlabel("rtol = atol (Tsit5)")
    a2.set_xlabel("step h (VariationalMidpoint)")
    a1.set_ylabel("error after one period")
    for a in (a1, a2):
        a.grid(True, which="both", alpha=0.3)
        a.legend()
    fig.suptitle("float32 against float64: the pendulum at 2.5 rad")
    fig.tight_layout()
    return fig


def plot(results, suffix):
    import matplotlib

    matplotlib.use("Agg")
    plt = _plt()
    figures = {
        "long": figure_long(results["long_horizon"]),
        "stiff": figure_stiff(results["stiffness"]),
        "cusp": figure_cusp(results["coordinate_singularity"]),
        "float32": figure_float32(results["float32_vs_float64"]),
    }
    for name, fig in figures.items():
        fig.savefig(RESULTS / f"stability_{name}{suffix}.png", dpi=110)
        plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a small, fast run")
    parser.add_argument("--periods", type=int, default=None, help="long-run length")
    args = parser.parse_args()
    periods = args.periods or (1_000 if args.quick else 100_000)
    tols = [10.0**-k for k in range(3, 13)]
    steps = [2**k for k in range(4, 12 if args.quick else 16)]
    results = dict(
        meta=dict(
            machine=f"{platform.machine()} {os.cpu_count()} cores (shared, noisy)",
            jax=jax.__version__,
            quick=args.quick,
            periods=periods,
        ),
        long_horizon=long_horizon(periods),
        stiffness=stiffness(max_steps=1024 if args.quick else 4096),
        coordinate_singularity=coordinate_singularity(),
        float32_vs_float64=float32_vs_float64(tols, steps),
    )
    suffix = "_quick" if args.quick else ""
    RESULTS.mkdir(exist_ok=True)
    plot(results, suffix)
    with open(RESULTS / f"stability{suffix}.json", "w") as f:
        json.dump(results, f)
    print(f"wrote {RESULTS}/stability{suffix}.json and stability_*{suffix}.png")


if __name__ == "__main__":
    main()
