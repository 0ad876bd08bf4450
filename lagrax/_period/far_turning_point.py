r"""The far turning point of a swing, from the energy at rest.

For $L$ even in $\dot q$ and without explicit time, the energy at rest is $-L(q, 0)$:
the turning point beyond the point of maximum speed $q_m$ of a release at rest at
$q_0$ is the root of $F(q) = L(q, 0) - L(q_0, 0)$, with $F > 0$ between the turning
points. "matched" starts its second leg there.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._jaxpr.fusion import one_fusion
from .quantities import mechanics


# Safeguarded Newton converges in ~5 iterations from the bracket; the loop stops when
# every lane has converged.
_MAX_NEWTON = 60
_MAX_EXPAND = 40


class FarTurningPoint(eqx.Module):
    """`q1` where `found`; `band` its rounding band (zeros unless asked for: only the
    error estimate reads it); `in_range` False where L at the release point was not
    finite with the vectorized sines (an argument beyond their range)."""

    q1: Float[Array, " n"]
    found: Bool[Array, " n"]
    band: Float[Array, " n"]
    in_range: Bool[Array, " n"]


@eqx.filter_jit
def far_turning_point(L, consts, q0, q_m, with_band=True) -> FarTurningPoint:
    r"""The root of $F(q) = L(q, 0) - L(q_0, 0)$ beyond $q_m$: bracketed from the
    mirror image of $q_0$ outward, then safeguarded Newton; its tangent by the
    implicit function theorem."""
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    # ~20 values of L and its slope per lane. Beyond the vectorized sines' range
    # (|argument| > 8.2e5) they are NaN: `in_range` says where L at q0 was finite.
    # (Values at several points, and a value with its slope, each from one call:
    # on the tape path each call is an interpreter in the program.)
    mech = mechanics(L, consts)
    both = mech.rest_lanes_with_slope(dtype)
    # Each value of L is computed once and carried (for the pendulum each is a libm
    # call per lane, otherwise recomputed for F, its rounding and each loop's test).
    # The bracket starts at q_m and its mirror image q_m + (q_m - q0).
    (E0, La, Lb), dLb = both(jnp.stack([q0, q_m, q_m + (q_m - q0)]), 2)
    # F = L(q) - L(q0) is known only to the rounding of the two values of L: inside
    # that band every point is the turning point as far as float64 can tell.
    # The search carries no tangents: the root's comes from the implicit function
    # below, in which the tangent of x cancels (its loops' tangents would be traced
    # and compiled for nothing).
    sg = jax.lax.stop_gradient
    search = sg((E0, q0, q_m, La, Lb, dLb))
    noise = lambda Lq: 4 * eps * (jnp.abs(Lq) + jnp.abs(search[0]))
    a, b, Fa, Fb, Lb = _bracket(both, noise, *search)
    at_b = jnp.abs(Fb) <= noise(Lb)  # e.g. the mirror image, in a symmetric well
    found = ((Fb <= 0) | at_b) & (Fa > 0) & jnp.isfinite(a) & jnp.isfinite(b)
    secant = a + (b - a) * Fa / jnp.where(Fa != Fb, Fa - Fb, 1.0)
    x = jnp.where(found, jnp.where(at_b, b, secant), search[1])
    x = _newton(both, noise, search[0], a, b, x, found, at_b)
    # The tangent of the root by the implicit function theorem (zero primal).
    # (At the root F = 0: the slope's own tangent multiplies F and is dropped.)
    # With the band, L at x and at the band's points from one call.
    points = _band_points(x) if with_band else []
    Ls, slope = both(jnp.stack([x, *points]), 0)
    Lx, slope = Ls[0], jax.lax.stop_gradient(slope)
    f0 = Lx - E0
    corr = -f0 / slope
    corr = jnp.where(found & jnp.isfinite(corr), corr, 0.0)
    root = x + (corr - jax.lax.stop_gradient(corr))
    in_range = jnp.isfinite(E0)
    if not with_band:
        return FarTurningPoint(root, found, jnp.zeros_like(x), in_range)
    # (The band only sizes the error estimate: no tangent.)
    band = sg(_band(Ls[1:], E0, x, Lx, f0, slope))
    return FarTurningPoint(root, found, band, in_range)


def _bracket(both, noise, E0, q0, q_m, La, Lb, dLb):
    """`(a, b, F(a), F(b), L(b))` with F(a) > 0 >= F(b) (where found): from the mirror
    image of q0 (the root itself if the well is mirror-symmetric, up to rounding)
    outward by a Newton step times 1, 2, 4, … (for a convex F Newton undershoots),
    never less than a few ulps, and by |d| times the same factor where F does not
    fall outward (a shoulder). `La`, `Lb`, `dLb`: L at q_m and at the mirror image,
    and its slope there."""
    eps = jnp.finfo(q0.dtype).eps
    d = q_m - q0
    out = jnp.sign(d)  # away from the release point
    a, b = q_m, q_m + d
    Fa, Fb = La - E0, Lb - E0

    def expand(c):
        a, b, Fa, Fb, Lb, dLb, k = c
        more = Fb > noise(Lb)
        slope = -out * dLb
        newton = Fb / jnp.where(slope > 0, slope, 1.0)
        step = jnp.where(slope > 0, newton, jnp.abs(d)) * 2.0**k
        step = jnp.maximum(step, 4 * eps * jnp.maximum(jnp.abs(b), jnp.abs(d)))
        b2 = jnp.where(more, b + out * step, b)
        # (The slope at the new end with its value: one evaluation per step.)
        L2, dL2 = both(b2)
        new = dict(
            a=jnp.where(more, b, a),
            b=b2,
            Fa=jnp.where(more, Fb, Fa),
            Fb=jnp.where(more, L2 - E0, Fb),
            Lb=jnp.where(more, L2, Lb),
            dLb=jnp.where(more, dL2, dLb),
        )
        # (Each loop's new values from one fusion, as in the period loop.)
        new = one_fusion(new)
        return (*new.values(), k + 1)

    a, b, Fa, Fb, Lb, _, _ = jax.lax.while_loop(
        lambda c: jnp.any(c[3] > noise(c[4])) & (c[6] < _MAX_EXPAND),
        expand,
        (a, b, Fa, Fb, Lb, dLb, 0),
    )
    return a, b, Fa, Fb, Lb


def _newton(both, noise, E0, a, b, x, found, at_b):
    """Safeguarded Newton from `x` inside the bracket `[a, b]`, to the rounding of F."""
    eps = jnp.finfo(x.dtype).eps

    def newton(c):
        a, b, x, done, k = c
        Lx, dLx = both(x)
        fx = Lx - E0
        done = done | (jnp.abs(fx) <= noise(Lx))
        a, b = jnp.where(fx > 0, x, a), jnp.where(fx > 0, b, x)
        x_new = x - fx / dLx
        ok = jnp.isfinite(x_new) & ((x_new - a) * (x_new - b) < 0)
        x_new = jnp.where(ok, x_new, 0.5 * (a + b))
        done = done | (jnp.abs(x_new - x) <= 2 * eps * jnp.abs(x))
        new = dict(a=a, b=b, x=jnp.where(done, x, x_new), done=done)
        new = one_fusion(new)
        return (*new.values(), k + 1)

    _, _, x, _, _ = jax.lax.while_loop(
        lambda c: jnp.any(found & ~c[3]) & (c[4] < _MAX_NEWTON),
        newton,
        (a, b, x, ~found | at_b, 0),
    )
    return x


_BAND_STEPS = (-4, -3, -2, -1, 1, 2, 3, 4)


def _band_spacing(x):
    eps = jnp.finfo(x.dtype).eps
    return 64 * eps * jnp.maximum(jnp.abs(x), eps)


def _band_points(x):
    """Where `_band` reads L: 64 ulps apart around x."""
    h = _band_spacing(x)
    return [x + j * h for j in _BAND_STEPS]


def _band(Ls, E0, x, Lx, f0, slope):
    """How far the root is undetermined: the rounding scatter of F near the root,
    measured (the user's L may round by many ulps, or by half of one), over its
    slope. Nine values of F spaced 64 ulps apart (the middle one is f0; `Ls`: L at
    the others, `_band_points`), against the tangent line."""
    eps = jnp.finfo(x.dtype).eps
    h = _band_spacing(x)
    scatter = jnp.zeros_like(x)
    for j, Lj in zip(_BAND_STEPS, Ls):
        scatter = jnp.maximum(scatter, jnp.abs(Lj - E0 - f0 - slope * j * h))
    half_ulp = 0.5 * eps * jnp.maximum(jnp.abs(Lx), jnp.abs(E0))
    return (scatter + half_ulp) / jnp.abs(slope)
