r"""What "quarter" assumes, checked: $T = 4\,t(q_0 \to q_m)$ holds for a well
mirror-symmetric about the point of maximum speed $q_m$."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .estimate import PROMISE
from .quantities import mechanics


@eqx.filter_jit
def is_turning_point(L, consts, q0, q, tol):
    """Whether q is, within `tol` in q plus rounding, on the energy level of a release
    at rest at q0: |L(q, 0) - L(q0, 0)| <= rounding + tol |∂L/∂q(q, 0)|."""
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    # Beyond the vectorized sines' range L is NaN here and the test fails; such a
    # lane has already failed in the loop ("solver failed": its steps use the same
    # sines), and only a success is ever turned into "not symmetric".
    mech = mechanics(L, consts)
    Lr = mech.rest(dtype)
    both = mech.rest_value_and_slope(dtype)

    def one(q0, q, tol):
        Lq, dLq = both(q)
        Lq0 = Lr(q0)
        noise = 4 * eps * (jnp.abs(Lq) + jnp.abs(Lq0))
        return jnp.abs(Lq - Lq0) <= noise + tol * jnp.abs(dLq)

    return jax.vmap(one)(q0, q, tol)


# Where L's mirror symmetry is tested across the swing (fractions of it, away from
# simple ratios; the turning point itself is tested on its own).
_MIRROR_POINTS = (0.2763932, 0.5527864, 0.8291796)


@eqx.filter_jit
def mirror_symmetric(L, consts, q0, q_m, qd_m, rtols):
    """Whether L is mirror-symmetric about `q_m` across the swing, as
    T = 4 t(q0 -> q_m) assumes: L(q_m + y, w) = L(q_m - y, -w) at three points
    y inside the swing, at rest (the potential) and at the speed |q̇_m| of the
    meeting point (the mass too), to `PROMISE` rtol of the well's depth
    |L(q_m, 0) - L(q0, 0)| plus rounding (the centre q_m is only as exact as the
    integration). Sampled, not proven: a well whose far side differs between these
    points only is not detected; but one whose far turning point merely happens to
    be the mirror image of q0 (an asymmetric well at one amplitude: V = x²/2 +
    x³(x² - 1)/10 released at 1) is, where the turning-point test alone reports
    a success 4% off. A velocity term that is a total derivative, f(q) q̇, breaks
    the literal symmetry and is refused too (`"matched"` handles it)."""
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    z = jnp.zeros((), dtype)
    mech = mechanics(L, consts)
    Lr = lambda q, w: mech.value(jnp.reshape(q, (1,)), jnp.reshape(w, (1,)), z)

    def one(q0, q_m, qd_m, rtol):
        # (At the speed of the meeting point: the potential and the mass at once; a
        # coincidence cancelling the two at every point is not sought.)
        y = np.array(_MIRROR_POINTS, dtype) * (q0 - q_m)
        w = jnp.full(y.shape, jnp.abs(qd_m))
        # The eight values of L as one array: written out as eight calls, XLA copies
        # L's program into each of their readers inside the sweep.
        Ls = jax.vmap(Lr)(
            jnp.concatenate([jnp.stack([q_m, q0]), q_m + y, q_m - y]),
            jnp.concatenate([jnp.stack([z, z]), w, -w]),
        )
        depth = jnp.abs(Ls[0] - Ls[1])
        a, b = Ls[2:5], Ls[5:]
        noise = 8 * eps * (jnp.abs(a) + jnp.abs(b))
        return jnp.isfinite(depth) & jnp.all(
            jnp.abs(a - b) <= noise + PROMISE * rtol * depth
        )

    return jax.vmap(one)(q0, q_m, qd_m, rtols)
