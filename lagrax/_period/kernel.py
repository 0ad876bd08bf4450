r"""The batch kernel behind `sweep_periods`: one compiled loop per device.

Each device runs one `lax.while_loop` over `width` lanes. Every iteration advances every
lane by one explicit Runge–Kutta step written out stage by stage from the solver's
diffrax `ButcherTableau` (no coefficients copied by hand), with diffrax's I-controller
rule for the next step size. A lane that finishes its amplitude writes its result into
the output arrays and takes the next amplitude from the queue inside the loop, so lanes
never wait for the slowest one and the input order does not matter.

Measured on the pendulum (4096 lanes, one CPU core, float64): diffrax's `Dopri8().step`
called in a lean loop costs ~600–700 ns per lane-step, most of it the stage loop and
general tree operations; the step written out here, with the loop's bookkeeping,
costs 73-83 ns per lane-step for Dopri8, 2.7-3.1x the vector field alone (see
`benchmarks/sweep.py`, which prints ns per lane-step and the vector-field-only
ceiling).

With `solver=lagrax.Taylor()` the step is a Taylor expansion of order K instead
(`_taylor_step`): coefficients by recurrence from the acceleration's jaxpr
(`taylor_coefficients`), written out order by order, the step length chosen from
the last coefficients before the step is taken (never rejected), and the step's outputs
forced into ONE fused loop over the lanes (`one_fusion`): XLA on a CPU otherwise
duplicates the shared recurrence into each consumer. Measured on the pendulum (one
core, rtol 1e-14): ~5 lane-steps per quarter period against ~26 for Dopri8, at
~115-120 ns each, of which the step itself (vectorized, ~1000 flops per lane) is
~90-100 ns.

Every iteration is a handful of kernels, because on a CPU each kernel is a separate
call (~0.1-0.2 µs) and XLA has no multi-output fusion there: the step (a Runge–Kutta
step's stages, each read by several later ones, would otherwise be 13 fusions), the
lane update and the refill each leave through one `one_fusion`, with the gather, the
scatter and the refill's count around them (17 kernels per iteration for Dopri8, ~50
and ten copies of carried fields before: Dopri8 +20-25% periods/s, measured).

The queue's refill is one gather of packed per-amplitude rows and one scatter of
packed results per iteration, without a `lax.cond` (each gather, scatter or small
fusion is a separate call; ten of them and the `cond` cost as much as the Taylor
step, measured); lanes freed at the end of an iteration take their new amplitude
at the start of the next.

The event (a turning point, $\dot q = 0$, or the point of maximum speed, $\ddot q = 0$)
is detected by a sign change over an accepted step and located by re-stepping from the
last accepted state with the step length as the unknown: Newton with the exact
derivative for $\dot q = 0$ (its derivative is the acceleration at the end of the
trial step, which a FSAL tableau has already computed) and a safeguarded secant for
$\ddot q = 0$. Each trial is a full step of the solver, so the located state is as
accurate as any accepted step; nothing is interpolated. A Taylor step needs no
trials: its polynomials are the solution over the whole step (a step of any length
$t \le h$ from the same base is the polynomials at $t$), so the event is located in
the step that crosses it, by Newton on the event function's polynomial and one
Newton correction with the exact event value (`_taylor_step`); trials remain the
fallback where that correction is not below round-off. Measured on the pendulum
(4096 lanes, one core, rtol 1e-14): "quarter" 9.1 -> 5.1 lane-steps per amplitude,
"matched" 16.2 -> 9.2, 1.4x the periods per second, the same errors.

With the error estimate (`_Pass.screen`), each step also adds its terms of the
first-order error bound to per-lane sums carried in the loop (`_screen_terms`); the
bound itself, the methods' legs and rounds, and sharding over devices are in
`lagrax._period.sweep`.
"""

import functools
import weakref

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._eom.mechanics import _accelerations, _jacobi
from .._jaxpr.fusion import one_fusion
from .._jaxpr.trig import vectorized_trig
from .._results import (
    ENERGY_DRIFT,
    MAX_STEPS as S_MAX_STEPS,
    NONFINITE_INPUT,
    NOT_OSCILLATING,
    ROOT_FIND_FAILED,
    SINGULAR_MASS,
    SOLVER_FAILED,
    SUCCESS,
)
from .._taylor.program import taylor_coefficients
from .._taylor.solver import Taylor


# Raw outcomes of the loop, refined into statuses by the post-pass.
LOCATED = 0
NO_EVENT = 1  # escaped, or reached t_max
MAX_STEPS = 2
LOCATE_FAILED = 4
STEP_FAILED = 6
INVALID = 7  # not started: the post-pass says why (non-finite, singular, equilibrium)

_ESCAPE = 1e6
_NO_LIMIT = 1e30
# Newton (q̇ = 0) converges in 2–3 trials, the secant (q̈ = 0) in 4–6 (Taylor lanes
# locate their events inside the crossing step, with trials only as a fallback); a
# lane that has not converged after this many trials is reported as not located.
_MAX_LOCATE = 12


class _Tableau(eqx.Module):
    """An explicit tableau as Python floats (constants in the compiled step)."""

    a: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    b: tuple[float, ...] = eqx.field(static=True)
    e: tuple[float, ...] = eqx.field(static=True)
    c: tuple[float, ...] = eqx.field(static=True)
    fsal: bool = eqx.field(static=True)
    error_order: float = eqx.field(static=True)


def explicit_tableau(solver) -> _Tableau | None:
    """The tableau of a diffrax explicit Runge–Kutta solver, or None for any other."""
    if not isinstance(solver, dfx.AbstractERK):
        return None
    # Read once per solver: converting diffrax's tableau to floats cost ~130 µs, and
    # every sweep asked twice (its checks, then the kernel): ~2.5% of a 4096-amplitude
    # Dopri8 sweep on one core (measured).
    try:
        return _tableau_of(solver)
    except TypeError:  # an unhashable solver (array fields): read it anew
        return _tableau_of.__wrapped__(solver)


@functools.lru_cache(maxsize=32)
def _tableau_of(solver) -> _Tableau | None:
    tab = type(solver).tableau
    if getattr(tab, "implicit", False) or tab.b_error is None:
        return None
    a = tuple(tuple(float(v) for v in np.asarray(row)) for row in tab.a_lower)
    b = tuple(float(v) for v in np.asarray(tab.b_sol))
    e = tuple(float(v) for v in np.asarray(tab.b_error))
    c = tuple(float(v) for v in np.asarray(tab.c))
    fsal = bool(tab.fsal) and a[-1] == b[:-1] and c[-1] == 1.0
    order = float(solver.error_order(dfx.ODETerm(lambda t, y, args: y)))
    return _Tableau(a, b, e, c, fsal, order)


def stepper(solver) -> "_Tableau | Taylor | None":
    """What the kernel steps with: a `Taylor` as it is, a diffrax ERK's tableau."""
    if isinstance(solver, Taylor):
        return solver
    return explicit_tableau(solver)


def _log2(n):
    """log2 of a positive float to 0.014 (frexp and a cubic; no libm call): the
    step-length rule's j-th roots need only a few digits."""
    m, e = jnp.frexp(n)  # n = m 2^e, m in [1/2, 1)
    t = 2.0 * m - 1.0
    return e.astype(n.dtype) - 1.0 + t * (1.4425 + t * (-0.7213 + t * 0.2788))


def _root(x, n):
    """`x ** (1 / n)`; by nested square roots where `n` is a power of two (Dopri8's
    step-size controller: n = 8). XLA's CPU backend calls the C library's scalar
    `pow` once per lane (~8 ns, 10% of a Dopri8 "quarter" sweep; measured), while
    `sqrt` is vectorized and correctly rounded, so every lane gets the same bits
    whatever its position in the vector (an `exp2(log2(x) / n)` did not: its
    vector and scalar code paths differ in the last bit, round two session 9)."""
    k = int(n)
    if k == n and k >= 1 and k & (k - 1) == 0:
        for _ in range(k.bit_length() - 1):
            x = jnp.sqrt(x)
        return x
    return x ** (1.0 / n)


def _horner(cs, h):
    out = cs[-1]
    for c in cs[-2::-1]:
        out = out * h + c
    return out


def _horner2(cs, t):
    """The polynomial sum_k cs[k] t^k and its derivative."""
    p, dp = cs[-1], jnp.zeros_like(cs[-1])
    for c in cs[-2::-1]:
        dp = dp * t + p
        p = p * t + c
    return p, dp


def _event_polynomial(xs, vs, as_, kind, sigma, xt):
    """The coefficients of the event function g(s + τ) of the step's polynomials:
    σ v(τ), σ a(τ) (degree K - 1) or σ (x_t - x(τ)), by each lane's `kind`."""
    K = len(xs) - 1
    cs = []
    for k in range(K + 1):
        ak = as_[k] if k < K else jnp.zeros_like(xs[k])
        c = jnp.where(kind == TURNING, vs[k], jnp.where(kind == MAX_SPEED, ak, -xs[k]))
        if k == 0:
            c = c + jnp.where(kind == POSITION, xt, 0.0)
        cs.append(sigma * c)
    return cs


# The event polynomial's root: Newton from regula falsi, first on its leading terms
# (cheap; each Horner sweep is a chain of dependent multiply-adds), then on all.
_ROOT_LOW_TERMS, _ROOT_LOW_ITERS, _ROOT_FULL_ITERS = 8, 2, 1


def _polynomial_root(cs, h, g0, g1):
    """A root in [0, h] of the event polynomial `cs` (g0 > 0 at 0, the exact g1 <= 0
    at h on the lanes that crossed), good to ~1e-10 of h."""
    d = g0 - g1
    t = jnp.where(d > 0, g0 * h / jnp.where(d > 0, d, 1.0), 0.5 * h)
    for n in range(_ROOT_LOW_ITERS + _ROOT_FULL_ITERS):
        g, dg = _horner2(cs[:_ROOT_LOW_TERMS] if n < _ROOT_LOW_ITERS else cs, t)
        tn = t - g / jnp.where(dg != 0, dg, 1.0)
        t = jnp.where((tn > 0) & (tn < h), tn, t)
    return t


_GL3 = tuple((float(x), float(w)) for x, w in zip(*np.polynomial.legendre.leggauss(3)))


def _taylor_step(
    spec, coeffs, accel, s, x, v, h_req, free, rtol, atol, cap, event, screen=False
):
    """One Taylor step of every lane: of its own length (`free`) or of length `h_req`
    (an event's trial). Returns the state at s + h, the acceleration there and h, or
    on lanes whose step crossed their event (`event` = (kind, sigma, x_t) per lane)
    and located it inside the step (`inner`), the event's state and step length; and
    the located step length as the first trial of the others (`guess`)."""
    K = spec.order
    xs, vs, as_ = coeffs(s, x, v)
    tol = atol + rtol * jnp.maximum(jnp.abs(x), jnp.abs(v))
    # The radius of convergence from the root test on the last coefficients, as
    # Jorba and Zou (and heyoka.py) do, but over the last four orders instead of two:
    # from rest, x(s) is even, its odd coefficients vanish, and the last two orders
    # then rest on a single number that passes through zero as the amplitude varies
    # (measured: the pendulum at q0 = 2.23692 took a first step 1.4x too long and
    # lost 1.8e-9 in the period at rtol 1e-13; neighbours 1e-12).
    # In the log domain, max_j log2(n_j) / j, and one exp2 (four `pow` calls cost
    # ~30 ns per lane-step, measured).
    lg = None
    for j in range(max(1, K - 3), K + 1):
        n = jnp.maximum(jnp.abs(xs[j]), jnp.abs(vs[j]))
        lj = jnp.where(n > 0, _log2(n), -jnp.inf) / j
        lg = lj if lg is None else jnp.maximum(lg, lj)
    # tol^(1/K) in the log domain too: XLA calls libm's scalar `pow` for every lane
    # (~8 ns each, against ~1 ns for its vectorized exp2; measured).
    # (Each exp2 with one reader: see the end of this function.)
    c = float(np.exp(-0.7 / (K - 1)))  # (a weak Python float)
    h_jz = c * jnp.exp2(jnp.log2(tol) / K - lg)
    h = jnp.where(free, jnp.minimum(h_jz, jnp.minimum(cap, spec.max_step)), h_req)
    h = jax.lax.stop_gradient(h)
    x1, v1 = _horner(xs, h), _horner(vs, h)
    a1 = accel(s + h, x1, v1)
    # The event inside the step: the polynomials are the solution over the whole step
    # (a step of any length t <= h from this base IS x(t), v(t)), so the event is
    # their root, found without stepping again: Newton on the event polynomial, then
    # one Newton correction with the exact event value there (for q̈ = 0 the
    # acceleration's own series, of degree K - 1, is ~100x less accurate than x(t)).
    kind, sigma, xt = event
    g0 = _event_value(kind, sigma, xt, x, v, as_[0])
    g1 = _event_value(kind, sigma, xt, x1, v1, a1)
    sg = jax.lax.stop_gradient
    cs = sg(_event_polynomial(xs, vs, as_, kind, sigma, xt))
    tp = _polynomial_root(cs, h, sg(g0), sg(g1))
    xe, ve = _horner(xs, tp), _horner(vs, tp)
    ae = accel(s + tp, xe, ve)
    da = _horner2(as_, tp)[1]
    ge = _event_value(kind, sigma, xt, xe, ve, ae)
    se = sigma * jnp.where(kind == TURNING, ae, jnp.where(kind == MAX_SPEED, da, -ve))
    # (A division's result read by several values splits XLA's fusion: the CPU
    # fusion pass will not duplicate an expensive op, and then copies the cheap
    # recurrence into each part, measured 3-4x slower. Behind a select, the
    # division has one reader and the cheap select is what fans out.)
    dt = sg(jnp.where(se != 0, -ge / jnp.where(se != 0, se, 1.0), 0.0))
    te = tp + dt
    # Located in this step where the step crossed and the last correction was below
    # 1e-8 of the step (another would be below round-off); the step then ends there.
    crossed = free & (g1 <= 0) & jnp.isfinite(h) & jnp.isfinite(x1) & jnp.isfinite(v1)
    crossed = crossed & jnp.isfinite(a1)
    xe, ve, ae = xe + ve * dt, ve + ae * dt, ae + sg(da) * dt
    inner = crossed & (jnp.abs(dt) <= 1e-8 * h) & (te > 0) & (te <= h)
    inner = inner & jnp.isfinite(xe) & jnp.isfinite(ve) & jnp.isfinite(ae)
    outs = dict(
        x1=jnp.where(inner, xe, x1),
        v1=jnp.where(inner, ve, v1),
        a1=jnp.where(inner, ae, a1),
        h=jnp.where(inner, te, h),
        guess=te,
        inner=inner,
    )
    if screen:
        # (No tangents: the estimate is not differentiated.)
        scale = c * jnp.exp2(jnp.log2(tol) / K)
        terms = (xs, vs, as_, v, outs["h"], scale)
        outs.update(_screen_terms(spec, *jax.tree.map(sg, terms)))
    # One loop for every output (`one_fusion`): the recurrence is computed once. It
    # stays one loop only while no expensive op (a division, a transcendental) in it
    # has several readers and the acceleration called here has no `one_fusion` of its
    # own; otherwise XLA's CPU fusion splits it and copies the recurrence into each
    # part (3-4x slower per lane-step, measured).
    out = one_fusion(outs)
    keys = ("x1", "v1", "a1", "h", "guess", "inner")
    return tuple(out[k] for k in keys) + (
        tuple(out[k] for k in ("W", "dq", "dv")) if screen else (None,) * 3
    )


def _screen_terms(spec, xs, vs, as_, v, hu, scale):
    """The step's terms of the first-order error bound (`_screen`), from its
    polynomials and the step `hu` taken."""
    K = spec.order
    # The step's truncation: the last two terms kept, the second-to-last scaled by
    # the step's ratio h/ρ to the radius of convergence (a bound on the first term
    # dropped, pessimistic by ρ/h). W = ∫ ds / v(s)² over the step by 3-point
    # Gauss–Legendre on the velocity polynomial; from rest (v = a0 s + ...) its
    # Hadamard finite part, ∫ (1/v² - 1/(a0 s)²) ds - 1/(a0² h). One division per
    # node (each has one reader, see `_taylor_step`).
    hk1 = hu ** (K - 1)
    dq = hk1 * (jnp.abs(xs[K]) * hu + scale * jnp.abs(xs[K - 1]))
    dv = hk1 * (jnp.abs(vs[K]) * hu + scale * jnp.abs(vs[K - 1]))
    rest = v == 0
    a2 = jnp.where(rest, as_[0] * as_[0], 1.0)
    w_sum = None
    for xi, wi in _GL3:
        sk = 0.5 * hu * (1.0 + xi)
        vk2 = _horner(vs, sk) ** 2
        d2 = a2 * sk * sk
        term = wi * (d2 - jnp.where(rest, vk2, 0.0)) / (vk2 * d2)
        w_sum = term if w_sum is None else w_sum + term
    W = 0.5 * hu * w_sum - jnp.where(rest, 1.0 / (a2 * hu), 0.0)
    return dict(W=W, dq=dq, dv=dv)


def _combine(coeffs, ks):
    """sum_j coeffs[j] ks[j], skipping exact zeros (the tableaux are sparse)."""
    out = None
    for cj, kj in zip(coeffs, ks):
        if cj == 0.0:
            continue
        term = cj * kj
        out = term if out is None else out + term
    return out


def _rk_step(tab, accel, s, x, v, a, h):
    """One step of the tableau for x' = v, v' = accel(s, x, v), all lanes at once.

    Returns the state at s + h, the acceleration there (FSAL) and the error estimate.
    """
    kx, kv = [v], [a]
    for ci, row in zip(tab.c[:-1] if tab.fsal else tab.c, tab.a):
        dx, dv = _combine(row, kx), _combine(row, kv)
        xi = x if dx is None else x + h * dx
        vi = v if dv is None else v + h * dv
        kx.append(vi)
        kv.append(accel(s + ci * h, xi, vi))
    x1 = x + h * _combine(tab.b, kx)
    v1 = v + h * _combine(tab.b, kv)
    # The field at the new point: for a FSAL tableau it is the last stage (whose
    # weight in b_error is not zero for Tsit5, Dopri5, Bosh3), else one more call.
    a1 = accel(s + h, x1, v1)
    if tab.fsal:
        kx.append(v1)
        kv.append(a1)
    ex, ev = h * _combine(tab.e, kx), h * _combine(tab.e, kv)
    return x1, v1, a1, ex, ev


# What ends a leg, per lane: the next turning point (σq̇ from + to 0), the point of
# maximum speed (σq̈ from + to 0), or a given position. Per lane rather than per
# compiled loop, so that one compiled kernel serves every leg of every method (and
# the tolerances of the error estimate's second solve): compile time is one loop.
TURNING, MAX_SPEED, POSITION = 0, 1, 2

# What each amplitude's lane hands in (packed as the columns of one array).
_OUT = ("sigma", "raw", "s", "x", "v", "steps")
# ... and with `_Pass.screen`, the sums of the first-order error bound (`_screen`).
_SCREEN_OUT = ("ph", "J", "F", "G")
# A lane's constants, the rows of its parameter block `p` (`_run_queue`).
_PARAMS = ("q0", "Qs", "tau", "xt", "limit", "kind", "rtol", "atol")


class _Pass(eqx.Module):
    """Everything static about one pass of the kernel over the queue.

    `legs`: legs per lane (2: through the turning point and back, for "full").
    `screen`: accumulate the sums of the first-order error bound (`_screen`).
    """

    tab: "_Tableau | Taylor"
    legs: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    screen: bool = eqx.field(static=True, default=False)


def _release(Lp, q0):
    """What one lane knows at its release point (a scalar `q0`): whether it can start
    (finite, a regular mass, a non-zero acceleration), and its own units: lengths
    `Qs` = |q0| (1 at 0), times `tau` = sqrt(Qs / |q̈0|), `sigma` the sign of q̈0."""
    zero = jnp.zeros((), q0.dtype)
    finite = jnp.isfinite(q0)
    q0 = jnp.where(finite, q0, 1.0)
    # (Unfused here: `_lane_scales` fuses this function's outputs as a whole.)
    a0, (M0, ok0) = _accelerations(Lp, q0[None], zero[None], zero, fuse=False)
    a0, M0 = a0[0], M0[0, 0]
    start_ok = ok0 & jnp.isfinite(a0)
    moving = a0 != 0
    valid = finite & start_ok & moving
    Qs = jnp.where(q0 != 0, jnp.abs(q0), 1.0)
    a0s = jnp.where(valid, a0, -1.0)
    return dict(
        q0=q0,
        finite=finite,
        start_ok=start_ok,
        moving=moving,
        valid=valid,
        M0=M0,
        a0s=a0s,
        Qs=Qs,
        tau=jnp.sqrt(Qs / jnp.abs(a0s)),
        sigma=jnp.sign(a0s),
    )


def _lane_scales(L, q0, consts):
    """`_release` of each lane (vmapped): validity, the lane's own units, and what
    `_finish` reads (computed once per pass: ~0.1 ms per 4096 lanes, measured)."""
    release = lambda q0: _release(lambda q, qd, t: L(q, qd, t, *consts), q0)
    # Its outputs through one fusion: each is read by several fusions (the table of
    # constants, `_finish`), and XLA copied the acceleration at q0, a call of the C
    # library's sine per lane for the pendulum, into each of them (see `_finish`).
    return one_fusion(jax.vmap(release)(q0))


def _scaled_acceleration(L, consts, fuse=None):
    """The acceleration in a lane's own units: `accel(q0, Qs, tau, s, x, v)`."""

    def accel_one(q0, Qs, tau, s, x, v):
        Vs, As = Qs / tau, Qs / tau**2
        qddot, _ = _accelerations(
            lambda q, qd, t: L(q, qd, t, *consts),
            (q0 + Qs * x)[None],
            (Vs * v)[None],
            tau * s,
            fuse=fuse,
        )
        # Behind a select (As > 0 always: the same values), the division has one
        # reader: XLA's CPU fusion will not copy an expensive op to several readers
        # and splits the Taylor step's fusion instead (measured, see _taylor_step).
        return jnp.where(As != 0, qddot[0] / As, jnp.nan)

    return accel_one


# Whether `Taylor` covers a Lagrangian, per function object (weakly held): the check
# traces the acceleration (~20 ms), which every eager call would otherwise repeat.
_TAYLOR_SUPPORT = weakref.WeakKeyDictionary()


def resolve_solver(solver, L, dtype):
    """The solver the kernel steps with: `Taylor(fallback=...)` is a plain `Taylor`
    where every primitive of L's acceleration has a recurrence and its program can be
    unrolled, its fallback elsewhere (decided from the jaxpr, once per function,
    dtype and solver; nothing is evaluated)."""
    if not (isinstance(solver, Taylor) and solver.fallback is not None):
        return solver
    try:
        known = _TAYLOR_SUPPORT.setdefault(L, {})
    except TypeError:  # not weakly referenceable: decide anew
        known = {}
    key = (jnp.dtype(dtype).name, solver)
    if key not in known:
        plain = Taylor(order=solver.order, max_step=solver.max_step)
        accel_one = _scaled_acceleration(L, ())
        scalar = jax.ShapeDtypeStruct((), dtype)
        accel = lambda s, x, v, q0, Qs, tau: accel_one(q0, Qs, tau, s, x, v)
        # With a recurrence for every primitive, and a program small enough to be
        # unrolled: the loop over orders ran 5-10x slower than the fallback (Taylor
        # docstring; measured).
        try:  # (tracing the order-K program also finds a primitive without one)
            supported = plain.unrolls(accel, dtype, scalar, scalar, scalar)
        except NotImplementedError:
            supported = False
        # The solver itself, made once: building it per call cost ~10 µs.
        known[key] = plain if supported else solver.fallback
    return known[key]


def _col(mask, like):
    """`mask` (per lane) shaped to select rows of `like`."""
    return mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))


def _run_queue(L, cfg: _Pass, q0s, targets, kinds, rtols, atols, t_max, consts, n_live):
    """The first `n_live` amplitudes of `q0s` (shape (n,)) through `cfg.width`
    refilling lanes (the rest are left unsolved).

    Returns per amplitude: raw outcome, event time (lane units), end state (x, v),
    steps (and with `cfg.screen` the error bound's sums); the number of executed
    lane-steps (for the useful-work statistic); and each amplitude's `_release`.
    """
    n = q0s.shape[0]
    W = width = min(cfg.width, n)  # (`width` in `body`, where W is a weight)
    dtype = q0s.dtype
    eps = jnp.finfo(dtype).eps
    tab = cfg.tab
    dtmin = 1024 * eps
    # diffrax.PIDController's defaults (I-controller): the same constants and rule.
    ctrl = dfx.PIDController(rtol=0.0, atol=0.0)
    safety, fmin, fmax = ctrl.safety, ctrl.factormin, ctrl.factormax
    taylor = isinstance(tab, Taylor)
    expo = 1.0 / (tab.order if taylor else tab.error_order)
    keys = _OUT + (_SCREEN_OUT if cfg.screen else ())

    accel_one = _scaled_acceleration(L, consts)

    # Traced once and reused by every call site (13 per Dopri8 step, the refinement,
    # the refill): tracing the scalarized equations anew at each cost ~13 ms apiece.
    # Not inlined into the kernel's jaxpr: `jvp` and `vmap` of the call are then
    # done once for all sites (jacfwd through a "matched" sweep: tracing 14.9 s ->
    # 9.6 s); XLA inlines the calls, the compiled loop runs as fast (measured).
    # Sines and cosines by `_trig.sincos`, which XLA vectorizes, not one libm call
    # per lane each (13 per Dopri8 step: Dopri8 quarter 1e-12, pendulum, one core,
    # 260k -> 395-414k periods/s, measured).
    # Without the acceleration's own `one_fusion` (a reduce): inside a step that is
    # one fusion (the Taylor step; a Runge-Kutta step's outputs, see `body`), a
    # nested reduce splits it. For the Taylor step, read by every output through the
    # event's location, XLA's code-duplication limit split the recurrence into ~14
    # fusions (4x slower per lane-step); a Dopri8 sweep ran 13% slower (measured).
    # The Taylor step's loop vectorizes only while LLVM's loop vectorizer can
    # prove its buffers apart: in a large fusion (the Taylor step with the error
    # bound's sums and the sines, or order >= 22) alias analysis no longer
    # separates them and it falls back to runtime alias checks,
    # one per (output, input) pair and per pair of outputs, with a limit of 128
    # (`-vectorize-memory-check-threshold`); above it the loop stays scalar, 3.4x
    # slower ("too many memory checks needed" in its remarks; measured). With 17
    # inputs and 9 outputs (189 checks) the estimate's step had to keep libm's
    # sines (round 2, session 11). Now it reads 9 buffers (117 checks: a margin of
    # one input): each lane's constants are one block `p`, and the refill is at
    # the end of the iteration (see `body`). With the sines the estimate's step
    # costs 14% less (2.57 vs 3.15 ms per call, pendulum, 4096 lanes, one core),
    # and orders 22 and 24 vectorize with the sums too. Watch the step fusion's
    # operand count (`--xla_dump_to`, `*after_optimizations.txt`) after changes to
    # the loop body: one more input of the step costs 9 checks.
    plain = _scaled_acceleration(L, consts, fuse=False)
    accel_plain = jax.jit(jax.vmap(vectorized_trig(plain)))

    # Each amplitude's release quantities, once for the whole queue: computing them
    # in the refill for every lane cost ~20% of a Taylor sweep (measured, 1 core).
    rel = _lane_scales(L, q0s, consts)

    # Each amplitude's constants, one column per amplitude and a last column for
    # idle lanes, so that a refill is one gather (each gather, scatter or small
    # fusion is a separate call of ~0.5-1 µs on a CPU: with ten of them and a
    # `lax.cond`, the refill cost as much as the Taylor step, measured). A lane
    # carries its column as ONE array `p` (a row per constant), not eight: one
    # input of the Taylor step's fusion instead of eight, under the limit of LLVM's
    # runtime alias checks (see `accel_plain`).
    valid, Qs, tau = rel["valid"], rel["Qs"], rel["tau"]
    rows = {  # name: (its value per amplitude, its value on an idle lane)
        "q0": (q0s, 1.0),
        "Qs": (Qs, 1.0),
        "tau": (tau, 1.0),
        # A POSITION event's target, in the lane's units.
        "xt": ((targets.astype(dtype) - q0s) / Qs, 0.0),
        "limit": (jnp.where(valid, t_max / tau, 0.0), 0.0),
        "kind": (kinds.astype(dtype), 0.0),
        "rtol": (rtols.astype(dtype), 1.0),
        "atol": (atols.astype(dtype), 1.0),
        "sigma": (rel["sigma"], 1.0),
        # The first step's length: computed in the refill, its `pow` (a libm call
        # per lane) cost ~8 ns per lane-step, twice (XLA also copied it into the
        # step's fusion; measured).
        "h0": (0.1 * jnp.minimum(rtols, atols).astype(dtype) ** expo, 1.0),
        "valid": (valid.astype(dtype), 0.0),
    }
    assert tuple(rows)[: len(_PARAMS)] == _PARAMS  # `p` is the first rows
    live_cols = jnp.stack([v for v, _ in rows.values()])
    idle_col = np.array([[idle] for _, idle in rows.values()], dtype)
    table = jnp.concatenate([live_cols, idle_col], axis=1)
    row = {k: i for i, k in enumerate(rows)}

    def load(idx):
        """Lane parameters and initial state for queue positions `idx` (>= n: idle)."""
        live = idx < n_live
        p = table[:, jnp.where(live, idx, n)]
        valid = p[row["valid"]] > 0
        z = jnp.zeros_like(p[0])
        # The error bound's sums (`_screen`), one array of five columns: the phase
        # (ph), energy errors times their leverage (J), ∫ds/v² (F; from rest its
        # finite part), the same without the first step (G), and the energy errors
        # so far (D). (One array: one select per refill and per step, not five.)
        sums = dict(sums=jnp.zeros(z.shape + (5,), dtype)) if cfg.screen else {}
        return dict(
            p=p[: len(_PARAMS)],
            idx=jnp.where(live, idx, n).astype(jnp.int32),
            done=~valid,
            raw=jnp.where(live & ~valid, INVALID, LOCATED).astype(jnp.int32),
            sigma=p[row["sigma"]],
            leg=jnp.zeros_like(idx, jnp.int32),
            s=z,
            x=z,
            v=z,
            a=p[row["sigma"]],  # q̈(q0) in the lane's units is ±1 by construction
            h=p[row["h0"]],
            steps=jnp.zeros_like(idx, jnp.int32),
            # Event location: trials from the frozen base (s, x, v, a).
            locating=jnp.zeros_like(idx, bool),
            lo=z,
            hi=z,
            glo=z,
            ghi=z,
            hp=z,  # the previous trial (step length, event value), for the secant
            gp=z,
            hsave=z,  # the controller's step size when the crossing was found
            tries=jnp.zeros_like(idx, jnp.int32),
            **sums,
        )

    def fuse_fields(fields):
        """The same lane fields, those of shape (width,) from one fusion."""
        flat = {k: val for k, val in fields.items() if val.shape == (width,)}
        return dict(fields, **one_fusion(flat))

    def g_of(lane, x, v, a):
        return _event_value(lane["kind"], lane["sigma"], lane["xt"], x, v, a)

    def body(carry):
        lane, out, nxt, it, _ = carry
        params = {k: lane["p"][i] for i, k in enumerate(_PARAMS)}
        params["kind"] = params["kind"].astype(kinds.dtype)
        lane = dict(lane, **params)
        s, x, v, a, h = lane["s"], lane["x"], lane["v"], lane["a"], lane["h"]
        active = ~lane["done"]

        def accel(si, xi, vi):
            return accel_plain(lane["q0"], lane["Qs"], lane["tau"], si, xi, vi)

        rtol, atol, kind = lane["rtol"], lane["atol"], lane["kind"]
        if taylor:
            p = (lane["q0"], lane["Qs"], lane["tau"])
            coeffs = taylor_coefficients(
                lambda s, x, v, p: accel_one(*p, s, x, v),
                tab.order,
                dtype,
                True,
                vectorized_trig=True,
            )
            cap = jnp.maximum(lane["limit"] - s, dtmin)
            x1, v1, a1, h, te, inner, W, dq, dv = _taylor_step(
                tab,
                lambda s, x, v: coeffs(s, x, v, p),
                lambda si, xi, vi: accel_plain(*p, si, xi, vi),
                s,
                x,
                v,
                h,
                ~lane["locating"],
                rtol,
                atol,
                cap,
                (kind, lane["sigma"], lane["xt"]),
                screen=cfg.screen,
            )
            # Chosen before it is taken: never rejected; a non-finite step fails.
            err = jnp.where(jnp.isfinite(h), 0.0, jnp.nan)
        else:
            x1, v1, a1, ex, ev = _rk_step(tab, accel, s, x, v, a, h)
            sx = atol + rtol * jnp.maximum(jnp.abs(x), jnp.abs(x1))
            sv = atol + rtol * jnp.maximum(jnp.abs(v), jnp.abs(v1))
            err = jnp.sqrt(0.5 * ((ex / sx) ** 2 + (ev / sv) ** 2))
            # The step's outputs from one fusion: each stage's value has several
            # readers (the later stages, b, b_error), so XLA kept the 13 stages as
            # separate fusions (Dopri8 quarter 1e-12, pendulum, one core: 472-477k
            # -> 505k periods/s, measured).
            fused = one_fusion(dict(x1=x1, v1=v1, a1=a1, err=err))
            x1, v1, a1, err = (fused[k] for k in ("x1", "v1", "a1", "err"))
        finite = jnp.isfinite(err) & jnp.isfinite(x1) & jnp.isfinite(v1)
        finite = finite & jnp.isfinite(a1)
        accept = finite & (err <= 1.0)
        if taylor:
            # (err is 0 or NaN: the factor is a constant, without a `pow` per lane,
            # a libm call of ~8 ns per lane-step, measured.)
            grow = float(np.clip(safety * 1e10**expo, 1.0, fmax))
            factor = jnp.where(finite, grow, 0.0)
        else:
            grows = finite & (err > 0)
            inv = jnp.where(grows, 1.0 / jnp.where(err > 0, err, 1.0), 1e10)
            factor = jnp.clip(
                safety * _root(inv, tab.error_order),
                jnp.where(accept, 1.0, fmin),
                jnp.where(accept, fmax, safety),
            )
            factor = jnp.where(finite, factor, fmin)
        h_next = jax.lax.stop_gradient(h * factor)
        g1 = g_of(lane, x1, v1, a1)
        locating = lane["locating"]

        # --- stepping lanes
        crossed = accept & (g1 <= 0) & ~locating
        if taylor:
            # Located inside the step (`_taylor_step`): x1, v1, a1, h are the event's.
            crossed = crossed | inner
        advance = accept & ~crossed & ~locating
        # --- locating lanes: bracket [lo, hi] of step lengths from the base
        pos = g1 > 0
        lo = jnp.where(locating & pos, h, lane["lo"])
        glo = jnp.where(locating & pos, g1, lane["glo"])
        hi = jnp.where(locating & ~pos, h, lane["hi"])
        ghi = jnp.where(locating & ~pos, g1, lane["ghi"])
        lo = jnp.where(crossed, 0.0, lo)
        glo = jnp.where(crossed, g_of(lane, x, v, a), glo)
        hi = jnp.where(crossed, h, hi)
        ghi = jnp.where(crossed, g1, ghi)
        # σq̈ = 0: secant through the two latest trials. σq̇ = 0 or σ(x_t - x) = 0:
        # Newton, whose derivative (σq̈ or -σq̇ at the trial's end) is at hand.
        # Both are a few flops; each lane takes its own. Kept inside the bracket.
        hp = jnp.where(crossed, 0.0, lane["hp"])
        gp = jnp.where(crossed, glo, lane["gp"])
        denom = g1 - gp
        secant = h - g1 * (h - hp) / jnp.where(denom != 0, denom, 1.0)
        dg = _event_slope(kind, lane["sigma"], v1, a1)
        newton = h - g1 / jnp.where(dg != 0, dg, 1.0)
        guess = jnp.where(kind == MAX_SPEED, secant, newton)
        inside = (guess > lo) & (guess < hi) & jnp.isfinite(guess)
        guess = jnp.where(inside, guess, 0.5 * (lo + hi))
        if taylor:
            # The event located inside the crossing step (`_taylor_step`): done in
            # this iteration where its last Newton correction was below 1e-8 of the
            # step (the next one would be below round-off); else its estimate is the
            # first trial (module docstring).
            guess = jnp.where(crossed & (te > lo) & (te < hi), te, guess)
        conv_tol = 4 * eps * jnp.maximum(jnp.abs(s + h), 1.0)
        # The event value is known only to its rounding: for σq̇ that of q̇ + hΣb q̈
        # (measured: Newton otherwise stalls there on 5% of the pendulum's lanes); for
        # σq̈, that of q̈, whose scale is 1 in the lane's units.
        g_scale = jnp.where(
            kind == MAX_SPEED,
            1.0,
            jnp.where(
                kind == TURNING,
                jnp.abs(v) + 4 * jnp.abs(h * a1),
                jnp.abs(x) + jnp.abs(lane["xt"]) + 4 * jnp.abs(h * v1),
            ),
        )
        g_noise = 8 * eps * g_scale
        converged = (
            (locating | crossed)
            & finite
            & ((jnp.abs(guess - h) <= conv_tol) | (jnp.abs(g1) <= g_noise))
        )
        converged = converged & ((err <= 10.0) | crossed)
        if taylor:
            converged = converged | inner
        tries = jnp.where(crossed, 0, lane["tries"] + locating.astype(jnp.int32))
        gave_up = locating & ~converged & (tries >= _MAX_LOCATE)
        # A crossing exactly at the end of an accepted step needs no trials.
        new_locating = (locating | crossed) & ~converged & ~gave_up

        # --- the new state
        moved = advance | converged
        s_new = jnp.where(moved, s + h, s)
        x_new = jnp.where(moved, x1, x)
        v_new = jnp.where(moved, v1, v)
        a_new = jnp.where(moved, a1, a)
        hsave = jnp.where(crossed, h_next, lane["hsave"])
        h_new = jnp.where(new_locating, jax.lax.stop_gradient(guess), h_next)
        # After a located event, go on with the step size from before the crossing.
        h_new = jnp.where(converged, hsave, h_new)
        steps = lane["steps"] + active.astype(jnp.int32)
        if cfg.screen:
            # The step's errors (truncation bound plus rounding of the state), as a
            # time shift δx/|v| and an energy error per unit mass |v|δv + |a|δx;
            # an energy error made before this step moves the leg's end by its
            # leverage ∫ds/v² over the rest of the leg (`_screen`).
            x_err = dq + 4 * eps * (1.0 + jnp.abs(x1))
            v_err = dv + 4 * eps * (jnp.abs(v1) + jnp.abs(h * a1))
            e_err = jnp.abs(v1) * v_err + jnp.abs(a1) * x_err
            shift_ = x_err / jnp.abs(v1)
            from_rest = v == 0
            sums = lane["sums"]
            inc = (shift_, sums[:, 4] * W, W, jnp.where(from_rest, 0.0, W), e_err)
            inc = jax.lax.stop_gradient(jnp.stack(inc, axis=1))

        # --- lane outcomes
        escape = _ESCAPE * jnp.maximum(lane["Qs"], 1.0) / lane["Qs"]
        escaped = advance & (jnp.abs(x_new) > escape)
        ran_out = advance & (s_new >= lane["limit"])
        h_new = jnp.minimum(h_new, jnp.maximum(lane["limit"] - s_new, dtmin))
        collapsed = ~new_locating & ~moved & (h_next < dtmin)
        out_of_steps = steps >= cfg.max_steps
        leg = lane["leg"]
        if cfg.legs == 2:
            next_leg = converged & (leg == 0)
            finished = converged & (leg == 1)
        else:
            next_leg = jnp.zeros_like(converged)
            finished = converged
        # Nested `where`s, not `jnp.select` (an argmax over the stacked conditions,
        # a reduction XLA recomputed the whole step into: measured 5x the step).
        raw = lane["raw"]
        for cond_, code in reversed(
            [
                (finished, LOCATED),
                (gave_up, LOCATE_FAILED),
                (escaped | ran_out, NO_EVENT),
                (collapsed, STEP_FAILED),
                (out_of_steps, MAX_STEPS),
            ]
        ):
            raw = jnp.where(cond_, code, raw)
        ends = active & (
            finished | gave_up | escaped | ran_out | collapsed | out_of_steps
        )
        # The second leg of "full" starts at rest at the turning point just found, at a
        # time that carries the implicit-function tangent of the event (zero primal).
        dg1 = _event_slope(kind, lane["sigma"], v1, a1)
        corr = -g1 / jnp.where(dg1 != 0, dg1, 1.0)
        corr = jnp.where(jnp.isfinite(corr), corr, 0.0)
        s_new = jnp.where(next_leg, s_new + (corr - jax.lax.stop_gradient(corr)), s_new)
        sigma = jnp.where(next_leg, jnp.sign(a_new), lane["sigma"])
        v_new = jnp.where(next_leg, 0.0, v_new)
        lane = dict(
            lane,
            done=lane["done"] | ends,
            raw=raw,
            sigma=sigma,
            leg=leg + next_leg.astype(jnp.int32),
            s=s_new,
            x=x_new,
            v=v_new,
            a=a_new,
            h=h_new,
            steps=steps,
            locating=new_locating & active,
            lo=lo,
            hi=hi,
            glo=glo,
            ghi=ghi,
            tries=tries,
            hsave=hsave,
        )
        lane["hp"] = jnp.where(locating | crossed, h, lane["hp"])
        lane["gp"] = jnp.where(locating | crossed, g1, lane["gp"])
        for k in _PARAMS:
            del lane[k]
        # The lane's new fields from one fusion, with `moved` for the error bound's
        # sums (below): XLA computed them in ~30 small fusions, each a separate call
        # (~0.1-0.2 µs on a CPU), and copied ten carried fields per iteration because
        # some readers of their old values were not ordered before the writers.
        # Measured (one core, alternated 8-s loops): Dopri8 "quarter" 1e-12 +15-20%,
        # the default sweep +4-6% (with `moved` outside it, its sums' fusion
        # recomputed it: -6%).
        lane = fuse_fields(dict(lane, **(dict(moved=moved) if cfg.screen else {})))
        if cfg.screen:
            moved = lane.pop("moved")
            lane["sums"] = jnp.where(moved[:, None], sums + inc, sums)

        # --- lanes that are done hand in their result and are given the next amplitude
        done = lane["done"] & (lane["idx"] < n)
        cols = [lane[k].astype(dtype) for k in _OUT]
        if cfg.screen:
            cols += [lane["sums"][:, i] for i in range(len(_SCREEN_OUT))]
        rows = jnp.stack(cols, axis=1)
        out = out.at[jnp.where(done, lane["idx"], n)].set(rows, mode="drop")
        # Lanes that are done take the next amplitudes, at the end of the iteration:
        # the next step then reads the carried buffers themselves. (Refilled at
        # its start, XLA fused the refill's selects into the Taylor step's fusion,
        # three inputs per field (flag, old, new): with ~17 inputs and 9 outputs
        # LLVM's loop vectorizer needs more runtime alias checks than its limit,
        # see `accel_plain`.)
        free = lane["done"]
        rank = jnp.cumsum(free.astype(jnp.int32))
        pending = jnp.where(free, nxt + rank - 1, n).astype(jnp.int32)
        new = load(pending)
        lane = {
            k: jnp.where(free if k == "p" else _col(free, old), new[k], old)
            for k, old in lane.items()
        }
        # (One fusion again: Dopri8 "quarter" +8-12%, the default sweep neutral.)
        lane = fuse_fields(lane)
        # Lanes with an amplitude (to step, or to hand in): those not free, and the
        # free ones that took one. Counted from the refill's own total, not by a
        # reduction over the lanes in `cond` (three more kernels per iteration).
        n_free = rank[-1]
        busy = (width - n_free + jnp.clip(n_live - nxt, 0, n_free)).astype(jnp.int32)
        return lane, out, (nxt + n_free).astype(jnp.int32), it + 1, busy

    def cond(carry):
        *_, it, busy = carry
        return (busy > 0) | (it == 0)

    # Every lane starts done and idle: the first iteration steps nothing and its
    # refill loads the first amplitudes, so no copy of `load` is compiled outside
    # the loop (a default sweep compiles 151 fusions instead of 166, ~15 ms each;
    # the same numbers).
    shapes = jax.eval_shape(load, jnp.arange(W, dtype=jnp.int32))
    lane = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
    lane = dict(lane, done=jnp.ones(W, bool), idx=jnp.full(W, n, jnp.int32))
    out = jnp.zeros((n, len(keys)), dtype)
    nxt, it = jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32)
    init = (lane, out, nxt, it, jnp.zeros((), jnp.int32))
    lane, out, _, iterations, _ = jax.lax.while_loop(cond, body, init)
    out = {k: out[:, i] for i, k in enumerate(keys)}
    out["raw"] = out["raw"].astype(jnp.int32)
    out["steps"] = out["steps"].astype(jnp.int32)
    return out, iterations * W, rel


def _event_value(kind, sigma, xt, x, v, a):
    """The event function g, positive during a leg, crossing to <= 0 at its end."""
    return sigma * jnp.where(
        kind == TURNING, v, jnp.where(kind == MAX_SPEED, a, xt - x)
    )


def _event_slope(kind, sigma, v, a):
    """dg/ds along the motion where it needs no extra evaluation (MAX_SPEED: 1)."""
    return jnp.where(
        kind == TURNING, sigma * a, jnp.where(kind == POSITION, -sigma * v, 1.0)
    )


def _finish(L, consts, q0, targets, kinds, rtols, out, rel, energy_tol):
    """Statuses, event times and end states from the loop's raw outcomes (vmapped).
    `rel`: each lane's `_release` (`_lane_scales`)."""
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    zero = jnp.zeros((), dtype)
    Lp = lambda q, qd, t: L(q, qd, t, *consts)

    def one(r, target, kind, rtol, sigma, raw, s_e, x_e, v_e, ph, J, F, G):
        q0, finite_q0 = r["q0"], r["finite"]
        start_ok, moving = r["start_ok"], r["moving"]
        M0, a0s, Qs, tau = r["M0"], r["a0s"], r["Qs"], r["tau"]
        q_end, qdot_end, t_end = q0 + Qs * x_e, (Qs / tau) * v_e, tau * s_e
        h0, size0 = _jacobi(Lp, q0[None], zero[None], zero)
        h1, size1 = _jacobi(Lp, q_end[None], qdot_end[None], t_end)
        scale = jnp.abs(M0 * a0s) * Qs
        tol = jnp.sqrt(rtol) if energy_tol is None else energy_tol
        allowed = tol * scale + 1024 * eps * (size0 + size1)
        drifted = ~(jnp.abs(h1 - h0) <= allowed)  # NaN energies count as drift
        _, (M_end, ok_end) = _accelerations(
            Lp, q_end[None], qdot_end[None], t_end, fuse=False
        )
        # The estimate's sums in time units (`_screen`); they assume a constant
        # mass, checked at the leg's two ends.
        const_mass = jnp.abs(M_end[0, 0] - M0) <= 8 * eps * jnp.abs(M0)
        terms = (tau * ph, tau * J, tau * F / Qs, jnp.where(const_mass, G, jnp.inf))
        status = jnp.select(
            [raw == LOCATED, raw == LOCATE_FAILED, raw == NO_EVENT, raw == MAX_STEPS],
            [SUCCESS, ROOT_FIND_FAILED, NOT_OSCILLATING, S_MAX_STEPS],
            SOLVER_FAILED,
        )
        status = jnp.select(
            [
                (status == SUCCESS) & drifted,
                (status != SUCCESS) & (status != NOT_OSCILLATING) & ~ok_end,
                (status == NOT_OSCILLATING) & drifted & jnp.isfinite(h1),
            ],
            [ENERGY_DRIFT, SINGULAR_MASS, ENERGY_DRIFT],
            status,
        )
        status = jnp.select(
            [~finite_q0, ~start_ok, ~moving],
            [NONFINITE_INPUT, SINGULAR_MASS, NOT_OSCILLATING],
            status,
        )

        a_e = accel(r, s_e, x_e, v_e)
        xt = (target - q0) / Qs
        g = _event_value(kind, sigma, xt, x_e, v_e, a_e)
        _, jerk = jax.jvp(
            lambda s, x, v: accel(r, s, x, v),
            (s_e, x_e, v_e),
            (jnp.ones_like(s_e), v_e, a_e),
        )
        ends = (status.astype(jnp.int32), q_end, qdot_end, a_e, g, jerk)
        return ends, terms

    # The loop's step lengths carry no tangent (the controller's choices are not
    # differentiated); the event time's tangent is the implicit function's,
    # ds = -dg/ġ, added here with a zero primal.
    def accel(r, s, x, v):
        q0, Qs, tau = r["q0"], r["Qs"], r["tau"]
        qddot, _ = _accelerations(
            Lp, (q0 + Qs * x)[None], (Qs / tau * v)[None], tau * s, fuse=False
        )
        return qddot[0] * tau**2 / Qs

    def central(r, s_e, x_e, v_e, a_e):
        # The user's L may have a removable singularity in a third derivative exactly
        # at the event (x ** p with an array of exponents at x = 0 gives 0 * inf):
        # then a central difference along the flow.
        d = 1e-5
        return (
            accel(r, s_e + d, x_e + v_e * d + 0.5 * a_e * d**2, v_e + a_e * d)
            - accel(r, s_e - d, x_e - v_e * d + 0.5 * a_e * d**2, v_e - a_e * d)
        ) / (2 * d)

    def two(r, kind, sigma, raw, s_e, v_e, a_e, g, jerk, q_end, qdot_end):
        Qs, tau = r["Qs"], r["tau"]
        gdot = jnp.where(
            kind == MAX_SPEED, sigma * jerk, _event_slope(kind, sigma, v_e, a_e)
        )
        # The implicit function theorem at g = 0: ds = -dg / ġ. The tangent of ġ
        # multiplies g, zero to rounding, and is dropped: differentiating the jerk
        # (a third derivative of L) again tripled the compile time of a gradient.
        gdot = jax.lax.stop_gradient(gdot)
        corr = -g / jnp.where(gdot != 0, gdot, 1.0)
        # A correction that is not finite carries no tangent and must not touch the
        # value (its primal contribution is zero).
        corr = jnp.where(jnp.isfinite(corr), corr, 0.0)
        # Only a located event defines its time by g = 0: any other end state (one
        # that "matched" may use as its meeting point, see `_run_method`) is the
        # state at a time, whose tangent is the state's own.
        corr = jnp.where(raw == LOCATED, corr, 0.0)
        dcorr = corr - jax.lax.stop_gradient(corr)  # zero, with the event's tangent
        t_e = tau * (s_e + dcorr)
        # The state at the event moves with it: (x, v) + (v, a) δs to first order. The
        # event's position is the target of "matched"'s second leg: without this its
        # dT/dparameter was off by 15-30 % on a bead track (tests/test_gradients.py).
        q_end = q_end + Qs * v_e * dcorr
        qdot_end = qdot_end + (Qs / tau) * a_e * dcorr
        return t_e, q_end, qdot_end

    sums = (out.get(k, jnp.zeros_like(q0)) for k in _SCREEN_OUT)
    s_e, x_e, v_e = out["s"], out["x"], out["v"]
    per_lane = (targets, kinds, rtols, out["sigma"], out["raw"], s_e, x_e, v_e)
    ends, terms = jax.vmap(one)(rel, *per_lane, *sums)
    # One fusion for the per-lane outputs, so that L's values at the two ends of the
    # leg (energies, mass, acceleration, jerk) are computed once each, not once per
    # reader: with `_lane_scales`'s, the compiled default sweep has 7 calls of the C
    # library's sine or cosine per lane and pass instead of 11, and 174 kernels to
    # compile instead of 185; ~2% faster (pendulum, 4096 amplitudes, one core, three
    # alternated pairs; `lagrax._jaxpr.trig`'s sines here instead were slower, more code
    # per copy).
    both = one_fusion(dict(enumerate(ends + terms)))
    ends = tuple(both[i] for i in range(len(ends)))
    terms = tuple(both[len(ends) + i] for i in range(len(terms)))
    status, q_end, qdot_end, a_e, g, jerk = ends
    # (The central difference only where some jerk is not finite: two more
    # accelerations per lane otherwise, ~0.05 ms per 4096 lanes and pass.)
    bad = ~jnp.isfinite(jerk)
    jerk = jax.lax.cond(
        jnp.any(bad),
        lambda: jnp.where(bad, jax.vmap(central)(rel, s_e, x_e, v_e, a_e), jerk),
        lambda: jerk,
    )
    lanes = (rel, kinds, out["sigma"], out["raw"], s_e, v_e, a_e, g, jerk)
    t_e, q_end, qdot_end = jax.vmap(two)(*lanes, q_end, qdot_end)
    return (status, t_e, q_end, qdot_end), terms


@eqx.filter_jit
def _pass(L, cfg, lanes, consts, t_max, energy_tol):
    """One pass of the kernel over every lane of one device, compiled once per static
    configuration (`L`, `cfg`, shapes). `lanes`: per-lane arrays `(q0, targets, kinds,
    rtols, atols, live)`, the live lanes a prefix (the others are never loaded).
    Returns `(status, t_event, q_end, qdot_end, steps, *bound_sums), executed`."""
    q0, targets, kinds, rtols, atols, live = lanes
    t_lim = jnp.asarray(_NO_LIMIT if t_max is None else t_max, q0.dtype)
    n_live = jnp.sum(live.astype(jnp.int32))
    out, executed, rel = _run_queue(
        L, cfg, q0, targets, kinds, rtols, atols, t_lim, consts, n_live
    )
    (status, t_e, q_e, qd_e), terms = _finish(
        L, consts, q0, targets, kinds, rtols, out, rel, energy_tol
    )
    return (status, t_e, q_e, qd_e, out["steps"], *terms), executed
