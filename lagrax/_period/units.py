r"""Each lane in its own units.

A lane released at rest at $q_0$ is integrated in $x = (q - q_0)/Q$ and $s = t/\tau$,
with $Q = |q_0|$ (1 at 0) and $\tau = \sqrt{Q/|\ddot q(q_0)|}$, so that `rtol` and
`atol` mean the same thing at an amplitude of $10^{-3}$ as at $3$; its acceleration
at release is $\pm 1$.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._stepper.base import fused
from .quantities import mechanics


class Release(eqx.Module):
    """What one lane knows at its release point: whether it can start (finite, a
    regular mass, a non-zero acceleration), and its own units: lengths `Qs`, times
    `tau`, `sigma` the sign of q̈0."""

    q0: Float[Array, ""]
    finite: Bool[Array, ""]
    start_ok: Bool[Array, ""]
    moving: Bool[Array, ""]
    valid: Bool[Array, ""]
    M0: Float[Array, ""]
    a0s: Float[Array, ""]
    Qs: Float[Array, ""]
    tau: Float[Array, ""]
    sigma: Float[Array, ""]


def release_point(q0):
    """Where a lane's release quantities are evaluated: `q0`, or 1 where it is not
    finite (its status says so)."""
    return jnp.where(jnp.isfinite(q0), q0, 1.0)


def _release(mech, q0) -> Release:
    """`Release` of one lane (a scalar `q0`; `mech`: `mechanics(L, consts)`)."""
    zero = jnp.zeros((), q0.dtype)
    at = release_point(q0)
    # (Unfused here: `lane_scales` fuses this function's outputs as a whole.)
    a0, (M0, ok0) = mech.accelerations(at[None], zero[None], zero, fuse=False)
    return _release_from(q0, a0[0], M0[0, 0], ok0)


def _release_from(q0, a0, M0, ok0) -> Release:
    """`Release` of one lane from the acceleration, mass and its verdict at its
    `release_point`."""
    finite = jnp.isfinite(q0)
    q0 = release_point(q0)
    start_ok = ok0 & jnp.isfinite(a0)
    moving = a0 != 0
    valid = finite & start_ok & moving
    Qs = jnp.where(q0 != 0, jnp.abs(q0), 1.0)
    a0s = jnp.where(valid, a0, -1.0)
    tau = jnp.sqrt(Qs / jnp.abs(a0s))
    return Release(q0, finite, start_ok, moving, valid, M0, a0s, Qs, tau, jnp.sign(a0s))


def lane_scales(L, q0, consts) -> Release:
    """`Release` of each lane (vmapped), computed once per pass for the whole queue:
    the table of constants and `finish` read it."""
    release = lambda q0: _release(mechanics(L, consts), q0)
    # Its outputs through one fusion: each is read by several fusions, and XLA
    # would copy the acceleration at q0 (a libm sine per lane for the pendulum) into
    # each of them.
    return fused(jax.vmap(release)(q0))[0]


def lane_scales_from(q0, a0, M0, ok0) -> Release:
    """`lane_scales` from each lane's acceleration, mass and verdict at its
    `release_point` (arrays over lanes)."""
    return fused(jax.vmap(_release_from)(q0, a0, M0, ok0))[0]


def scaled_acceleration(L, consts, fuse=None):
    """The acceleration in a lane's own units: `accel(q0, Qs, tau, s, x, v)`."""
    return mechanics(L, consts).scaled_acceleration(fuse)
