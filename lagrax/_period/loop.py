r"""The period loop: one `lax.while_loop` per device over `width` refilling lanes.

Every iteration advances every lane by one step of its stepper (`lagrax._stepper`:
a Runge–Kutta step from a diffrax tableau or a Taylor step), asks the controller for
the next step length, looks for the lane's event (`events.py`), decides the lane's
outcome (`outcome.py`), hands in the lanes that are done and refills them from the
queue (`queue.py`).

Every iteration is a handful of kernels, because on a CPU each kernel is a separate
call and XLA has no multi-output fusion there: the step, the lane update and the
refill each leave through one `one_fusion`, with the gather, the scatter and the
refill's count around them.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .._jaxpr.switches import switches
from .._stepper.base import AbstractStepper, LaneField
from .._stepper.controller import IController
from .._taylor.stepper import TaylorStepper
from .estimate import step_increments, step_terms
from .events import Event, locate_in_step, search
from .lane import advance, fuse_lanes, Lane, LaneConstants, next_lane
from .outcome import lane_outcome
from .quantities import CompactLagrangian, mechanics
from .queue import Queue
from .units import lane_scales


class Pass(eqx.Module):
    """Everything static about one pass of the loop over the queue.

    `screen`: accumulate the sums of the first-order error bound (`estimate.py`).
    """

    stepper: AbstractStepper
    width: int = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    screen: bool = eqx.field(static=True, default=False)


def _accelerations(L, consts):
    """The acceleration in lane units: for one lane (`scalar_accel(s, x, v, p)`,
    what Taylor coefficients are computed from), and over lanes for the steps
    (`accel_lanes`, `Mechanics.lane_field_accel`: traced once and reused by every
    call site, 13 per Dopri8 step, the event, the refill)."""
    mech = mechanics(L, consts)
    return mech.scalar_accel(), mech.lane_field_accel()


def _queue(cfg, controller, rel, q0s, targets, kinds, rtols, atols, t_max, n_live):
    """The queue of one pass: each amplitude's constants (`Queue.build`)."""
    dtype, stepper = q0s.dtype, cfg.stepper
    valid, Qs, tau = rel.valid, rel.Qs, rel.tau
    columns = {  # name: (its value per amplitude, its value on an idle lane)
        "q0": (q0s, 1.0),
        "Qs": (Qs, 1.0),
        "tau": (tau, 1.0),
        "xt": ((targets.astype(dtype) - q0s) / Qs, 0.0),
        "limit": (jnp.where(valid, t_max / tau, 0.0), 0.0),
        "kind": (kinds.astype(dtype), 0.0),
        "rtol": (rtols.astype(dtype), 1.0),
        "atol": (atols.astype(dtype), 1.0),
        "sigma": (rel.sigma, 1.0),
        # (Computed here, not in the refill: its `pow` is a libm call per lane.)
        "h0": (controller.initial_step(stepper, rtols, atols, dtype), 1.0),
        "valid": (valid.astype(dtype), 0.0),
    }
    return Queue.build(columns, n_live, cfg.screen)


def run_queue(
    L, cfg: Pass, q0s, targets, kinds, rtols, atols, t_max, consts, n_live, rel=None
):
    """The first `n_live` amplitudes of `q0s` (shape (n,)) through `cfg.width`
    refilling lanes (the rest are left unsolved); `rel`: their `Release`, where the
    caller has it.

    Returns `(LoopOutput, executed lane-steps, Release)`: per amplitude the raw
    outcome, event time and state in lane units, steps (and with `cfg.screen` the
    error bound's sums); the lane-steps executed (for the useful-work statistic);
    and each amplitude's `Release`.
    """
    n = q0s.shape[0]
    width = min(cfg.width, n)
    dtmin = 1024 * jnp.finfo(q0s.dtype).eps
    stepper, controller = _checked(cfg.stepper, L, consts, q0s.dtype), IController()
    scalar_accel, accel_lanes = _accelerations(L, consts)
    # Each amplitude's release quantities, once for the whole queue (in the refill
    # they would be computed again for every lane).
    rel = lane_scales(L, q0s, consts) if rel is None else rel
    per_amplitude = (q0s, targets, kinds, rtols, atols, t_max)
    queue = _queue(cfg, controller, rel, *per_amplitude, n_live)

    def body(carry):
        lane, out, state = carry
        lane = _unpack_state(lane)
        c = LaneConstants.unpack(lane.p, kinds.dtype)
        active = ~lane.done
        event = Event(c.kind, lane.sigma, c.xt)
        field = LaneField(
            accel=lambda s, x, v: accel_lanes(c.q0, c.Qs, c.tau, s, x, v),
            scalar_accel=scalar_accel,
            params=(c.q0, c.Qs, c.tau),
        )
        base, free = (lane.s, lane.x, lane.v, lane.a), ~lane.search.locating
        within = _within(stepper, event, field, base, free, cfg.screen)

        # --- step, controller, event
        cap = jnp.maximum(c.limit - lane.s, dtmin)
        step = stepper.step(
            field, *base, lane.h, c.rtol, c.atol, free=free, cap=cap, within=within
        )
        located, terms = step.extras
        finite = step.finite()
        accept = finite & (step.error <= 1.0)
        h_next = controller.adapt(stepper, step.h, step.error, finite, accept)
        g1 = event.value(step.x, step.v, step.a)
        found = search(event, base, lane.search, step, g1, accept, finite, located)

        # --- the new state, the lane's outcome
        new = advance(lane, step, found, h_next, active)
        if cfg.screen:
            inc = step_increments(lane.sums, terms, step, lane.v)
        end = lane_outcome(lane, c, found, new, h_next, active, cfg, dtmin)
        lane = next_lane(lane, step, g1, found, new, end, active)
        # (`moved` from the same fusion: outside it, the sums' fusion recomputes it.)
        lane, *moved = fuse_lanes(lane, *([new.moved] if cfg.screen else []))
        if cfg.screen:
            sums = jnp.where(moved[0][:, None], lane.sums + inc, lane.sums)
            lane = dataclasses.replace(lane, sums=sums)

        # --- lanes that are done hand in their result and take the next amplitude
        out = queue.hand_in(out, lane)
        lane, state = queue.refill(lane, state)
        return _pack_state(lane), out, state

    def cond(carry):
        state = carry[2]
        return (state.busy > 0) | (state.iterations == 0)

    lane, out, state = queue.empty(width)
    init = (_pack_state(lane), out, state)
    lane, out, state = jax.lax.while_loop(cond, body, init)
    return queue.output(out), state.iterations * width, rel


def _checked(stepper, L, consts, dtype):
    """`stepper`, whose Taylor step checks its end (`TaylorStepper.checked`) only
    where `L` switches branch with the state or time (`lagrax._jaxpr.switches`),
    as the trajectories' loop does: for an analytic acceleration the step's defect
    is its truncation, far below the limit, and the check is a Horner sweep per
    step. The compact tier's `L` (its tapes) is not analysed: checked."""
    if not isinstance(stepper, TaylorStepper) or isinstance(L, CompactLagrangian):
        return stepper
    q = jax.ShapeDtypeStruct((1,), dtype)
    state = (q, q, jax.ShapeDtypeStruct((), dtype))
    if switches(lambda q, qdot, t, *c: L(q, qdot, t, *c), state, consts):
        return stepper
    return dataclasses.replace(stepper, checked=False)


# The fields of `Lane` that a step reads, carried from one iteration to the next as
# the consecutive pieces of one array.
_STATE = ("s", "x", "v", "a", "h", "sigma")


def _pack_state(lane: Lane):
    """`(lane, y)`: the lanes with the fields `_STATE` as the consecutive pieces of
    `y` (of shape `(6 lanes,)`).

    The step's fusion reads every carried buffer it uses, and writes its outputs;
    LLVM's loop vectorizer needs a runtime alias check per pair of an output and an
    input (or another output) it cannot prove apart, and above its limit
    (`-vectorize-memory-check-threshold`, 128) leaves the step's loop scalar,
    several times slower (see `Lane`). One buffer for the state the step reads is
    one input instead of one per field: a margin under that limit for the inputs
    that depend on the Lagrangian (what XLA computes from its constants). (Pieces of
    a flat array, not the rows of a matrix: read through rows, a value of the step
    may be emitted as a function called from several places, which LLVM may keep as
    calls, and then vectorizes nothing.)"""
    y = jnp.concatenate([getattr(lane, k) for k in _STATE])
    return dataclasses.replace(lane, **{k: None for k in _STATE}), y


def _unpack_state(packed) -> Lane:
    lane, y = packed
    W = y.shape[0] // len(_STATE)
    fields = {k: y[i * W : (i + 1) * W] for i, k in enumerate(_STATE)}
    return dataclasses.replace(lane, **fields)


def _within(stepper, event, field, base, free, screen):
    """What the loop reads from a step's polynomials, inside the step's fusion: the
    event inside the step, and with `screen` the step's terms of the error bound.
    Returns `within` for `AbstractStepper.step`; its extras are `(InStep, StepTerms)`
    (Nones for a step without polynomials: events are then located by trials)."""
    s, x, v, _ = base

    def within(raw):
        if raw.expansion is None:
            return dataclasses.replace(raw, extras=(None, None))
        raw, located = locate_in_step(raw, event, field.accel, s, x, v, free)
        terms = step_terms(stepper, raw.expansion, v, raw.h, raw.a) if screen else None
        return dataclasses.replace(raw, extras=(located, terms))

    return within
