"""How a lane's leg ends: the loop's raw outcomes, refined into statuses by `finish`."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


LOCATED = 0
NO_EVENT = 1  # escaped, or reached t_max
MAX_STEPS = 2
LOCATE_FAILED = 4
STEP_FAILED = 6
INVALID = 7  # not started: the post-pass says why (non-finite, singular, equilibrium)

_ESCAPE = 1e6


class Outcome(eqx.Module):
    """Per lane: its raw outcome so far, whether its amplitude ends in this iteration
    (`ends`), and the next step length `h` kept within the time limit."""

    raw: Int[Array, " lanes"]
    ends: Bool[Array, " lanes"]
    h: Float[Array, " lanes"]


def lane_outcome(lane, c, found, new, h_next, active, cfg, dtmin) -> Outcome:
    """How each lane's iteration ends (`new`: its `NewState`; `cfg`: the `Pass`)."""
    moved, s_new, x_new, h_new, steps = new.moved, new.s, new.x, new.h, new.steps
    advance, converged = found.advance, found.converged
    escape = _ESCAPE * jnp.maximum(c.Qs, 1.0) / c.Qs
    escaped = advance & (jnp.abs(x_new) > escape)
    ran_out = advance & (s_new >= c.limit)
    h_new = jnp.minimum(h_new, jnp.maximum(c.limit - s_new, dtmin))
    collapsed = ~found.locating & ~moved & (h_next < dtmin)
    out_of_steps = steps >= cfg.max_steps
    # Nested `where`s, not `jnp.select` (an argmax over the stacked conditions, a
    # reduction XLA recomputes the whole step into).
    raw = lane.raw
    for cond_, code in reversed(
        [
            (converged, LOCATED),
            (found.gave_up, LOCATE_FAILED),
            (escaped | ran_out, NO_EVENT),
            (collapsed, STEP_FAILED),
            (out_of_steps, MAX_STEPS),
        ]
    ):
        raw = jnp.where(cond_, code, raw)
    ends = active & (
        converged | found.gave_up | escaped | ran_out | collapsed | out_of_steps
    )
    return Outcome(raw, ends, h_new)
