"""Cost of `lagrax._taylor.program.taylor_coefficients` against one `jnp.sin` call.

Per lane: order-K Taylor coefficients of the pendulum x' = v, v' = -sin(q0 + x), with
the acceleration from lagrax's autodiff `_accelerations` of L = qdot^2/2 + cos q, at
W = 256 and 4096 lanes, float64, one process. The baseline is `jnp.sin` on the same W
(XLA's float64 sin is a scalar libm call). Compile time is measured on its own (lower +
compile). Best of repeats; run on a quiet machine, timings on a shared one are noisy.

    python benchmarks/taylor_coefficients.py [--order 20]
"""

import argparse
import time

import jax
import jax.numpy as jnp


jax.config.update("jax_enable_x64", True)

from lagrax._eom.mechanics import _accelerations  # noqa: E402
from lagrax._taylor.program import taylor_coefficients  # noqa: E402


def L(q, qdot, t):
    return 0.5 * qdot[0] ** 2 + jnp.cos(q[0])


def accel(s, x, v, q0):
    return _accelerations(L, (q0 + x)[None], v[None], s)[0][0]


def measure(f, args, repeats):
    t0 = time.perf_counter()
    compiled = jax.jit(f).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - t0)
    return compile_s, best


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--order", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=50)
    opts = parser.parse_args()
    coeffs = taylor_coefficients(accel, opts.order, jnp.float64)
    for W in (256, 4096):
        s = jnp.zeros(W)
        x = jnp.zeros(W)
        v = jnp.linspace(-0.3, 0.3, W)
        q0 = jnp.linspace(0.1, 3.0, W)
        args = (s, x, v, q0)
        jax.clear_caches()
        c_t, t_t = measure(coeffs, args, opts.repeats)
        c_s, t_s = measure(lambda s, x, v, q0: jnp.sin(q0 + x), args, opts.repeats)
        print(
            f"W={W:5d} order={opts.order}: coeffs {t_t / W * 1e9:8.1f} ns/lane "
            f"(compile {c_t:.2f} s); sin {t_s / W * 1e9:6.1f} ns/elem; "
            f"ratio {t_t / t_s:6.1f} sines"
        )


if __name__ == "__main__":
    main()
