"""The period loop's lane state, and each lane's constants."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._stepper.base import fused
from .events import Search


class LaneConstants(eqx.Module):
    """A lane's constants, the rows of its parameter block `Lane.p`: the release point
    and units, a `POSITION` event's target `xt` and the time `limit` in lane units, the
    event's kind and the tolerances."""

    q0: Float[Array, " lanes"]
    Qs: Float[Array, " lanes"]
    tau: Float[Array, " lanes"]
    xt: Float[Array, " lanes"]
    limit: Float[Array, " lanes"]
    kind: Int[Array, " lanes"]
    rtol: Float[Array, " lanes"]
    atol: Float[Array, " lanes"]

    @staticmethod
    def unpack(p, kind_dtype) -> "LaneConstants":
        q0, Qs, tau, xt, limit, kind, rtol, atol = (p[i] for i in range(len(PARAMS)))
        return LaneConstants(
            q0, Qs, tau, xt, limit, kind.astype(kind_dtype), rtol, atol
        )


PARAMS = tuple(f.name for f in dataclasses.fields(LaneConstants))


class Lane(eqx.Module):
    """The state of every lane of the period loop.

    A lane carries its constants as ONE array `p` (a row per constant, lanes last),
    not eight: one input of the Taylor step's fusion instead of eight; between
    iterations the loop carries the state the step reads as one array too
    (`loop._pack_state`). LLVM's loop vectorizer needs a runtime alias check per
    (output, input) pair and per pair of outputs of a fusion whose buffers it cannot
    prove apart, with a limit of 128 (`-vectorize-memory-check-threshold`); above it
    the step's loop stays scalar, several times slower. With the error bound's sums
    the step writes 9 buffers: each input read inside its loop costs 9 checks, and
    besides the lanes' own buffers XLA adds what it computes from L's constants
    outside the step. Count the checks after changing the loop: the `found.conflict`
    values in the step kernel's optimized LLVM IR (`--xla_dump_to`, with the
    threshold raised by `--xla_backend_extra_options` so that they are emitted).
    Check there too that the loop is vectorized at all (`x double>` values) and
    that the file defines no function besides the kernel (`define internal`): XLA
    may emit a value with many readers as a function called from the loop, and
    LLVM then leaves the loop scalar whatever the checks. Small changes to what
    the step reads (the kind read as a float, the lane's units carried as rows of
    `p`) do that.
    """

    p: Float[Array, "params lanes"]
    idx: Int[Array, " lanes"]  # its amplitude's queue position (n: idle)
    done: Bool[Array, " lanes"]
    raw: Int[Array, " lanes"]  # its outcome so far (`outcome.py`)
    sigma: Float[Array, " lanes"]  # the sign of its event function during the leg
    s: Float[Array, " lanes"]  # time, position, velocity, acceleration, lane units
    x: Float[Array, " lanes"]
    v: Float[Array, " lanes"]
    a: Float[Array, " lanes"]
    h: Float[Array, " lanes"]  # the next step length (or trial)
    steps: Int[Array, " lanes"]
    search: Search
    sums: Float[Array, "lanes sums"] | None  # the error bound's sums (`estimate.py`)


class NewState(eqx.Module):
    """A lane's state after one iteration, before its outcome: `moved` where the step
    (or the located event) was taken."""

    moved: Bool[Array, " lanes"]
    s: Float[Array, " lanes"]
    x: Float[Array, " lanes"]
    v: Float[Array, " lanes"]
    a: Float[Array, " lanes"]
    h: Float[Array, " lanes"]
    hsave: Float[Array, " lanes"]
    steps: Int[Array, " lanes"]


def advance(lane: Lane, step, found, h_next, active) -> NewState:
    """Lanes that advanced or located their event move to the step's end; the others
    stay at their base. The next step length: the controller's, the next trial's
    while locating, and after a located event the one from before the crossing."""
    moved = found.advance | found.converged
    s_new = jnp.where(moved, lane.s + step.h, lane.s)
    x_new = jnp.where(moved, step.x, lane.x)
    v_new = jnp.where(moved, step.v, lane.v)
    a_new = jnp.where(moved, step.a, lane.a)
    hsave = jnp.where(found.crossed, h_next, lane.search.hsave)
    h_new = jnp.where(found.locating, jax.lax.stop_gradient(found.guess), h_next)
    h_new = jnp.where(found.converged, hsave, h_new)
    steps = lane.steps + active.astype(jnp.int32)
    return NewState(moved, s_new, x_new, v_new, a_new, h_new, hsave, steps)


def next_lane(lane: Lane, step, g1, found, new: NewState, end, active) -> Lane:
    """The lanes after one iteration (`end`: their `Outcome`)."""
    lo, hi, glo, ghi = found.bracket
    old = lane.search
    return Lane(
        p=lane.p,
        idx=lane.idx,
        done=lane.done | end.ends,
        raw=end.raw,
        sigma=lane.sigma,
        s=new.s,
        x=new.x,
        v=new.v,
        a=new.a,
        h=end.h,
        steps=new.steps,
        search=Search(
            locating=found.locating & active,
            lo=lo,
            hi=hi,
            glo=glo,
            ghi=ghi,
            # (The latest trial: the secant's second point.)
            hp=jnp.where(old.locating | found.crossed, step.h, old.hp),
            gp=jnp.where(old.locating | found.crossed, g1, old.gp),
            hsave=new.hsave,
            tries=found.tries,
        ),
        sums=lane.sums,
    )


def where_lanes(mask, new: Lane, old: Lane) -> Lane:
    """`new` on the lanes of `mask`, `old` elsewhere."""
    p = jnp.where(mask, new.p, old.p)  # (lanes last)
    col = lambda like: mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))
    pick = lambda n, o: jnp.where(col(o), n, o)
    rest = jax.tree.map(
        pick, dataclasses.replace(new, p=None), dataclasses.replace(old, p=None)
    )
    return dataclasses.replace(rest, p=p)


def fuse_lanes(lane: Lane, *more):
    """The same lanes (and `more` per-lane arrays), the fields of shape `(lanes,)`
    from one fusion: XLA computes them in many small fusions otherwise, each a
    separate call on a CPU, and copies carried fields whose old values are read
    after the new ones are written. Returns `(lane, *more)`."""
    width = lane.idx.shape[0]
    leaves, treedef = jax.tree.flatten((lane, more))
    pick = [i for i, x in enumerate(leaves) if x.shape == (width,)]
    out = fused([leaves[i] for i in pick])[0]
    for i, x in zip(pick, out):
        leaves[i] = x
    lane, more = jax.tree.unflatten(treedef, leaves)
    return (lane, *more)
