r"""Which program sweeps a Lagrangian first: the tape path, or the specialized one.

The specialized program (L's equations compiled in) runs fastest but costs seconds
of XLA compile for each new Lagrangian. The tape path (`mechanics.TapeMechanics`,
`lagrax._stepper.tape.TapeTaylorStepper`) runs the same period program with $L$ as
data: its executable is the same for every Lagrangian whose tapes fit its sizes,
compiled once per machine and kept on disk (`lagrax._cache.executables`), so a new
$L$ costs the tracing of its tapes. It runs slower per step (an interpreter over
the tape's nodes), so it is taken, like a JIT's first tier, for eager sweeps until the
amplitudes swept with one Lagrangian and configuration would repay the specialized
compile (`SPECIALIZE_AFTER`), and then the specialized program takes over.

Taken only where nothing is traced (eager calls: under `jit`, `grad` or `vmap` the
program being compiled is the caller's), the stepper is the Taylor step, and the
Lagrangian's tapes can be built (scalar parameters, primitives with an opcode).

Taken only with `LAGRAX_TAPE_TIER=1` (`0` or unset: never): each place the period
program evaluates $L$ inlines an interpreter (twelve: the step's coefficients, its
end and its event in the loop; the release; three at the end of a leg; four in the
far turning point's search; the mass check), each one interpreter over all the lanes
and points it needs, and XLA compiles each on its own. Its one compile per machine
(and tracing, three times the specialized program's) costs more than a Lagrangian's
specialized first sweep, and it runs tens of times slower per step
(`benchmarks/first_result.py` measures both). The sweep runs on it in pieces of one
size (`sweep.tape_piece`), so that one executable serves every number of amplitudes.
Its results agree with the specialized program's to rounding, with the same
statuses.
"""

import collections
import os

import jax
import numpy as np

from .._stepper.tape import TapeTaylorStepper
from .._taylor.solver import Taylor
from .._taylor.tape import build_tape
from .mechanics import AutodiffMechanics, TapeLagrangian, TapeSet


# Amplitudes swept with one canonical Lagrangian and configuration before the
# specialized program is compiled (its compile is repaid past about this many).
SPECIALIZE_AFTER = 200_000
# Smallest tape sizes `(slots, nodes)`: most small Lagrangians share one executable.
_MIN_SIZE = (128, 64)

# Tapes per (canonical L, dtype): a `(TapeLagrangian, TapeSet)` or None (no tape).
_TAPES: collections.OrderedDict = collections.OrderedDict()
_MAX_TAPES = 256
# Amplitudes swept on the tape path per (canonical L, configuration).
_SWEPT: collections.Counter = collections.Counter()


def _concrete(tree) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


def tapes_of(L_c, consts, dtype):
    """`(TapeLagrangian, TapeSet)` of the canonical `L_c`, or None where it has no
    tape; built once per canonical function (the parameters are tape inputs)."""
    key = (L_c, np.dtype(dtype).name)
    if key in _TAPES:
        _TAPES.move_to_end(key)
        return _TAPES[key]
    try:
        found = _build(L_c, consts, dtype)
    except (NotImplementedError, TypeError, ValueError):
        found = None
    _TAPES[key] = found
    if len(_TAPES) > _MAX_TAPES:
        _TAPES.popitem(last=False)
    return found


def _params(n):
    """Parameter inputs per tape: a multiple of 8 at least `n` (the unused ones
    zero), so that Lagrangians with a few more or fewer constants share one
    executable."""
    return 8 * max(1, -(-n // 8))


def _build(L_c, consts, dtype):
    P = _params(len(consts))
    if any(np.size(c) != 1 for c in consts):
        raise NotImplementedError("a tape takes scalar parameters")
    shaped = lambda params: [
        jax.numpy.reshape(p, np.shape(c)) for p, c in zip(params, consts)
    ]
    mech = lambda params: AutodiffMechanics(L_c, shaped(params))
    one = lambda u: jax.numpy.reshape(u, (1,))

    def scaled(s, x, v, q0, Qs, tau, *params):
        return mech(params).scaled_acceleration()(q0, Qs, tau, s, x, v)

    def point(q, qd, t, *params):
        m = mech(params)
        qddot, (M, ok) = m.accelerations(one(q), one(qd), t, fuse=False)
        h, size = m.jacobi(one(q), one(qd), t)
        return qddot[0], M[0, 0], ok, h, size, m.value(one(q), one(qd), t)

    def rest(q, *params):
        m = mech(params)
        z = jax.numpy.zeros((1,), dtype)
        return m.value(one(q), z, jax.numpy.zeros((), dtype))

    tapes = TapeSet(
        scaled=build_tape(scaled, 6 + P, dtype, (0, 1, 2), _MIN_SIZE),
        point=build_tape(point, 3 + P, dtype, (0, 1, 2), _MIN_SIZE),
        rest=build_tape(rest, 1 + P, dtype, (0,), _MIN_SIZE),
    )
    sizes = (tapes.scaled.size, tapes.point.size, tapes.rest.size)
    return TapeLagrangian(sizes, P), tapes


def enabled() -> bool:
    """`LAGRAX_TAPE_TIER`: "1" (on), "0" or unset (off)."""
    value = os.environ.get("LAGRAX_TAPE_TIER", "0").strip() or "0"
    if value not in ("0", "1"):
        raise ValueError(
            f"The environment variable LAGRAX_TAPE_TIER must be 0 or 1; got {value!r}."
        )
    return value == "1"


def choose(L_c, consts, solver, key, q0, n):
    """`(L, consts, stepper, solver)` of the tape path where this sweep takes it
    (module docstring), else None. `key`: the configuration, for counting the
    amplitudes swept with it. On the tape path a `Taylor` solver steps with Taylor
    wherever every primitive has a recurrence (the fallback, for programs too large
    to unroll in the specialized step, does not concern the interpreter)."""
    if not enabled():
        return None
    if not isinstance(solver, Taylor) or not _concrete((q0, consts)):
        return None
    count = (L_c, key)
    if _SWEPT[count] + n > SPECIALIZE_AFTER:
        return None
    found = tapes_of(L_c, consts, q0.dtype)
    if found is None:
        return None
    _SWEPT[count] += n
    L_t, tapes = found
    params = [np.asarray(c).reshape(()) for c in consts]
    params += [np.zeros((), q0.dtype)] * (L_t.n_params - len(params))
    taped = TapeTaylorStepper(order=solver.order, max_step=solver.max_step)
    plain = Taylor(order=solver.order, max_step=solver.max_step)
    return L_t, [tapes, *params], taped, plain
