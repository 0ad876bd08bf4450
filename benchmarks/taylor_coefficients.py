"""Taylor coefficients of a vector field: the compact program against the unrolled one.

For each system (the pendulum, the double pendulum, chains of n pendulums written from
particle positions), the order-K coefficients of the first-order system that
`simulate_batch` integrates, computed by

- the unrolled program (`lagrax._taylor.system.System.coefficients`, the orders
  written out: one straight-line program per Lagrangian), and
- the compact program (`lagrax._taylor.compact`: the recurrences as data, one
  program per size class),

each compiled with XLA's elemental CPU emitters (as the library compiles them). Per
program: trace + compile time, the serialized executable's size and load time, and
the cost per lane-step (`--steps` coefficient computations in one compiled loop over
W lanes, best of `--repeats`). The compact program's size class is also compiled once
and reused for a second system of the same class (time of that first call: the
tape's build only). The results go to `results/taylor_coefficients.json`.

    python benchmarks/taylor_coefficients.py [--order 16] [--width 128]
        [--systems pendulum double_pendulum chain2 chain4] [--unrolled-max 4]

Pin it (`taskset -c 1`) on a quiet machine: the figures are per core.
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import serialize_executable


jax.config.update("jax_enable_x64", True)

import lagrax  # noqa: E402
from lagrax._jaxpr.canonical import canonical_lagrangian  # noqa: E402
from lagrax._jaxpr.fusion import elemental_options  # noqa: E402
from lagrax._taylor import compact  # noqa: E402
from lagrax._trajectory.batch import _system as batch_system  # noqa: E402


HERE = os.path.dirname(os.path.abspath(__file__))
G = 9.81


def lagrangian(name):
    if name == "pendulum":
        return (lambda q, qd, t: 0.5 * qd[0] ** 2 + G * jnp.cos(q[0])), 1
    if name == "double_pendulum":

        def L(q, qd, t):
            t1, t2, w1, w2 = q[0], q[1], qd[0], qd[1]
            T = w1**2 + 0.5 * w2**2 + w1 * w2 * jnp.cos(t1 - t2)
            return T + 2 * G * jnp.cos(t1) + G * jnp.cos(t2)

        return L, 2
    n = int(name.removeprefix("chain"))

    def positions(q, t):
        return jnp.stack([jnp.cumsum(jnp.sin(q)), -jnp.cumsum(jnp.cos(q))], axis=1)

    L = lagrax.particle_lagrangian(
        jnp.ones(n), positions, lambda r, t: G * jnp.sum(r[:, 1])
    )
    return L, n


def system(name):
    L, n = lagrangian(name)
    L_c, consts = canonical_lagrangian(L, jnp.float64, n)
    return batch_system(L_c, consts, None, jnp.zeros(n), jnp.zeros(n)), n


def loop(coefficients, steps):
    """`steps` coefficient computations in one program (each from a state moved by
    the last coefficients, so none is hoisted out of the loop; by a bounded amount,
    so that the state stays finite and near its start)."""

    def run(*args):
        t, ys, sigma, rest = args[0], args[1], args[2], args[3:]

        def body(i, ys):
            cs = coefficients(t, ys, sigma, *rest)
            return ys + 1e-20 * jnp.tanh(jnp.stack([c[-1] for c in cs]))

        return jax.lax.fori_loop(0, steps, body, ys)

    return jax.jit(run, compiler_options=elemental_options())


def measure(jitted, args, repeats):
    t0 = time.perf_counter()
    lowered = jitted.lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    payload = serialize_executable.serialize(compiled)
    t3 = time.perf_counter()
    serialize_executable.deserialize_and_load(*payload)
    load = time.perf_counter() - t3
    jax.block_until_ready(compiled(*args))
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - t)
    return dict(
        trace_s=t1 - t0,
        compile_s=t2 - t1,
        bytes=len(payload[0]),
        load_s=load,
        seconds=best,
    ), compiled


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--order", type=int, default=16)
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument(
        "--systems", nargs="+",
        default=["pendulum", "double_pendulum", "chain2", "chain4", "chain6", "chain8"],
    )  # fmt: skip
    parser.add_argument(
        "--unrolled-max", type=int, default=4,
        help="the largest chain whose unrolled program is compiled (minutes beyond)",
    )  # fmt: skip
    opts = parser.parse_args()
    K, W = opts.order, opts.width
    rows = []
    rng = np.random.default_rng(0)
    for name in opts.systems:
        sys_, n = system(name)
        t = jnp.asarray(rng.uniform(0, 1, W))
        ys = jnp.asarray(rng.uniform(-0.5, 0.5, (2 * n, W)))
        sigma = jnp.ones(W)
        prog = sys_.prog
        t0 = time.perf_counter()
        tape = compact.build(prog, prog.inputs, prog.params, prog.outs, jnp.float64)
        build_s = time.perf_counter() - t0
        compact_fn = loop(
            lambda t, ys, sigma, tape: compact.compact_coefficients(
                tape, K, t, list(ys), [sigma], trig=True
            ),
            opts.steps,
        )
        m, _ = measure(compact_fn, (t, ys, sigma, tape), opts.repeats)
        per = m["seconds"] / opts.steps / W
        rows.append(dict(system=name, program="compact", order=K, width=W,
                         build_s=build_s, lane_step_us=per * 1e6, **m))  # fmt: skip
        print(
            f"{name:16s} compact : tape {build_s:.3f} s, trace {m['trace_s']:.2f} s, "
            f"compile {m['compile_s']:.2f} s, {m['bytes'] / 1e6:.2f} MB, "
            f"load {m['load_s'] * 1e3:.0f} ms, {per * 1e6:.2f} us/lane-step",
            flush=True,
        )
        if name.startswith("chain") and n > opts.unrolled_max:
            continue
        unrolled_fn = loop(
            lambda t, ys, sigma: sys_.coefficients(
                K, t, [ys[:n].T, ys[n:].T], [sigma], unrolled=True, trig=True
            ),
            opts.steps,
        )
        m, _ = measure(unrolled_fn, (t, ys, sigma), opts.repeats)
        per = m["seconds"] / opts.steps / W
        rows.append(dict(system=name, program="unrolled", order=K, width=W,
                         lane_step_us=per * 1e6, **m))  # fmt: skip
        print(
            f"{name:16s} unrolled: trace {m['trace_s']:.2f} s, "
            f"compile {m['compile_s']:.2f} s, {m['bytes'] / 1e6:.2f} MB, "
            f"load {m['load_s'] * 1e3:.0f} ms, {per * 1e6:.2f} us/lane-step",
            flush=True,
        )
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
        cwd=HERE,
    ).stdout.strip()  # fmt: skip
    report = dict(
        date=time.strftime("%Y-%m-%d"),
        machine=platform.processor() or platform.machine(),
        commit=commit,
        jax=jax.__version__,
        argv=sys.argv[1:],
        rows=rows,
    )
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    with open(os.path.join(HERE, "results", "taylor_coefficients.json"), "w") as fh:
        json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main()
