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
    return FarTurningPoint(*_far(L, with_band, consts, q0, q_m))


# Each lane's stages in `_search`'s loop, one value of L (with its slope) per
# iteration: L at q0, at q_m and at the mirror image, the bracket, Newton, then L at
# the root and at the band's points (`_band_points`), then nothing.
_AT_Q0, _AT_QM, _AT_MIRROR, _BRACKET, _NEWTON, _AT_ROOT = range(6)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _far(L, with_band, consts, q0, q_m):
    """`(root, found, band, in_range)`; the root's tangent by `_far_jvp`."""
    x, found, band, in_range, E0, Lx, slope = _search(L, with_band, consts, q0, q_m)
    corr = _correction(found, Lx - E0, slope)
    return x + (corr - corr), found, band, in_range


@_far.defjvp
def _far_jvp(L, with_band, primals, tangents):
    """The tangent of the root by the implicit function theorem: L at q0 and at the
    root, differentiated with respect to q0 and L's parameters (the root's own
    tangent cancels: at the root F = 0, and the slope's tangent multiplies F)."""
    consts, q0, q_m = primals
    x, found, band, in_range, E0, Lx, slope = _search(L, with_band, *primals)
    corr = _correction(found, Lx - E0, slope)
    root = x + (corr - corr)
    both = lambda consts, q0: _rest(L, consts, q0.dtype)(jnp.stack([q0, x]))[0]
    _, (dE0, dLx) = jax.jvp(both, (consts, q0), tangents[:2])
    dcorr = jnp.where(found & jnp.isfinite(corr), -(dLx - dE0) / slope, 0.0)
    zero = lambda u: np.zeros(u.shape, jax.dtypes.float0)
    return (root, found, band, in_range), (
        dcorr,
        zero(found),
        jnp.zeros_like(band),
        zero(in_range),
    )


def _correction(found, f0, slope):
    """The Newton correction at the root, zero where not found or not finite."""
    corr = -f0 / slope
    return jnp.where(found & jnp.isfinite(corr), corr, 0.0)


def _rest(L, consts, dtype):
    return mechanics(L, consts).rest_lanes_with_slope(dtype)


def _search(L, with_band, consts, q0, q_m):
    """The root `x` (no tangent), whether `found`, its rounding `band`, `in_range`,
    and L at q0 and at x with its slope there: every value of L from one loop whose
    body evaluates L (and its slope) once per lane, each lane at its own stage (the
    program holds one copy of L's evaluation, not one per stage)."""
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    sg = jax.lax.stop_gradient
    both = _rest(L, sg(consts), dtype)
    q0, q_m = sg(q0), sg(q_m)
    d = q_m - q0
    out = jnp.sign(d)  # away from the release point
    mirror = q_m + d
    # (Beyond the vectorized sines' range, |argument| > 8.2e5, L is NaN: `in_range`
    # says where L at q0 was finite.)
    noise = lambda E0, Lq: 4 * eps * (jnp.abs(Lq) + jnp.abs(E0))
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
        # The bracket's end (F no longer above its rounding, or 40 steps): from the
        # secant inside it, Newton.
        more = (c["Fb"] > noise(E0, c["Lb"])) & (k < _MAX_EXPAND)
        ends = (stage == _BRACKET) & ~more
        a, b, Fa, Fb = c["a"], c["b"], c["Fa"], c["Fb"]
        at_b = jnp.abs(Fb) <= noise(E0, c["Lb"])  # e.g. the mirror image
        found = ((Fb <= 0) | at_b) & (Fa > 0) & jnp.isfinite(a) & jnp.isfinite(b)
        secant = a + (b - a) * Fa / jnp.where(Fa != Fb, Fa - Fb, 1.0)
        x0 = jnp.where(found, jnp.where(at_b, b, secant), q0)
        c["x"] = jnp.where(ends, x0, c["x"])
        c["found"] = jnp.where(ends, found, c["found"])
        c["done"] = jnp.where(ends, ~found | at_b, c["done"])
        stage = jnp.where(ends, _NEWTON, stage)
        k = jnp.where(ends, 0, k)
        # Newton's end: converged, or 60 steps.
        stage = jnp.where(
            (stage == _NEWTON) & (c["done"] | (k >= _MAX_NEWTON)), _AT_ROOT, stage
        )
        # This iteration's point.
        slope = -out * c["dLb"]
        newton = Fb / jnp.where(slope > 0, slope, 1.0)
        step = jnp.where(slope > 0, newton, jnp.abs(d)) * 2.0**k
        step = jnp.maximum(step, 4 * eps * jnp.maximum(jnp.abs(b), jnp.abs(d)))
        x = c["x"]
        h = _band_spacing(x)
        j = jnp.clip(stage - (_AT_ROOT + 1), 0, len(steps) - 1)
        point = jnp.select(
            [stage == _AT_Q0, stage == _AT_QM, stage == _AT_MIRROR, stage == _BRACKET],
            [q0, q_m, mirror, b + out * step],
            jnp.where(stage > _AT_ROOT, x + steps[j] * h, x),
        )
        Lq, dLq = both(point)
        # The stages' updates.
        E0 = c["E0"] = jnp.where(stage == _AT_Q0, Lq, E0)
        c["Fa"] = jnp.where(stage == _AT_QM, Lq - E0, Fa)
        mir = stage == _AT_MIRROR
        c["Fb"] = jnp.where(mir, Lq - E0, Fb)
        c["Lb"] = jnp.where(mir, Lq, c["Lb"])
        c["dLb"] = jnp.where(mir, dLq, c["dLb"])
        br = stage == _BRACKET
        c["a"] = jnp.where(br, b, a)
        c["b"] = jnp.where(br, point, b)
        c["Fa"] = jnp.where(br, Fb, c["Fa"])
        c["Fb"] = jnp.where(br, Lq - E0, c["Fb"])
        c["Lb"] = jnp.where(br, Lq, c["Lb"])
        c["dLb"] = jnp.where(br, dLq, c["dLb"])
        nw = stage == _NEWTON
        fx = Lq - E0
        done = c["done"] | (jnp.abs(fx) <= noise(E0, Lq))
        na, nb = jnp.where(fx > 0, x, c["a"]), jnp.where(fx > 0, c["b"], x)
        x_new = x - fx / dLq
        ok = jnp.isfinite(x_new) & ((x_new - na) * (x_new - nb) < 0)
        x_new = jnp.where(ok, x_new, 0.5 * (na + nb))
        done = done | (jnp.abs(x_new - x) <= 2 * eps * jnp.abs(x))
        c["a"], c["b"] = jnp.where(nw, na, c["a"]), jnp.where(nw, nb, c["b"])
        c["x"] = jnp.where(nw & ~done, x_new, x)
        c["done"] = jnp.where(nw, done, c["done"])
        root = stage == _AT_ROOT
        c["Lx"] = jnp.where(root, Lq, c["Lx"])
        c["slope"] = jnp.where(root, dLq, c["slope"])
        row = jnp.arange(len(steps))[:, None] == (stage - (_AT_ROOT + 1))[None]
        c["band"] = jnp.where(row, Lq[None], c["band"])
        c["k"] = jnp.where(br | nw, k + 1, k)
        c["stage"] = jnp.where(
            (stage < _BRACKET) | (stage >= _AT_ROOT),
            jnp.minimum(stage + 1, last + 1),
            stage,
        )
        # (Each iteration's new values from one fusion, as in the period loop; the
        # band's rows, of another shape, beside it.)
        band = c.pop("band")
        return dict(one_fusion(c), band=band)

    c = jax.lax.while_loop(lambda c: jnp.any(c["stage"] <= last), body, init)
    x, found, E0, Lx, slope = c["x"], c["found"], c["E0"], c["Lx"], c["slope"]
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
