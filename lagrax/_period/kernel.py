"""One pass of the period kernel over the lanes of one device: the loop, then the
post-pass that turns its raw outcomes into statuses and event times."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .estimate import BoundTerms
from .finish import _central_points, finish
from .loop import Pass, run_queue
from .quantities import CompactLagrangian, MASS, mechanics, OK, QDDOT
from .units import lane_scales_from, release_point


_NO_LIMIT = 1e30


class Lanes(eqx.Module):
    """What a pass solves, per lane: release point, a `POSITION` event's target, the
    event's kind, tolerances, and whether the lane is live (the live lanes are a
    prefix; the others are never loaded)."""

    q0: Float[Array, " n"]
    target: Float[Array, " n"]
    kind: Int[Array, " n"]
    rtol: Float[Array, " n"]
    atol: Float[Array, " n"]
    live: Bool[Array, " n"]


class PassResult(eqx.Module):
    """Per lane: status, event time and end state, steps, the error bound's sums (from
    zeros without `Pass.screen`); and the lane-steps the loop executed."""

    status: Int[Array, " n"]
    t_event: Float[Array, " n"]
    q_end: Float[Array, " n"]
    qdot_end: Float[Array, " n"]
    steps: Int[Array, " n"]
    terms: BoundTerms
    executed: Int[Array, ""]


@eqx.filter_jit
def run_pass(L, cfg: Pass, lanes: Lanes, consts, t_max, energy_tol) -> PassResult:
    """One pass of the kernel over every lane of one device, compiled once per static
    configuration (`L`, `cfg`, shapes)."""
    q0 = lanes.q0
    t_lim = jnp.asarray(_NO_LIMIT if t_max is None else t_max, q0.dtype)
    n_live = jnp.sum(lanes.live.astype(jnp.int32))
    per_lane = (q0, lanes.target, lanes.kind, lanes.rtol, lanes.atol)
    legs = None
    if isinstance(L, CompactLagrangian):
        # The point tape at the release points and at the legs' ends from one
        # evaluation site (each an inlined copy of the tape's program).
        def run(at):
            at = at[:, 0]
            rel = lane_scales_from(q0, at[QDDOT], at[MASS], at[OK] != 0)
            out, executed, _ = run_queue(
                L, cfg, *per_lane, t_lim, consts, n_live, rel=rel
            )
            return rel, (out.s, out.x, out.v), (out, executed)

        rel, _, (out, executed), legs = mechanics(L, consts).release_and_leg_ends(
            release_point(q0), run, _central_points
        )
    else:
        out, executed, rel = run_queue(L, cfg, *per_lane, t_lim, consts, n_live)
    ends, terms = finish(
        L, consts, q0, lanes.target, lanes.kind, lanes.rtol, out, rel, energy_tol, legs
    )
    e = ends
    return PassResult(
        e.status, e.t_event, e.q_end, e.qdot_end, out.steps, terms, executed
    )
