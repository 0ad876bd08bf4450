"""The period loop's queue: amplitudes loaded into lanes, results handed in.

A lane that finishes its amplitude writes its result into the output table and takes
the next amplitude from the queue inside the loop, so lanes never wait for the slowest
one and the input order does not matter. The refill is one gather of packed
per-amplitude columns and one scatter of packed results per iteration, without a
`lax.cond`: each gather, scatter or small fusion is a separate call on a CPU, and ten
of them with a `cond` cost as much as the Taylor step.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .estimate import NUM_SUMS, SUMS_OUT
from .events import Search
from .lane import fuse_lanes, Lane, PARAMS, where_lanes
from .outcome import INVALID, LOCATED


# What each amplitude's lane hands in (packed as the columns of one array), and the
# first of the error bound's sums with `screen`.
_OUT = ("sigma", "raw", "s", "x", "v", "steps")


class QueueState(eqx.Module):
    """The next queue position to hand out (`head`), the iterations so far, and the
    lanes with an amplitude (to step, or to hand in)."""

    head: Int[Array, ""]
    iterations: Int[Array, ""]
    busy: Int[Array, ""]


class LoopOutput(eqx.Module):
    """Per amplitude: the sign of its last leg's event function, raw outcome, event
    time and state (lane units), steps, and with `screen` the error bound's sums."""

    sigma: Float[Array, " n"]
    raw: Int[Array, " n"]
    s: Float[Array, " n"]
    x: Float[Array, " n"]
    v: Float[Array, " n"]
    steps: Int[Array, " n"]
    sums: tuple | None


class Queue(eqx.Module):
    """Every amplitude's constants, one column per amplitude and a last column for idle
    lanes, so that a refill is one gather (`table`, rows by name in `rows`)."""

    table: Float[Array, "rows n1"]
    rows: dict = eqx.field(static=True)
    n_live: Int[Array, ""]
    screen: bool = eqx.field(static=True)

    @staticmethod
    def build(columns: dict, n_live, screen) -> "Queue":
        """`columns`: name -> (its value per amplitude, its value on an idle lane), the
        lane constants (`PARAMS`) first."""
        assert tuple(columns)[: len(PARAMS)] == PARAMS  # `p` is the first rows
        dtype = next(iter(columns.values()))[0].dtype
        live_cols = jnp.stack([v for v, _ in columns.values()])
        idle_col = np.array([[idle] for _, idle in columns.values()], dtype)
        table = jnp.concatenate([live_cols, idle_col], axis=1)
        rows = {k: i for i, k in enumerate(columns)}
        return Queue(table, rows, n_live, screen)

    @property
    def n(self):
        return self.table.shape[1] - 1

    def load(self, idx) -> Lane:
        """Lane constants and initial state for queue positions `idx` (>= n: idle)."""
        n, row = self.n, self.rows
        live = idx < self.n_live
        p = self.table[:, jnp.where(live, idx, n)]
        valid = p[row["valid"]] > 0
        z = jnp.zeros_like(p[0])
        sums = jnp.zeros(z.shape + (NUM_SUMS,), z.dtype) if self.screen else None
        return Lane(
            p=p[: len(PARAMS)],
            idx=jnp.where(live, idx, n).astype(jnp.int32),
            done=~valid,
            raw=jnp.where(live & ~valid, INVALID, LOCATED).astype(jnp.int32),
            sigma=p[row["sigma"]],
            s=z,
            x=z,
            v=z,
            a=p[row["sigma"]],  # q̈(q0) in the lane's units is ±1 by construction
            h=p[row["h0"]],
            steps=jnp.zeros_like(idx, jnp.int32),
            search=Search(
                locating=jnp.zeros_like(idx, bool),
                lo=z,
                hi=z,
                glo=z,
                ghi=z,
                hp=z,
                gp=z,
                hsave=z,
                tries=jnp.zeros_like(idx, jnp.int32),
            ),
            sums=sums,
        )

    def empty(self, width) -> tuple[Lane, Array, QueueState]:
        """Every lane done and idle: the first iteration steps nothing and its
        refill loads the first amplitudes (no copy of `load` outside the loop)."""
        n = self.n
        shapes = jax.eval_shape(self.load, jnp.arange(width, dtype=jnp.int32))
        lane = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
        lane = dataclasses.replace(
            lane, done=jnp.ones(width, bool), idx=jnp.full(width, n, jnp.int32)
        )
        cols = len(_OUT) + (len(SUMS_OUT) if self.screen else 0)
        out = jnp.zeros((n, cols), self.table.dtype)
        head, iterations = jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32)
        return lane, out, QueueState(head, iterations, jnp.zeros((), jnp.int32))

    def hand_in(self, out, lane: Lane):
        """Lanes that are done write their results into their amplitude's row."""
        n, dtype = self.n, out.dtype
        done = lane.done & (lane.idx < n)
        cols = [getattr(lane, k).astype(dtype) for k in _OUT]
        if self.screen:
            cols += [lane.sums[:, i] for i in range(len(SUMS_OUT))]
        rows = jnp.stack(cols, axis=1)
        return out.at[jnp.where(done, lane.idx, n)].set(rows, mode="drop")

    def refill(self, lane: Lane, state: QueueState) -> tuple[Lane, QueueState]:
        """Lanes that are done take the next amplitudes, at the end of the iteration:
        the next step then reads the carried buffers themselves (refilled at its
        start, the refill's selects would join the Taylor step's fusion, three inputs
        per field, past LLVM's limit of alias checks: see `Lane`)."""
        n, nxt = self.n, state.head
        width = lane.idx.shape[0]
        free = lane.done
        rank = jnp.cumsum(free.astype(jnp.int32))
        pending = jnp.where(free, nxt + rank - 1, n).astype(jnp.int32)
        lane = fuse_lanes(where_lanes(free, self.load(pending), lane))[0]
        # Lanes with an amplitude: those not free, and the free ones that took one.
        # Counted from the refill's own total, not by a reduction over the lanes in
        # the loop's `cond` (more kernels per iteration).
        n_free = rank[-1]
        live_left = jnp.clip(self.n_live - nxt, 0, n_free)
        busy = (width - n_free + live_left).astype(jnp.int32)
        next_ = (nxt + n_free).astype(jnp.int32)
        return lane, QueueState(next_, state.iterations + 1, busy)

    def output(self, out) -> LoopOutput:
        cols = [out[:, i] for i in range(out.shape[1])]
        sigma, raw, s, x, v, steps = cols[: len(_OUT)]
        sums = tuple(cols[len(_OUT) :]) if self.screen else None
        return LoopOutput(
            sigma, raw.astype(jnp.int32), s, x, v, steps.astype(jnp.int32), sums
        )
