r"""The far turning point of a swing, from the energy at rest.

For $L$ even in $\dot q$ and without explicit time, the energy at rest is $-L(q, 0)$:
the turning point beyond the point of maximum speed $q_m$ of a release at rest at
$q_0$ is the root of $F(q) = L(q, 0) - L(q_0, 0)$, with $F > 0$ between the turning
points. "matched" starts its second leg there.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._jaxpr.fusion import one_fusion
from .quantities import CompactLagrangian, mechanics


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
    implicit function theorem.

    The compact tier (`CompactLagrangian`) runs every evaluation of L in one loop
    (`_one_site`): each place that evaluates L is a copy of the tape's interpreter
    in the program, loaded with it. The specialized program evaluates L where each
    value is needed (fewer iterations, L inlined at each place)."""
    if isinstance(L, CompactLagrangian):
        return FarTurningPoint(*_one_site(L, with_band, consts, q0, q_m))
    dtype = q0.dtype
    # ~20 values of L and its slope per lane. Beyond the vectorized sines' range
    # (|argument| > 8.2e5) they are NaN: `in_range` says where L at q0 was finite.
    # (Values at several points, and a value with its slope, each from one call.)
    both = mechanics(L, consts).rest_lanes_with_slope(dtype)
    # Each value of L is computed once and carried (for the pendulum each is a libm
    # call per lane, otherwise recomputed for F, its rounding and each loop's test).
    # The bracket starts at q_m and its mirror image q_m + (q_m - q0).
    (E0, La, Lb), dLb = both(jnp.stack([q0, q_m, q_m + (q_m - q0)]), 2)
    # The search carries no tangents: the root's comes from the implicit function
    # below, in which the tangent of x cancels (its loops' tangents would be traced
    # and compiled for nothing).
    sg = jax.lax.stop_gradient
    search = sg((E0, q0, q_m, La, Lb, dLb))
    E0s = search[0]
    a, b, Fa, Fb, Lb = _bracket(both, *search)
    found, at_b, x = _newton_start(E0s, search[1], a, b, Fa, Fb, Lb)
    x = _newton(both, E0s, a, b, x, found, at_b)
    # The tangent of the root by the implicit function theorem (zero primal).
    # (At the root F = 0: the slope's own tangent multiplies F and is dropped.)
    # With the band, L at x and at the band's points from one call.
    points = _band_points(x) if with_band else []
    Ls, slope = both(jnp.stack([x, *points]), 0)
    Lx, slope = Ls[0], jax.lax.stop_gradient(slope)
    f0 = Lx - E0
    corr = _correction(found, f0, slope)
    root = x + (corr - jax.lax.stop_gradient(corr))
    in_range = jnp.isfinite(E0)
    if not with_band:
        return FarTurningPoint(root, found, jnp.zeros_like(x), in_range)
    # (The band only sizes the error estimate: no tangent.)
    band = sg(_band(Ls[1:], E0, x, Lx, f0, slope))
    return FarTurningPoint(root, found, band, in_range)


def _noise(E0, Lq):
    """F = L(q) - L(q0) is known only to the rounding of the two values of L: inside
    this band every point is the turning point as far as float64 can tell."""
    eps = jnp.finfo(Lq.dtype).eps
    return 4 * eps * (jnp.abs(Lq) + jnp.abs(E0))


def _expand(E0, q0, q_m, b, Fb, Lb, dLb, k):
    """`(more, b2)`: whether the bracket `[a, b]` grows (F at b not yet below its
    rounding), and its next end: outward by a Newton step times 2^k (for a convex F
    Newton undershoots), never less than a few ulps, and by |d| times the same
    factor where F does not fall outward (a shoulder)."""
    eps = jnp.finfo(b.dtype).eps
    d = q_m - q0
    out = jnp.sign(d)  # away from the release point
    more = Fb > _noise(E0, Lb)
    slope = -out * dLb
    newton = Fb / jnp.where(slope > 0, slope, 1.0)
    step = jnp.where(slope > 0, newton, jnp.abs(d)) * 2.0**k
    step = jnp.maximum(step, 4 * eps * jnp.maximum(jnp.abs(b), jnp.abs(d)))
    return more, b + out * step


def _newton_start(E0, q0, a, b, Fa, Fb, Lb):
    """`(found, at_b, x)`: whether the bracket holds the root, whether its outer end
    is the root to rounding (e.g. the mirror image, in a symmetric well), and
    Newton's start (the secant inside the bracket)."""
    at_b = jnp.abs(Fb) <= _noise(E0, Lb)
    found = ((Fb <= 0) | at_b) & (Fa > 0) & jnp.isfinite(a) & jnp.isfinite(b)
    secant = a + (b - a) * Fa / jnp.where(Fa != Fb, Fa - Fb, 1.0)
    return found, at_b, jnp.where(found, jnp.where(at_b, b, secant), q0)


def _newton_step(E0, a, b, x, done, Lx, dLx):
    """One safeguarded Newton step from `x` in the bracket `[a, b]`, L and its slope
    at x given: `(a, b, x, done)`."""
    eps = jnp.finfo(x.dtype).eps
    fx = Lx - E0
    done = done | (jnp.abs(fx) <= _noise(E0, Lx))
    a, b = jnp.where(fx > 0, x, a), jnp.where(fx > 0, b, x)
    x_new = x - fx / dLx
    ok = jnp.isfinite(x_new) & ((x_new - a) * (x_new - b) < 0)
    x_new = jnp.where(ok, x_new, 0.5 * (a + b))
    done = done | (jnp.abs(x_new - x) <= 2 * eps * jnp.abs(x))
    return a, b, jnp.where(done, x, x_new), done


def _correction(found, f0, slope):
    """The Newton correction at the root, zero where not found or not finite."""
    corr = -f0 / slope
    return jnp.where(found & jnp.isfinite(corr), corr, 0.0)


def _bracket(both, E0, q0, q_m, La, Lb, dLb):
    """`(a, b, F(a), F(b), L(b))` with F(a) > 0 >= F(b) (where found): from the mirror
    image of q0 (the root itself if the well is mirror-symmetric, up to rounding)
    outward (`_expand`). `La`, `Lb`, `dLb`: L at q_m and at the mirror image, and
    its slope there."""
    a, b = q_m, q_m + (q_m - q0)
    Fa, Fb = La - E0, Lb - E0

    def expand(c):
        a, b, Fa, Fb, Lb, dLb, k = c
        more, b2 = _expand(E0, q0, q_m, b, Fb, Lb, dLb, k)
        b2 = jnp.where(more, b2, b)
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
        lambda c: jnp.any(c[3] > _noise(E0, c[4])) & (c[6] < _MAX_EXPAND),
        expand,
        (a, b, Fa, Fb, Lb, dLb, 0),
    )
    return a, b, Fa, Fb, Lb


def _newton(both, E0, a, b, x, found, at_b):
    """Safeguarded Newton from `x` inside the bracket `[a, b]`, to the rounding of F."""

    def newton(c):
        a, b, x, done, k = c
        a, b, x, done = _newton_step(E0, a, b, x, done, *both(x))
        new = one_fusion(dict(a=a, b=b, x=x, done=done))
        return (*new.values(), k + 1)

    _, _, x, _, _ = jax.lax.while_loop(
        lambda c: jnp.any(found & ~c[3]) & (c[4] < _MAX_NEWTON),
        newton,
        (a, b, x, ~found | at_b, 0),
    )
    return x


# Each lane's stages in `_search`'s loop, one value of L (with its slope) per
# iteration: L at q0, at q_m and at the mirror image, the bracket, Newton, then L at
# the root and at the band's points (`_band_points`), then nothing.
_AT_Q0, _AT_QM, _AT_MIRROR, _BRACKET, _NEWTON, _AT_ROOT = range(6)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _one_site(L, with_band, consts, q0, q_m):
    """`(root, found, band, in_range)` from `_search`; the root's tangent by
    `_one_site_jvp`."""
    x, found, band, in_range, E0, Lx, slope = _search(L, with_band, consts, q0, q_m)
    corr = _correction(found, Lx - E0, slope)
    return x + (corr - corr), found, band, in_range


@_one_site.defjvp
def _one_site_jvp(L, with_band, primals, tangents):
    """The tangent of the root by the implicit function theorem: L at q0 and at the
    root, differentiated with respect to q0 and L's parameters (the root's own
    tangent cancels: at the root F = 0, and the slope's tangent multiplies F)."""
    consts, q0, q_m = primals
    x, found, band, in_range, E0, Lx, slope = _search(L, with_band, *primals)
    corr = _correction(found, Lx - E0, slope)
    root = x + (corr - corr)
    rest = lambda consts, q0: _rest(L, consts, q0.dtype)(jnp.stack([q0, x]))[0]
    _, (dE0, dLx) = jax.jvp(rest, (consts, q0), tangents[:2])
    dcorr = jnp.where(found & jnp.isfinite(corr), -(dLx - dE0) / slope, 0.0)
    zero = lambda u: np.zeros(u.shape, jax.dtypes.float0)
    tangent = (dcorr, zero(found), jnp.zeros_like(band), zero(in_range))
    return (root, found, band, in_range), tangent


def _rest(L, consts, dtype):
    return mechanics(L, consts).rest_lanes_with_slope(dtype)


def _search(L, with_band, consts, q0, q_m):
    """The root `x` (no tangent), whether `found`, its rounding `band`, `in_range`,
    and L at q0 and at x with its slope there, as `far_turning_point` finds them:
    every value of L from one loop whose body evaluates L (and its slope) once per
    lane, each lane at its own stage."""
    dtype = q0.dtype
    sg = jax.lax.stop_gradient
    both = _rest(L, sg(consts), dtype)
    q0, q_m = sg(q0), sg(q_m)
    mirror = q_m + (q_m - q0)
    steps = jnp.asarray(_BAND_STEPS if with_band else (0,), dtype)
    last = _AT_ROOT + (len(_BAND_STEPS) if with_band else 0)
    z = jnp.zeros_like(q0)
    i32 = lambda v: jnp.full(q0.shape, v, jnp.int32)
    init = dict(
        stage=i32(_AT_Q0), k=i32(0), E0=z, a=q_m, b=mirror, Fa=z, Fb=z, Lb=z, dLb=z,
        x=q0, done=jnp.zeros(q0.shape, bool), found=jnp.zeros(q0.shape, bool),
        Lx=z, slope=z, band=jnp.zeros((len(steps),) + q0.shape, dtype),
    )  # fmt: skip

    def body(c):
        c = dict(c)
        stage, k, E0 = c["stage"], c["k"], c["E0"]
        a, b, Fa, Fb, Lb = c["a"], c["b"], c["Fa"], c["Fb"], c["Lb"]
        more, b2 = _expand(E0, q0, q_m, b, Fb, Lb, c["dLb"], k)
        # The bracket's end (F no longer above its rounding, or 40 steps): Newton.
        ends = (stage == _BRACKET) & ~(more & (k < _MAX_EXPAND))
        found, at_b, x0 = _newton_start(E0, q0, a, b, Fa, Fb, Lb)
        c["x"] = jnp.where(ends, x0, c["x"])
        c["found"] = jnp.where(ends, found, c["found"])
        c["done"] = jnp.where(ends, ~found | at_b, c["done"])
        stage = jnp.where(ends, _NEWTON, stage)
        k = jnp.where(ends, 0, k)
        # Newton's end: converged, or 60 steps.
        newton_ends = c["done"] | (k >= _MAX_NEWTON)
        stage = jnp.where((stage == _NEWTON) & newton_ends, _AT_ROOT, stage)
        # This iteration's point, L and its slope there.
        x = c["x"]
        j = jnp.clip(stage - (_AT_ROOT + 1), 0, len(steps) - 1)
        point = jnp.select(
            [stage == _AT_Q0, stage == _AT_QM, stage == _AT_MIRROR, stage == _BRACKET],
            [q0, q_m, mirror, b2],
            jnp.where(stage > _AT_ROOT, x + steps[j] * _band_spacing(x), x),
        )
        Lq, dLq = both(point)
        # The stages' updates.
        E0 = c["E0"] = jnp.where(stage == _AT_Q0, Lq, E0)
        c["Fa"] = jnp.where(stage == _AT_QM, Lq - E0, Fa)
        br = stage == _BRACKET
        new_b = br | (stage == _AT_MIRROR)
        c["a"] = jnp.where(br, b, a)
        c["b"] = jnp.where(br, point, b)
        c["Fa"] = jnp.where(br, Fb, c["Fa"])
        c["Fb"] = jnp.where(new_b, Lq - E0, Fb)
        c["Lb"] = jnp.where(new_b, Lq, Lb)
        c["dLb"] = jnp.where(new_b, dLq, c["dLb"])
        nw = stage == _NEWTON
        step = _newton_step(E0, c["a"], c["b"], x, c["done"], Lq, dLq)
        for key, value in zip(("a", "b", "x", "done"), step):
            c[key] = jnp.where(nw, value, c[key])
        root = stage == _AT_ROOT
        c["Lx"] = jnp.where(root, Lq, c["Lx"])
        c["slope"] = jnp.where(root, dLq, c["slope"])
        row = jnp.arange(len(steps))[:, None] == (stage - (_AT_ROOT + 1))[None]
        c["band"] = jnp.where(row, Lq[None], c["band"])
        c["k"] = jnp.where(br | nw, k + 1, k)
        moves_on = (stage < _BRACKET) | (stage >= _AT_ROOT)
        c["stage"] = jnp.where(moves_on, jnp.minimum(stage + 1, last + 1), stage)
        # (Each iteration's new values from one fusion, as in the period loop; the
        # band's rows, of another shape, beside it.)
        band = c.pop("band")
        return dict(one_fusion(c), band=band)

    c = jax.lax.while_loop(lambda c: jnp.any(c["stage"] <= last), body, init)
    x, found, E0, Lx, slope = c["x"], c["found"], c["E0"], c["Lx"], c["slope"]
    # (Beyond the vectorized sines' range L is NaN: `in_range` says where L at q0
    # was finite.)
    in_range = jnp.isfinite(E0)
    if not with_band:
        return x, found, jnp.zeros_like(x), in_range, E0, Lx, slope
    band = _band(c["band"], E0, x, Lx, Lx - E0, slope)
    return x, found, band, in_range, E0, Lx, slope


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
