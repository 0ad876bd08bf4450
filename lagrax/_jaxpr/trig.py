r"""Sine and cosine in float64 that XLA's CPU backend vectorizes.

XLA compiles `jnp.sin` and `jnp.cos` on a CPU to one scalar call of the C library per
element, while the arithmetic around them runs several lanes per instruction: in the
sweep kernel the pendulum's three sines per lane-step (the Taylor recurrence's order
0, the acceleration at the step's end and at a located event) are a large share of the
step. Written with `jnp` arithmetic, the same functions are fused and vectorized
(figures in `benchmarks/README.md`).

The algorithm is fdlibm's (Sun Microsystems, 1993; FreeBSD's `k_sin.c`, `k_cos.c`,
`e_rem_pio2.c`): $x = n\pi/2 + y$ with $n$ the nearest integer to $2x/\pi$ and $y$ a
double-double $y_0 + y_1$ from a three-part Cody-Waite reduction (fdlibm's "medium"
path, with all three of its iterations always taken: exact for the worst
cancellations below $2^{19}\pi/2$); then the minimax polynomials of
`__kernel_sin`/`__kernel_cos` on $|y| \le \pi/4$ and the quadrant's sign. Within
1 ulp of the correctly rounded value (against glibc, which rounds correctly almost
everywhere: at most 1 ulp apart on 10^7 points of $|x| \le 8\cdot10^5$; see
tests/test_trig.py).

Outside $|x| \le 2^{19}\pi/2 \approx 8.2\cdot10^5$ the reduction is no longer exact and
the functions return NaN (as for infinite or NaN arguments): a lane whose equations
take the sine of such an angle fails, it never gets a wrong number. (fdlibm goes on to
a Payne-Hanek reduction there; vectorized, every element would pay for it.)
"""

import jax
import jax.numpy as jnp
import numpy as np

from . import interpreter


# fdlibm's constants (e_rem_pio2.c): pi/2 in three 33-bit parts and the tail of the
# last; the products n * part are exact for |n| < 2^20.
_INVPIO2 = 6.36619772367581382433e-01
_PIO2_1 = 1.57079632673412561417e00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3, _PIO2_3T = 2.02226624871116645580e-21, 8.47842766036889956997e-32
_RANGE = 2.0**19 * np.pi / 2  # fdlibm's bound for this reduction
# k_sin.c, k_cos.c: minimax polynomials on [-pi/4, pi/4].
_S = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
_C = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)


def _two_diff(a, b):
    """`a - b` and its rounding error, exactly (Knuth's TwoSum)."""
    s = a - b
    bb = s - a
    return s, (a - (s - bb)) - (b + bb)


def _reduce(x):
    """$x = n\\pi/2 + y_0 + y_1$: the quadrant n mod 4 and the double-double y.

    fdlibm's medium path takes its second and third iterations (33 more bits of
    pi/2 each) only when the first cancels many bits; here both are always taken,
    each subtraction with its exact rounding error, so one program serves all."""
    fn = jnp.round(x * _INVPIO2)
    r = x - fn * _PIO2_1  # exact
    r, e2 = _two_diff(r, fn * _PIO2_2)
    r, e3 = _two_diff(r, fn * _PIO2_3)
    w = fn * _PIO2_3T - (e3 + e2)
    y0 = r - w
    y1 = (r - y0) - w
    return fn - 4.0 * jnp.floor(0.25 * fn), y0, y1


def _kernel_sin(x, y):
    s1, s2, s3, s4, s5, s6 = _S
    z = x * x
    w = z * z
    r = s2 + z * (s3 + z * s4) + z * w * (s5 + z * s6)
    v = z * x
    return x - ((z * (0.5 * y - v * r) - y) - v * s1)


def _kernel_cos(x, y):
    c1, c2, c3, c4, c5, c6 = _C
    z = x * x
    w = z * z
    r = z * (c1 + z * (c2 + z * c3)) + w * w * (c4 + z * (c5 + z * c6))
    hz = 0.5 * z
    w = 1.0 - hz
    return w + (((1.0 - w) - hz) + (z * r - x * y))


# Compiled as a call (XLA inlines it: the same program) so that its trace is cached
# per shape: the default sweep traces ~20 sincos calls.
@jax.jit
def _sincos(x):
    x = jnp.where(jnp.abs(x) <= _RANGE, x, jnp.nan)  # (NaN propagates to both)
    n, y0, y1 = _reduce(x)
    s, c = _kernel_sin(y0, y1), _kernel_cos(y0, y1)
    odd = (n == 1.0) | (n == 3.0)
    sin = jnp.where(odd, c, s) * jnp.where(n >= 2.0, -1.0, 1.0)
    cos = jnp.where(odd, s, c) * jnp.where((n == 1.0) | (n == 2.0), -1.0, 1.0)
    # sin(-0.0) is -0.0; below 2^-27, sin x rounds to x and cos x to 1.
    tiny = jnp.abs(x) < 2.0**-27
    sin = jnp.where(tiny, x, sin)
    cos = jnp.where(tiny, 1.0, cos)
    return sin, cos


@jax.custom_jvp
def sincos(x):
    """`(sin x, cos x)` for a float64 array, elementwise, vectorizable (see above)."""
    return _sincos(x)


@sincos.defjvp
def _sincos_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s, c = sincos(x)
    return (s, c), (c * dx, -s * dx)


def _rule(eqn, ins):
    if (
        eqn.primitive.name in ("sin", "cos")
        and eqn.invars[0].aval.dtype == jnp.float64
        and eqn.params.get("accuracy") is None
    ):
        return [sincos(ins[0])[eqn.primitive.name == "cos"]]
    return interpreter.bind(eqn, ins)


def vectorized_trig(f):
    """`f` with every float64 `sin` and `cos` in its jaxpr (and in the `jit` calls
    within) replaced by `sincos` above; the same outputs otherwise. Calls with a
    custom derivative are bound as they are (their derivative rule is kept, with the
    C library's sine inside). Traced at each call: wrap the result in `jax.jit`
    where it is called often."""

    def g(*args):
        closed, shape = jax.make_jaxpr(f, return_shape=True)(*args)
        flat = jax.tree.leaves(args)
        outs = interpreter.evaluate(closed.jaxpr, closed.consts, flat, _rule)
        return jax.tree.unflatten(jax.tree.structure(shape), outs)

    return g


__all__ = ["sincos", "vectorized_trig"]
