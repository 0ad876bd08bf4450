r"""The per-lane error estimate of a period.

With a Taylor step and `"matched"`, a first-order bound summed in the same loop
(`screen`): per step, the error bound of the step (its truncation, the first terms
dropped from the coefficients and the acceleration's defect, and the rounding of the
state) as a time shift along the orbit and an
energy error, which moves the end of the leg by its leverage $\int ds/\dot q^2$ over
the rest of it (Gauss–Legendre on the step's velocity polynomial); and the far
turning point's band times $d\tau/dE$, the finite part of that integral from rest.
Lanes it cannot vouch for are solved a second time at `TIGHTER` times the
tolerances from the far turning point moved across its band; every other method and
stepper a second time at `TIGHTER` times the tolerances ("half", and "full" where L
is even in q̇, by "matched") and, where a leg starts at the far turning point, a
third from it moved across its band (`second_solve_estimate`).
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._results import SUCCESS
from .._stepper.base import horner
from .._taylor.stepper import TaylorStepper


# The second solve: at `TIGHTER` times the tolerances ("half", "full": by
# "matched"), nearer the truth than the first by about that factor, so the
# difference is about the first solve's error; the band's share, from the far
# turning point moved across its rounding band, is a term of its own (in one solve
# with the truncation's, the two may cancel): `_SAFETY` times their sum, plus a
# fraction of rtol (`_FLOOR_RTOL`, per stepper: a lane whose error happens to cancel
# at one tolerance and not at the other, where the two solves agree more closely
# than either agrees with the truth; more often with the few long steps of a Taylor
# step, and where the many short steps of a pair of low order leave rounding errors
# of the same size in both solves), plus `_FLOOR_ULPS` ulps. Calibrated on exact periods
# (benchmarks/accuracy.py --periods, tests/test_estimate.py).
TIGHTER = 0.1
_SAFETY = 4.0
_FLOOR_RTOL = {"taylor": 0.1, "runge_kutta": 0.02, "low_order": 0.3}
# A Runge–Kutta pair below this error order is of low order (Tsit5, Dopri5).
_LOW_ORDER = 7
_FLOOR_ULPS = 16.0
#: A lane's period is trusted when its estimate is below this many times rtol.
PROMISE = 100.0
# The first-order bound: the safety factors of its terms (a time shift along the
# orbit and an energy error times its leverage; each from the steps' rounding and
# their truncation bound), and the largest leverage ∫ds/v² (lane units) of a leg past
# its first step for which it is used: beyond, rounding of the force, which it does
# not model, may be amplified (near a hump). The rounding of each step is modelled
# as four ulps of each component of the state, summed with one sign over the leg:
# itself a bound several times the rounding measured, even near a hump, where its
# share of the energy error is amplified coherently; the truncation terms are each
# estimated from the step's own terms, and carry the larger factors.
_SHIFT_SAFETY = (1.5, 2.0)  # (rounding, truncation)
_ENERGY_SAFETY = (1.0, 1.5)
_SCREEN_LEVERAGE = 100.0

_GL3 = tuple((float(x), float(w)) for x, w in zip(*np.polynomial.legendre.leggauss(3)))

# The loop's per-lane sums, the columns of one array (one select per refill and per
# step, not five): the phase (ph), energy errors times their leverage (J), ∫ds/v²
# (F; from rest its finite part), the same without the first step (G), and the
# energy errors so far (D). The first four are handed in.
NUM_SUMS = 5
SUMS_OUT = ("ph", "J", "F", "G")


class StepTerms(eqx.Module):
    """One step's terms of the bound: ∫ds/v² over the step (`W`) and the truncation
    bounds of position and velocity (`dq`, `dv`)."""

    W: Float[Array, " lanes"]
    dq: Float[Array, " lanes"]
    dv: Float[Array, " lanes"]


class BoundTerms(eqx.Module):
    """A leg's sums of the bound in time units (`_finish`): phase, energy errors times
    their leverage, the finite part of ∫dt/v² from rest, and the leg's leverage past
    its first step (infinite where the mass is not constant)."""

    ph: Float[Array, " lanes"]
    J: Float[Array, " lanes"]
    F: Float[Array, " lanes"]
    G: Float[Array, " lanes"]


def step_terms(stepper, expansion, v, h, a_end) -> StepTerms:
    r"""The step's terms of the bound, from its polynomials, the step `h` taken and
    the acceleration `a_end` where it ends.

    The truncation, each a first term dropped times the geometric tail
    $1/(1 - h/\rho)$: of the position, $x_{K+1} h^{K+1} = v_K h^{K+1}/(K+1)$ (known:
    $x' = v$); of the velocity, measured as the acceleration's, $h\,|a_1 -
    p_a(h)|/(K+1)$ (the acceleration where the step ends against its polynomial's,
    of degree $K - 1$). W = ∫ ds / v(s)² over the step by 3-point Gauss–Legendre on
    the velocity polynomial; from rest (v = a0 s + ...) its Hadamard finite part,
    ∫ (1/v² - 1/(a0 s)²) ds - 1/(a0² h). One division per node (each with one
    reader: the step is one fusion). No tangents: the estimate is not
    differentiated."""
    scale = stepper.radius_fraction(expansion.tol)
    terms = (expansion.xs, expansion.vs, expansion.as_, v, h, scale, a_end)
    xs, vs, as_, v, hu, scale, a_end = jax.tree.map(jax.lax.stop_gradient, terms)
    K = stepper.order
    # 1/(1 - q) by its series (no division: one with several readers would split
    # the step's fusion), q = h/ρ at most 3/4.
    q = jnp.minimum(scale, 0.75)
    tail = jnp.ones_like(q)
    for _ in range(12):
        tail = 1.0 + q * tail
    # The position's first term dropped, x_{K+1} h^{K+1}, and the last ones kept
    # carried on by a factor q per order to the first order dropped: K + 1, or K + 2
    # where x is even in time (released from rest: its odd coefficients vanish).
    even = (vs[K] == 0) & (xs[K - 1] == 0) & (xs[K - 3] == 0)
    extra = jnp.where(even, q, 1.0)
    terms = [
        jnp.abs(vs[K]) * hu / (K + 1),
        jnp.abs(xs[K]) * q * extra,
        jnp.abs(xs[K - 1]) * q**2,
        jnp.abs(xs[K - 2]) * q**3 * extra,
    ]
    dq = tail * hu**K * functools.reduce(jnp.maximum, terms)
    dv = tail * hu * jnp.abs(a_end - horner(as_, hu)) / (K + 1)
    rest = v == 0
    a2 = jnp.where(rest, as_[0] * as_[0], 1.0)
    w_sum = None
    for xi, wi in _GL3:
        sk = 0.5 * hu * (1.0 + xi)
        vk2 = horner(vs, sk) ** 2
        d2 = a2 * sk * sk
        term = wi * (d2 - jnp.where(rest, vk2, 0.0)) / (vk2 * d2)
        w_sum = term if w_sum is None else w_sum + term
    W = 0.5 * hu * w_sum - jnp.where(rest, 1.0 / (a2 * hu), 0.0)
    return StepTerms(W=W, dq=dq, dv=dv)


def step_increments(sums, terms: StepTerms, step, v):
    """What a step adds to the sums: its errors (truncation bound plus rounding of the
    state, each times its safety factor) as a time shift δx/|v| and an energy error
    per unit mass |v|δv + |a|δx; an energy error made before this step moves the
    leg's end by its leverage ∫ds/v² over the rest of the leg."""
    eps = jnp.finfo(v.dtype).eps
    x1, v1, a1, h, W = step.x, step.v, step.a, step.h, terms.W
    x_round = 4 * eps * (1.0 + jnp.abs(x1))
    v_round = 4 * eps * (jnp.abs(v1) + jnp.abs(h * a1))
    (rs, ts), (re, te) = _SHIFT_SAFETY, _ENERGY_SAFETY
    shift_ = (ts * terms.dq + rs * x_round) / jnp.abs(v1)
    e_err = jnp.abs(v1) * (te * terms.dv + re * v_round) + jnp.abs(a1) * (
        te * terms.dq + re * x_round
    )
    from_rest = v == 0
    inc = (shift_, sums[:, 4] * W, W, jnp.where(from_rest, 0.0, W), e_err)
    return jax.lax.stop_gradient(jnp.stack(inc, axis=1))


def screen(T, t_a, t_b, terms_a: BoundTerms, terms_b: BoundTerms, band, rtols):
    r"""A first-order bound on the relative error of "matched"'s period from its
    own solve (Taylor steps), without a second solve.

    Each step's error (its truncation bound, the rounding of the state) moves the
    leg's end in two ways: along the orbit, a time shift $\delta q/|\dot q|$; across
    it, an energy error $\delta E$, which changes the time left to the end of the
    leg by $\partial\tau/\partial E|_q = -\int \mathrm dt/(M\dot q^2)$ over the rest of
    the leg (the second solution of the variational equation by reduction of order:
    the flow $(\dot q, \ddot q)$ is the first, the Wronskian is $\propto 1/M$). The
    loop sums both per leg (`ph`, `J`). Leg B starts at a far turning point known
    to within `band`: its energy, and the leg's time by $d\tau/dE$, the Hadamard
    finite part of $\int_0 \mathrm dt/(M\dot q^2)$ from rest (`F`; zero for a
    harmonic well: isochronous). Bounded by absolute values; a constant mass is
    assumed (infinite `G` otherwise), and a leg whose leverage `G` exceeds
    `_SCREEN_LEVERAGE` is not bounded here (infinite)."""
    eps = jnp.finfo(T.dtype).eps
    T, t_a, t_b, band = jax.lax.stop_gradient((T, t_a, t_b, band))
    a, b = terms_a, terms_b
    # (The sums carry their safety factors; the band is itself a bound on the
    # root's rounding: none on it.)
    err = 2 * (a.ph + a.J + b.ph + b.J)
    far = 2 * band * jnp.abs(b.F)
    bound = (err + far) / jnp.abs(T) + 4 * eps
    usable = (a.G <= _SCREEN_LEVERAGE) & (b.G <= _SCREEN_LEVERAGE)
    usable = usable & jnp.isfinite(bound) & jnp.isfinite(band)
    return jnp.where(usable, bound, jnp.inf)


def screen_quarter(T, t_a, terms: BoundTerms):
    r"""The first-order bound of "quarter"'s period, $T = 4 t_a$: `screen` for its
    one leg, from rest to the point of maximum speed (the well's mirror symmetry,
    which the method checks to the tolerance, is assumed)."""
    eps = jnp.finfo(T.dtype).eps
    T, t_a = jax.lax.stop_gradient((T, t_a))
    err = 4 * (terms.ph + terms.J)
    bound = err / jnp.abs(T) + 4 * eps
    usable = (terms.G <= _SCREEN_LEVERAGE) & jnp.isfinite(bound)
    return jnp.where(usable, bound, jnp.inf)


def needs_second_solve(status, bound, rtols):
    """Lanes whose first-order bound cannot vouch for their period."""
    return (status == SUCCESS) & ~(bound <= PROMISE * rtols)


def second_solve_estimate(T, status, T2, status2, rtols, stepper, shifted=None):
    """The estimate from a second solve at `TIGHTER` times the tolerances:
    `_SAFETY` times the relative difference, plus a fraction of rtol (`_FLOOR_RTOL`
    for `stepper`: a Taylor step, a Runge–Kutta pair, one of low order) and
    `_FLOOR_ULPS` ulps; infinite where the second solve failed and
    the requested one did not (that says nothing sure).

    `shifted`: `(T3, status3, T_ref, status_ref)`, a solve from the far turning
    point moved across its rounding band and the one it differs from only by that;
    `_SAFETY` times their relative difference is added (infinite where the shifted
    one failed and the other did not)."""
    eps = jnp.finfo(T.dtype).eps
    if isinstance(stepper, TaylorStepper):
        kind = "taylor"
    elif stepper.error_order < _LOW_ORDER:
        kind = "low_order"
    else:
        kind = "runge_kutta"
    diff = jnp.abs(T2 - T)
    unsure = (status == SUCCESS) & (status2 != SUCCESS)
    if shifted is not None:
        T3, status3, T_ref, status_ref = shifted
        moved = jnp.abs(T3 - T_ref)
        diff = diff + jnp.where(status_ref == SUCCESS, moved, 0.0)
        unsure = unsure | ((status_ref == SUCCESS) & (status3 != SUCCESS))
    est = _SAFETY * diff / jnp.abs(T) + _FLOOR_RTOL[kind] * rtols
    est = est + _FLOOR_ULPS * eps
    return jnp.where(unsure, jnp.inf, est)
