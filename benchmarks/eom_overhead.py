r"""What the autodiff equations of motion cost inside a diffrax solve.

Run time of `lagrax.accelerations` (through `lagrax.vector_field` in one
`diffrax.diffeqsolve`, and through `lagrax.simulate`) against a hand-written equation of
motion, with the same solver and the same steps, for a batch of initial conditions under
`jit(vmap(...))`:

- pendulum, $L = \frac12\dot\theta^2 + \cos\theta$, against $\ddot\theta = -\sin\theta$;
- cycloid in the seed's $\theta$ (released between $\theta = 1$ and the bottom, away
  from the cusp), against the seed's final form;
- double pendulum, against its closed-form equations of motion, and against the
  equations sympy derives (Euler–Lagrange, solved and simplified symbolically) and
  emits with `sympy.lambdify(..., "jax")`. Symbolic derivation time is reported
  separately.

Two step regimes:

- *fixed*: Tsit5 with `ConstantStepSize`, the same number of steps for every variant
  (checked): `hand`, `sympy`, `lagrax` (`vector_field` in `diffeqsolve`) and `simulate`
  (`lagrax.simulate(..., stepsize_controller=ConstantStepSize(), dt0=dt)`).
- *adaptive*: `lagrax.simulate` with its default controller (a PID controller with a
  `dtmin`), and `vector_field` in `diffeqsolve` with that same controller, against the
  hand-written EOM in `diffeqsolve` with that same controller. The
  step counts are reported and compared lane by lane: round-off differences between the
  two EOMs can change an accept/reject decision, so the ratio is also given per step.

Each compiled function is built once (compile time measured on its own); the variants
are then timed in interleaved rounds (each round runs every variant once, in a rotated
order) with `jax.block_until_ready`; the median over rounds is reported, and the ratio
of the fastest rounds as well (contention only slows a run down). The ratios are
variant / hand-written, measured in the same run.

Where lagrax offers a choice, both sides are timed in the same run: `lagrax fuse=False`
is the n <= 2 vector field without the one fusion of its outputs (lagrax's default
fuses them), and `lagrax array path` the accelerations as array operations (what
lagrax does for n > 2) instead of entry by entry.

Usage: `python benchmarks/eom_overhead.py [--quick] [--repeats N] [--batch B]
[--chain N ...] [--part all|systems|chain]`. Writes
`benchmarks/results/eom_overhead.json` and `.png` (the systems) and
`eom_overhead_chain.json` and `.png` (the chain of N pendulums against N); `*_quick.*`
with `--quick`, so a quick run does not overwrite a full one.
"""

import argparse
import json
import os
import pathlib
import platform
import statistics
import time

import jax


jax.config.update("jax_enable_x64", True)

import diffrax as dfx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lagrax  # noqa: E402
from lagrax._trajectory.simulate import default_controller  # noqa: E402
from lagrax.systems import cycloid, double_pendulum, pendulum  # noqa: E402


# Cold compiles, as measured: the library's disk cache of executables off.
os.environ["LAGRAX_CACHE_DIR"] = ""


RESULTS = pathlib.Path(__file__).parent / "results"


# ----------------------------------------------------------------------------- systems


def double_pendulum_lagrangian(m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=1.0):
    r"""$L = \frac12(m_1+m_2)l_1^2\dot\theta_1^2 + \frac12 m_2 l_2^2\dot\theta_2^2
    + m_2 l_1 l_2\dot\theta_1\dot\theta_2\cos(\theta_1-\theta_2)
    + (m_1+m_2)g l_1\cos\theta_1 + m_2 g l_2\cos\theta_2$."""

    def L(q, qdot, t):
        th1, th2 = q[0], q[1]
        w1, w2 = qdot[0], qdot[1]
        T = (
            0.5 * (m1 + m2) * l1**2 * w1**2
            + 0.5 * m2 * l2**2 * w2**2
            + m2 * l1 * l2 * w1 * w2 * jnp.cos(th1 - th2)
        )
        V = -(m1 + m2) * g * l1 * jnp.cos(th1) - m2 * g * l2 * jnp.cos(th2)
        return T - V

    return L


def double_pendulum_hand(m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=1.0):
    """The textbook closed form of the double pendulum's accelerations."""
    params = dict(m1=m1, m2=m2, l1=l1, l2=l2, g=g)
    return lambda q, qdot: double_pendulum.acceleration(q, qdot, **params)


def double_pendulum_sympy(m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=1.0):
    """Euler–Lagrange by sympy, solved for the accelerations, simplified, lambdified.

    Returns `(qddot, seconds)`, the second being the symbolic derivation time (up to and
    including `lambdify`).
    """
    import sympy as sp

    start = time.perf_counter()
    th = sp.symbols("th1 th2")
    w = sp.symbols("w1 w2")
    L = (
        sp.Rational(1, 2) * (m1 + m2) * l1**2 * w[0] ** 2
        + sp.Rational(1, 2) * m2 * l2**2 * w[1] ** 2
        + m2 * l1 * l2 * w[0] * w[1] * sp.cos(th[0] - th[1])
        + (m1 + m2) * g * l1 * sp.cos(th[0])
        + m2 * g * l2 * sp.cos(th[1])
    )
    L = sp.nsimplify(L)
    M = sp.Matrix(2, 2, lambda i, j: sp.diff(L, w[i], w[j]))
    rhs = sp.Matrix(
        [
            sp.diff(L, th[i]) - sum(sp.diff(L, w[i], th[j]) * w[j] for j in range(2))
            for i in range(2)
        ]
    )
    acc = [sp.simplify(e) for e in M.LUsolve(rhs)]
    f = sp.lambdify([*th, *w], acc, "jax")
    seconds = time.perf_counter() - start

    def qddot(q, qdot):
        return jnp.stack(f(q[0], q[1], qdot[0], qdot[1]))

    return qddot, seconds


def double_pendulum_particles(m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=1.0):
    r"""The double pendulum as people write it from particles: bob velocities as
    vectors (`jnp.array`), $v_2 = v_1 + \dots$, $T = \sum \frac12 m\, v\cdot v$."""

    def L(q, qdot, t):
        th1, th2 = q[0], q[1]
        w1, w2 = qdot[0], qdot[1]
        v1 = l1 * w1 * jnp.array([jnp.cos(th1), jnp.sin(th1)])
        v2 = v1 + l2 * w2 * jnp.array([jnp.cos(th2), jnp.sin(th2)])
        y1 = -l1 * jnp.cos(th1)
        y2 = y1 - l2 * jnp.cos(th2)
        T = 0.5 * m1 * jnp.dot(v1, v1) + 0.5 * m2 * jnp.dot(v2, v2)
        V = m1 * g * y1 + m2 * g * y2
        return T - V

    return L


def chain_particles(N, m=1.0, l=1.0, g=1.0):
    r"""A chain of N pendulums written from particles: bob k's velocity is
    $v_k = v_{k-1} + l\dot\theta_k(\cos\theta_k, \sin\theta_k)$ (a `jnp.array`),
    $T = \sum_k \frac12 m\, v_k\cdot v_k$, $V = \sum_k m g y_k$."""

    def L(q, qdot, t):
        v = jnp.zeros(2, q.dtype)
        y = jnp.zeros((), q.dtype)
        T = V = 0.0
        for k in range(N):
            v = v + l * qdot[k] * jnp.array([jnp.cos(q[k]), jnp.sin(q[k])])
            y = y - l * jnp.cos(q[k])
            T = T + 0.5 * m * jnp.dot(v, v)
            V = V + m * g * y
        return T - V

    return L


def chain_hand(N, m=1.0, l=1.0, g=1.0):
    r"""The chain's equations of motion written by hand, solved as lagrax solves
    (closed form for N <= 2, Cholesky beyond), so that the ratio is that of forming
    $M$ and the forcing:
    $M_{ij} = l^2 S_{\max(i,j)}\cos(\theta_i - \theta_j)$,
    $f_i = -l^2\sum_j S_{\max(i,j)}\sin(\theta_i - \theta_j)\dot\theta_j^2
    - g l S_i \sin\theta_i$, with $S_k = m(N - k)$ the mass at and below bob k
    (0-based), and $\cos, \sin(\theta_i-\theta_j)$ from the N sines and cosines."""
    from lagrax._eom.mechanics import _solve_definite

    S = m * (N - jnp.arange(N))
    Smax = jnp.minimum(S[:, None], S[None, :])

    def acc(q, qdot):
        c, s = jnp.cos(q), jnp.sin(q)
        cos_d = c[:, None] * c[None, :] + s[:, None] * s[None, :]
        sin_d = s[:, None] * c[None, :] - c[:, None] * s[None, :]
        M = l**2 * Smax * cos_d
        f = -(l**2) * (Smax * sin_d) @ (qdot**2) - g * l * S * s
        qddot, ok = _solve_definite(M, f)
        return jnp.where(ok, qddot, jnp.nan)

    return acc


def fuse_toggled(L, n):
    """lagrax's vector field without the one fusion of its outputs (the default
    fuses them for n <= 2), or None for n > 2 (no fusion there)."""
    from lagrax._eom.mechanics import _accelerations

    if n > 2:
        return None, None
    fuse = False

    def f(t, y, args):
        q, qdot = y
        return qdot, _accelerations(L, q, qdot, t, fuse=fuse)[0]

    return f"lagrax fuse={fuse}", f


def _second_order(acc):
    def f(t, y, args):
        q, qdot = y
        return qdot, acc(q, qdot)

    return f


def systems(batch, key):
    """Each system: Lagrangian, hand-written vector field(s), initial states, t1."""
    k1, k2 = jax.random.split(key)
    out = {}
    # Pendulum: amplitudes 0.1..3.0 rad from rest.
    th0 = jnp.linspace(0.1, 3.0, batch)[:, None]
    out["pendulum"] = dict(
        L=pendulum.lagrangian(),
        hand={"hand": _second_order(lambda q, qdot: pendulum.acceleration(q))},
        y0=(th0, jnp.zeros_like(th0)),
    )
    # Cycloid in θ: released from rest between θ = 1 and the bottom (π); the motion
    # stays in [θ0, 2π - θ0], at least 1 rad from either cusp.
    th0 = jnp.linspace(1.0, 3.0, batch)[:, None]
    out["cycloid"] = dict(
        L=cycloid.lagrangian(),
        hand={"hand": _second_order(lambda q, qdot: cycloid.acceleration(q, qdot))},
        y0=(th0, jnp.zeros_like(th0)),
    )
    # Double pendulum: both angles in [-1, 1] rad, small random velocities.
    q0 = jax.random.uniform(k1, (batch, 2), minval=-1.0, maxval=1.0)
    qdot0 = jax.random.uniform(k2, (batch, 2), minval=-0.5, maxval=0.5)
    sympy_acc, sympy_seconds = double_pendulum_sympy()
    out["double_pendulum"] = dict(
        L=double_pendulum_lagrangian(),
        hand={
            "hand": _second_order(double_pendulum_hand()),
            "sympy": _second_order(sympy_acc),
        },
        y0=(q0, qdot0),
        sympy_derivation_s=sympy_seconds,
    )
    out["double_pendulum_particles"] = dict(
        L=double_pendulum_particles(),
        hand=out["double_pendulum"]["hand"],
        y0=(q0, qdot0),
    )
    return out


# --------------------------------------------------------------------------- variants


def fixed_variants(system, dt, nsteps):
    """Fixed-step Tsit5 solves of one state, keyed by variant name."""
    t0 = 0.0
    t1 = dt * nsteps
    # ConstantStepSize may need one more step than nsteps if dt*nsteps rounds down; the
    # step counts are checked afterwards anyway.
    max_steps = nsteps + 1
    solver = dfx.Tsit5()
    saveat = dfx.SaveAt(t1=True)

    def through_diffrax(f):
        def solve(q0, qdot0):
            sol = dfx.diffeqsolve(
                dfx.ODETerm(f),
                solver,
                t0,
                t1,
                dt,
                (q0, qdot0),
                saveat=saveat,
                stepsize_controller=dfx.ConstantStepSize(),
                max_steps=max_steps,
            )
            return sol.ys, sol.stats["num_steps"], sol.result != dfx.RESULTS.successful

        return solve

    def through_simulate(q0, qdot0):
        sol = lagrax.simulate(
            system["L"],
            q0,
            qdot0,
            t0,
            t1,
            solver=solver,
            dt0=dt,
            stepsize_controller=dfx.ConstantStepSize(),
            max_steps=max_steps,
            throw=False,
        )
        return sol.ys, sol.stats["num_steps"], sol.result != dfx.RESULTS.successful

    variants = {name: through_diffrax(f) for name, f in system["hand"].items()}
    variants["lagrax"] = through_diffrax(lagrax.vector_field(system["L"]))
    name, f = fuse_toggled(system["L"], system["y0"][0].shape[1])
    if f is not None:
        variants[name] = through_diffrax(f)
    variants["simulate"] = through_simulate
    return variants


def adaptive_variants(system, t1, rtol, max_steps):
    """Adaptive Tsit5 solves with `simulate`'s default controller, keyed by name."""
    t0 = 0.0
    solver = dfx.Tsit5()
    saveat = dfx.SaveAt(t1=True)

    def through_diffrax(f):
        def solve(q0, qdot0):
            controller = default_controller(
                rtol, rtol, jnp.asarray(t0), jnp.asarray(t1), q0.dtype
            )
            sol = dfx.diffeqsolve(
                dfx.ODETerm(f),
                solver,
                t0,
                t1,
                None,
                (q0, qdot0),
                saveat=saveat,
                stepsize_controller=controller,
                max_steps=max_steps,
                throw=False,
            )
            return sol.ys, sol.stats["num_steps"], sol.result != dfx.RESULTS.successful

        return solve

    def through_simulate(q0, qdot0):
        sol = lagrax.simulate(
            system["L"],
            q0,
            qdot0,
            t0,
            t1,
            solver=solver,
            rtol=rtol,
            atol=rtol,
            max_steps=max_steps,
            throw=False,
        )
        return sol.ys, sol.stats["num_steps"], sol.result != dfx.RESULTS.successful

    variants = {name: through_diffrax(f) for name, f in system["hand"].items()}
    variants["lagrax"] = through_diffrax(lagrax.vector_field(system["L"]))
    name, f = fuse_toggled(system["L"], system["y0"][0].shape[1])
    if f is not None:
        variants[name] = through_diffrax(f)
    variants["simulate"] = through_simulate
    return variants


# ---------------------------------------------------------------------------- timing


def compile_all(variants, y0):
    compiled, compile_s, outputs = {}, {}, {}
    for name, solve in variants.items():
        start = time.perf_counter()
        fn = jax.jit(jax.vmap(solve)).lower(*y0).compile()
        compile_s[name] = time.perf_counter() - start
        compiled[name] = fn
        outputs[name] = jax.block_until_ready(fn(*y0))  # warm-up, and the answers
    return compiled, compile_s, outputs


def time_interleaved(compiled, y0, repeats):
    names = list(compiled)
    samples = {name: [] for name in names}
    for r in range(repeats):
        shift = r % len(names)
        for name in names[shift:] + names[:shift]:
            start = time.perf_counter()
            jax.block_until_ready(compiled[name](*y0))
            samples[name].append(time.perf_counter() - start)
    return samples


def summarize(samples, compile_s, outputs, reference="hand"):
    ref_ys = outputs[reference][0]
    ref_median = statistics.median(samples[reference])
    ref_min = min(samples[reference])
    ref_steps = np.asarray(outputs[reference][1])
    rows = {}
    for name, times in samples.items():
        ys, steps, result = outputs[name]
        steps = np.asarray(steps)
        diff = max(
            float(jnp.max(jnp.abs(a - b)))
            for a, b in zip(jax.tree.leaves(ys), jax.tree.leaves(ref_ys))
        )
        median = statistics.median(times)
        rows[name] = dict(
            median_s=median,
            min_s=min(times),
            times_s=times,
            compile_s=compile_s[name],
            ratio=median / ref_median,
            # Contention from other processes only ever slows a run down: the ratio of
            # the fastest repeats is the less noisy estimate on a shared machine.
            ratio_min=min(times) / ref_min,
            total_steps=int(steps.sum()),
            max_steps=int(steps.max()),
            lanes_with_other_step_count=int(np.sum(steps != ref_steps)),
            ratio_per_step=(median / steps.sum()) / (ref_median / ref_steps.sum()),
            failed_lanes=int(np.sum(np.asarray(result))),
            max_abs_diff_from_hand=diff,
        )
    return rows


def check_accuracy(system, y0, count=64):
    """Autodiff accelerations agree with each hand-written EOM at the initial states."""
    q, qdot = (x[:count] for x in y0)
    auto = jax.vmap(lambda q, v: lagrax.vector_field(system["L"])(0.0, (q, v), None))(
        q, qdot
    )[1]
    errors = {}
    for name, f in system["hand"].items():
        hand = jax.vmap(lambda q, v: f(0.0, (q, v), None))(q, qdot)[1]
        errors[name] = float(jnp.max(jnp.abs(auto - hand) / (1 + jnp.abs(hand))))
        if errors[name] > 1e-10:
            raise AssertionError(f"autodiff and {name} EOM disagree: {errors[name]}")
    return errors


# ------------------------------------------------------------- isolated evaluations


def unfused_accelerations(L):
    """lagrax's accelerations as array operations (its path for n > 2): the same
    forward-over-reverse derivatives and solve, not evaluated entry by entry."""
    from lagrax._eom.mechanics import _lagrange_terms, _solve_definite

    def acc(q, qdot):
        M, rhs = _lagrange_terms(L, q, qdot, jnp.zeros((), q.dtype))
        qddot, ok = _solve_definite(M, rhs)
        return jnp.where(ok, qddot, jnp.nan)

    return acc


def autodiff_accelerations(L):
    f = lagrax.vector_field(L)
    return lambda q, qdot: f(jnp.zeros((), q.dtype), (q, qdot), None)[1]


def evaluation_variants(system):
    """Accelerations alone, `acc(q, qdot)`, keyed by variant name."""
    accs = {
        name: (lambda f: lambda q, qdot: f(0.0, (q, qdot), None)[1])(f)
        for name, f in system["hand"].items()
    }
    accs["lagrax"] = autodiff_accelerations(system["L"])
    n = system["y0"][0].shape[1]
    name, f = fuse_toggled(system["L"], n)
    if f is not None:
        accs[name] = (lambda f: lambda q, qdot: f(0.0, (q, qdot), None)[1])(f)
    if n <= 2:  # beyond, lagrax evaluates it this way itself
        accs["lagrax array path"] = unfused_accelerations(system["L"])
    return accs


def time_evaluations(accs, y0, iters, repeats):
    """`iters` evaluations of each batch of accelerations in a `fori_loop` (the
    state nudged each time, so nothing is hoisted), compiled once, timed in
    interleaved rounds; ratios to "hand" of the median and of the fastest round."""

    def build(acc):  # one lane; `compile_all` vmaps it over the batch
        def run(q, qdot):
            def body(i, state):
                q, qdot = state
                return q + 1e-6 * qdot, qdot + 1e-6 * acc(q, qdot)

            return jax.lax.fori_loop(0, iters, body, (q, qdot))

        return run

    compiled, compile_s, outputs = compile_all(
        {name: build(acc) for name, acc in accs.items()}, y0
    )
    samples = time_interleaved(compiled, y0, repeats)
    ref_median = statistics.median(samples["hand"])
    ref_min = min(samples["hand"])
    lanes = y0[0].shape[0]
    return {
        name: dict(
            median_s=statistics.median(times),
            min_s=min(times),
            ns_per_lane_evaluation=1e9 * min(times) / (lanes * iters),
            compile_s=compile_s[name],
            ratio=statistics.median(times) / ref_median,
            ratio_min=min(times) / ref_min,
        )
        for name, times in samples.items()
    }


def chain_study(Ns, batch, iters, repeats, dt, nsteps, key):
    """Chains of N pendulums written from particles against the hand-written EOM."""
    out = {}
    for N in Ns:
        k1, k2 = jax.random.split(jax.random.fold_in(key, N))
        q0 = jax.random.uniform(k1, (batch, N), minval=-0.5, maxval=0.5)
        qdot0 = jax.random.uniform(k2, (batch, N), minval=-0.3, maxval=0.3)
        system = dict(
            L=chain_particles(N),
            hand={"hand": _second_order(chain_hand(N))},
            y0=(q0, qdot0),
        )
        entry = dict(accuracy=check_accuracy(system, system["y0"]))
        entry["evaluation"] = time_evaluations(
            evaluation_variants(system), system["y0"], iters, repeats
        )
        variants = fixed_variants(system, dt, nsteps)
        variants.pop("simulate")
        compiled, compile_s, outputs = compile_all(variants, system["y0"])
        samples = time_interleaved(compiled, system["y0"], repeats)
        entry["fixed"] = summarize(samples, compile_s, outputs)
        out[N] = entry
        ev, fx = entry["evaluation"], entry["fixed"]
        extra = "".join(
            f"; {name} alone {ev[name]['ratio']:.2f}, in Tsit5 {fx[name]['ratio']:.2f}"
            if name in fx
            else f"; {name} alone {ev[name]['ratio']:.2f}"
            for name in ev
            if name not in ("hand", "lagrax")
        )
        print(
            f"chain N={N:2d}: lagrax/hand alone {ev['lagrax']['ratio']:.2f} "
            f"(fastest {ev['lagrax']['ratio_min']:.2f}), in Tsit5 "
            f"{fx['lagrax']['ratio']:.2f} (fastest {fx['lagrax']['ratio_min']:.2f})"
            f"{extra}; compile lagrax {ev['lagrax']['compile_s']:.1f} s, hand "
            f"{ev['hand']['compile_s']:.1f} s",
            flush=True,
        )
    return out


def plot_chain(report, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    chain = report["chain"]
    Ns = sorted(chain, key=int)
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for key, label, style in [
        (("evaluation", "lagrax"), "lagrax, accelerations alone", "o-"),
        (("fixed", "lagrax"), "lagrax, in a fixed-step Tsit5 solve", "s-"),
        (("evaluation", "lagrax fuse=False"), "fuse=False, alone", "^"),
        (("fixed", "lagrax fuse=False"), "fuse=False, in Tsit5", "D"),
        (("evaluation", "lagrax array path"), "array path, alone", "x--"),
    ]:
        have = [N for N in Ns if key[1] in chain[N][key[0]]]
        ratios = [chain[N][key[0]][key[1]]["ratio"] for N in have]
        ax.plot([int(N) for N in have], ratios, style, label=label)
    ax.axhline(1.0, color="0.5", lw=0.8)
    ax.axhline(1.2, color="k", ls=":", lw=0.8)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xticks([int(N) for N in Ns], [str(N) for N in Ns])
    ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_yticks([0.25, 0.5, 1, 2, 4, 8])
    ax.set_xlabel("N (pendulums in the chain)")
    ax.set_ylabel("run time / hand-written EOM")
    ax.set_title(
        f"Chain of N pendulums written from particles: lagrax / hand-written EOM\n"
        f"(batch {report['batch']}, medians of {report['repeats']} interleaved rounds, "
        f"1 CPU core)",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


# ------------------------------------------------------------------------------ main


def plot(report, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, regime in zip(axes, ["fixed", "adaptive"]):
        labels, ratios, colors = [], [], []
        palette = {
            "hand": "0.6",
            "sympy": "tab:green",
            "lagrax": "tab:blue",
            "lagrax fuse=False": "lightsteelblue",
        }
        for sysname, entry in report["systems"].items():
            for name, row in entry[regime].items():
                labels.append(f"{sysname}\n{name}")
                ratios.append(row["ratio"])
                colors.append(palette.get(name, "tab:orange"))
        x = np.arange(len(labels))
        ax.bar(x, ratios, color=colors)
        ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
        for target, style in [(1.0, "-"), (1.2, ":")]:
            ax.axhline(target, color="k", linestyle=style, linewidth=0.8)
        ax.set_title(f"{regime} steps (Tsit5, batch {report['batch']})")
    axes[0].set_ylabel("run time / hand-written EOM")
    fig.suptitle("lagrax autodiff EOM overhead (target: 1.2× a hand-written EOM)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a small, fast run")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--batch", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None, help="fixed-step count")
    parser.add_argument("--out", type=pathlib.Path, default=RESULTS)
    parser.add_argument(
        "--chain", type=int, nargs="*", default=None, help="chain sizes N"
    )
    parser.add_argument(
        "--part",
        choices=["all", "systems", "chain"],
        default="all",
        help="systems: eom_overhead[_quick].json/.png; chain: "
        "eom_overhead_chain[_quick].json/.png",
    )
    args = parser.parse_args(argv)
    eval_iters = 200 if args.quick else 1000
    Ns = args.chain or ([1, 2, 4] if args.quick else [1, 2, 4, 8, 16])
    batch = args.batch or (256 if args.quick else 1024)
    repeats = args.repeats or (3 if args.quick else 9)
    nsteps = args.steps or (200 if args.quick else 1000)
    dt = 0.01
    t1_adaptive = 10.0 if args.quick else 40.0
    rtol = 1e-10
    max_steps = 16384

    report = dict(
        benchmark="eom_overhead",
        machine=f"{platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores, jax {jax.__version__} on {jax.default_backend()}, "
        f"diffrax {dfx.__version__ if hasattr(dfx, '__version__') else '?'}",
        note="shared, noisy CPU: compare ratios within one run",
        batch=batch,
        repeats=repeats,
        fixed=dict(solver="Tsit5", dt=dt, steps=nsteps),
        adaptive=dict(solver="Tsit5", t1=t1_adaptive, rtol=rtol, atol=rtol),
        systems={},
    )
    print(report["machine"])
    args.out.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    report["quick"] = args.quick
    report["evaluation"] = dict(batch=batch, iterations=eval_iters)
    if args.part in ("all", "chain"):
        chain = {k: v for k, v in report.items() if k not in ("systems", "adaptive")}
        chain["chain"] = chain_study(
            Ns, batch, eval_iters, repeats, dt, nsteps, jax.random.key(1)
        )
        path = args.out / f"eom_overhead_chain{suffix}.json"
        path.write_text(json.dumps(chain, indent=1))
        plot_chain(chain, path.with_suffix(".png"))
        print(f"wrote {path} and .png")
    if args.part == "chain":
        return
    for sysname, system in systems(batch, jax.random.key(0)).items():
        y0 = system["y0"]
        entry = dict(accuracy=check_accuracy(system, y0))
        if "sympy_derivation_s" in system:
            entry["sympy_derivation_s"] = system["sympy_derivation_s"]
        if sysname.startswith("double_pendulum"):
            entry["evaluation"] = time_evaluations(
                evaluation_variants(system), y0, eval_iters, repeats
            )
        for regime, variants in [
            ("fixed", fixed_variants(system, dt, nsteps)),
            ("adaptive", adaptive_variants(system, t1_adaptive, rtol, max_steps)),
        ]:
            compiled, compile_s, outputs = compile_all(variants, y0)
            samples = time_interleaved(compiled, y0, repeats)
            entry[regime] = summarize(samples, compile_s, outputs)
        report["systems"][sysname] = entry

    header = (
        f"{'system':<16} {'regime':<8} {'variant':<16} {'median ms':>10} {'ratio':>7} "
        f"{'min':>7} {'/step':>7} {'steps':>9} {'compile s':>9} {'max|Δy|':>9}"
    )
    print(f"batch {batch}, {repeats} interleaved repeats, Tsit5")
    print(header)
    print("-" * len(header))
    for sysname, entry in report["systems"].items():
        for regime in ["fixed", "adaptive"]:
            for name, row in entry[regime].items():
                print(
                    f"{sysname:<16} {regime:<8} {name:<16} "
                    f"{1e3 * row['median_s']:>10.1f} "
                    f"{row['ratio']:>7.3f} {row['ratio_min']:>7.3f} "
                    f"{row['ratio_per_step']:>7.3f} "
                    f"{row['total_steps']:>9d} {row['compile_s']:>9.2f} "
                    f"{row['max_abs_diff_from_hand']:>9.1e}"
                )
        if "sympy_derivation_s" in entry:
            print(f"{sysname}: sympy derivation {entry['sympy_derivation_s']:.2f} s")
        for name, row in entry.get("evaluation", {}).items():
            print(
                f"{sysname:<16} accelerations alone ({eval_iters} x {batch} lanes) "
                f"{name:<24} {1e3 * row['median_s']:>9.1f} ms ratio "
                f"{row['ratio']:.3f} (fastest {row['ratio_min']:.3f}), "
                f"{row['ns_per_lane_evaluation']:.1f} ns per lane-evaluation"
            )
    stem = f"eom_overhead{suffix}"
    (args.out / f"{stem}.json").write_text(json.dumps(report, indent=1))
    plot(report, args.out / f"{stem}.png")
    print(f"wrote {args.out / stem}.json and .png")


if __name__ == "__main__":
    main()
