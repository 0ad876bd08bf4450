r"""What ends a leg, and how the period loop finds it.

A leg ends at an event: the next turning point ($\sigma\dot q$ from $+$ to $0$), the
point of maximum speed ($\sigma\ddot q$ from $+$ to $0$), or a given position. The
kind is per lane rather than per compiled loop, so that one compiled kernel serves
every leg of every method: compile time is one loop.

The event is detected by a sign change over an accepted step, with a direction, so
that the exact zero at release does not fire it. Where the step has polynomials
(a Taylor step), they are the solution over the whole step, and the event is their
root, found inside the step that crosses it (`locate_in_step`). Otherwise, and where
that root is not good to round-off, it is located by trial steps from the last
accepted state with the step length as the unknown (`search`): Newton with the exact
derivative for $\dot q = 0$ and a position (the acceleration or the velocity at the
trial's end), a safeguarded secant for $\ddot q = 0$. Each trial is a full step of the
solver, so the located state is as accurate as any accepted step.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._stepper.base import horner_with_derivative, StepResult


TURNING, MAX_SPEED, POSITION = 0, 1, 2

# Newton (q̇ = 0) converges in 2–3 trials, the secant (q̈ = 0) in 4–6; a lane that
# has not converged after this many trials is reported as not located.
_MAX_LOCATE = 12

# The event polynomial's root: Newton from regula falsi, first on its leading terms
# (cheap; each Horner sweep is a chain of dependent multiply-adds), then on all.
_ROOT_LOW_TERMS, _ROOT_LOW_ITERS, _ROOT_FULL_ITERS = 8, 2, 1


class Event(eqx.Module):
    """Each lane's event: its `kind`, the sign `sigma` that makes the event function
    positive during the leg, and the target `xt` of a `POSITION` event."""

    kind: Array
    sigma: Array
    xt: Array

    def value(self, x, v, a):
        """The event function g, positive during a leg, crossing to <= 0 at its end."""
        k = self.kind
        return self.sigma * jnp.where(
            k == TURNING, v, jnp.where(k == MAX_SPEED, a, self.xt - x)
        )

    def slope(self, v, a):
        """dg/ds along the motion where it needs no extra evaluation (MAX_SPEED: 1)."""
        k, sigma = self.kind, self.sigma
        return jnp.where(
            k == TURNING, sigma * a, jnp.where(k == POSITION, -sigma * v, 1.0)
        )

    def polynomial(self, xs, vs, as_):
        """The coefficients of g(s + τ) from a step's polynomials: σ v(τ), σ a(τ)
        (degree K - 1) or σ (x_t - x(τ)), by each lane's kind."""
        K = len(xs) - 1
        cs = []
        for k in range(K + 1):
            ak = as_[k] if k < K else jnp.zeros_like(xs[k])
            c = jnp.where(
                self.kind == TURNING,
                vs[k],
                jnp.where(self.kind == MAX_SPEED, ak, -xs[k]),
            )
            if k == 0:
                c = c + jnp.where(self.kind == POSITION, self.xt, 0.0)
            cs.append(self.sigma * c)
        return cs


def _polynomial_root(cs, h, g0, g1):
    """A root in [0, h] of the event polynomial `cs` (g0 > 0 at 0, the exact g1 <= 0
    at h on the lanes that crossed), good to ~1e-10 of h."""
    d = g0 - g1
    t = jnp.where(d > 0, g0 * h / jnp.where(d > 0, d, 1.0), 0.5 * h)
    for n in range(_ROOT_LOW_ITERS + _ROOT_FULL_ITERS):
        g, dg = horner_with_derivative(
            cs[:_ROOT_LOW_TERMS] if n < _ROOT_LOW_ITERS else cs, t
        )
        tn = t - g / jnp.where(dg != 0, dg, 1.0)
        t = jnp.where((tn > 0) & (tn < h), tn, t)
    return t


class InStep(eqx.Module):
    """The event located inside a step from its polynomials: `t`, its step length
    (the first trial where it is not good enough), and `inside`, the lanes whose step
    now ends at it."""

    t: Float[Array, " lanes"]
    inside: Bool[Array, " lanes"]


def locate_in_step(raw: StepResult, event: Event, accel, s, x, v, free):
    """The event inside the step: Newton on the event polynomial, then one Newton
    correction with the exact event value there (for q̈ = 0 the acceleration's own
    series, of degree K - 1, is far less accurate than x(τ)). Located where the step
    crossed and that correction was below 1e-8 of the step (another would be below
    round-off): the step then ends at the event. Returns `(raw, InStep)`."""
    xs, vs, as_ = raw.expansion.xs, raw.expansion.vs, raw.expansion.as_
    x1, v1, a1, h = raw.x, raw.v, raw.a, raw.h
    g0 = event.value(x, v, as_[0])
    g1 = event.value(x1, v1, a1)
    sg = jax.lax.stop_gradient
    cs = sg(event.polynomial(xs, vs, as_))
    tp = _polynomial_root(cs, h, sg(g0), sg(g1))
    xe, ve = raw.expansion.at(tp)
    ae = accel(s + tp, xe, ve)
    da = horner_with_derivative(as_, tp)[1]
    ge = event.value(xe, ve, ae)
    k = event.kind
    se = event.sigma * jnp.where(k == TURNING, ae, jnp.where(k == MAX_SPEED, da, -ve))
    # (A division read by several values splits XLA's fusion of the step: the CPU
    # fusion pass will not duplicate an expensive op, and copies the cheap recurrence
    # into each part instead. Behind a select the division has one reader.)
    dt = sg(jnp.where(se != 0, -ge / jnp.where(se != 0, se, 1.0), 0.0))
    te = tp + dt
    crossed = free & (g1 <= 0) & jnp.isfinite(h) & jnp.isfinite(x1) & jnp.isfinite(v1)
    crossed = crossed & jnp.isfinite(a1)
    xe, ve, ae = xe + ve * dt, ve + ae * dt, ae + sg(da) * dt
    inner = crossed & (jnp.abs(dt) <= 1e-8 * h) & (te > 0) & (te <= h)
    inner = inner & jnp.isfinite(xe) & jnp.isfinite(ve) & jnp.isfinite(ae)
    raw = dataclasses.replace(
        raw,
        x=jnp.where(inner, xe, x1),
        v=jnp.where(inner, ve, v1),
        a=jnp.where(inner, ae, a1),
        h=jnp.where(inner, te, h),
    )
    return raw, InStep(te, inner)


class Search(eqx.Module):
    """A lane's search for its event by trial steps from the frozen base (s, x, v, a):
    the bracket `[lo, hi]` of step lengths and the event values there, the previous
    trial `(hp, gp)` for the secant, the controller's step length `hsave` when the
    crossing was found, and the trials so far."""

    locating: Bool[Array, " lanes"]
    lo: Float[Array, " lanes"]
    hi: Float[Array, " lanes"]
    glo: Float[Array, " lanes"]
    ghi: Float[Array, " lanes"]
    hp: Float[Array, " lanes"]
    gp: Float[Array, " lanes"]
    hsave: Float[Array, " lanes"]
    tries: Int[Array, " lanes"]


class Found(eqx.Module):
    """What one iteration's step says about each lane's event."""

    crossed: Bool[Array, " lanes"]  # an accepted step crossed the event
    advance: Bool[Array, " lanes"]  # an accepted step before the event
    converged: Bool[Array, " lanes"]  # the event is located: the step ends there
    gave_up: Bool[Array, " lanes"]
    locating: Bool[Array, " lanes"]  # trials go on from the base
    guess: Float[Array, " lanes"]  # the next trial's step length
    bracket: tuple  # (lo, hi, glo, ghi)
    tries: Int[Array, " lanes"]


def search(event, base, old: Search, step: StepResult, g1, accept, finite, located):
    """One iteration of the event search on every lane: whether the step crossed the
    event or located it, the bracket, and the next trial. `base`: the lanes'
    `(s, x, v, a)`; `located`: an `InStep`, or None."""
    locating, h = old.locating, step.h
    crossed = accept & (g1 <= 0) & ~locating
    if located is not None:  # (x1, v1, a1, h are the event's there)
        crossed = crossed | located.inside
    advance = accept & ~crossed & ~locating
    pos = g1 > 0
    lo = jnp.where(locating & pos, h, old.lo)
    glo = jnp.where(locating & pos, g1, old.glo)
    hi = jnp.where(locating & ~pos, h, old.hi)
    ghi = jnp.where(locating & ~pos, g1, old.ghi)
    lo = jnp.where(crossed, 0.0, lo)
    glo = jnp.where(crossed, event.value(*base[1:]), glo)
    hi = jnp.where(crossed, h, hi)
    ghi = jnp.where(crossed, g1, ghi)
    guess = _next_trial(event, old, step, g1, crossed, lo, hi, glo, located)
    converged = _converged(event, base, step, g1, locating | crossed, guess, finite)
    converged = converged & ((step.error <= 10.0) | crossed)
    if located is not None:
        converged = converged | located.inside
    tries = jnp.where(crossed, 0, old.tries + locating.astype(jnp.int32))
    gave_up = locating & ~converged & (tries >= _MAX_LOCATE)
    # A crossing exactly at the end of an accepted step needs no trials.
    new_locating = (locating | crossed) & ~converged & ~gave_up
    bracket = (lo, hi, glo, ghi)
    return Found(
        crossed, advance, converged, gave_up, new_locating, guess, bracket, tries
    )


def _next_trial(event, old: Search, step, g1, crossed, lo, hi, glo, located):
    """The next trial's step length: σq̈ = 0, the secant through the two latest
    trials; σq̇ = 0 or σ(x_t - x) = 0, Newton, whose derivative (σq̈ or -σq̇ at the
    trial's end) is at hand; both kept inside the bracket. After a crossing, the
    event's location inside the step first (where it was not good enough)."""
    h = step.h
    hp = jnp.where(crossed, 0.0, old.hp)
    gp = jnp.where(crossed, glo, old.gp)
    denom = g1 - gp
    secant = h - g1 * (h - hp) / jnp.where(denom != 0, denom, 1.0)
    dg = event.slope(step.v, step.a)
    newton = h - g1 / jnp.where(dg != 0, dg, 1.0)
    guess = jnp.where(event.kind == MAX_SPEED, secant, newton)
    inside = (guess > lo) & (guess < hi) & jnp.isfinite(guess)
    guess = jnp.where(inside, guess, 0.5 * (lo + hi))
    if located is not None:
        te = located.t
        guess = jnp.where(crossed & (te > lo) & (te < hi), te, guess)
    return guess


def _converged(event, base, step, g1, trial, guess, finite):
    """Lanes whose trial located the event: the next trial would move by rounding,
    or the event value is at its rounding."""
    s, x, v, _ = base
    h, v1, a1 = step.h, step.v, step.a
    eps = jnp.finfo(h.dtype).eps
    conv_tol = 4 * eps * jnp.maximum(jnp.abs(s + h), 1.0)
    # The event value is known only to its rounding: for σq̇ that of q̇ + hΣb q̈
    # (Newton otherwise stalls there on a few lanes); for σq̈, that of q̈, whose
    # scale is 1 in the lane's units.
    g_scale = jnp.where(
        event.kind == MAX_SPEED,
        1.0,
        jnp.where(
            event.kind == TURNING,
            jnp.abs(v) + 4 * jnp.abs(h * a1),
            jnp.abs(x) + jnp.abs(event.xt) + 4 * jnp.abs(h * v1),
        ),
    )
    g_noise = 8 * eps * g_scale
    return (
        trial & finite & ((jnp.abs(guess - h) <= conv_tol) | (jnp.abs(g1) <= g_noise))
    )
