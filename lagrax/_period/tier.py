r"""Which program sweeps a Lagrangian: the compact one, or the specialized one.

The specialized program (L's equations compiled in) runs fastest but costs seconds
of XLA compile for each new Lagrangian. The compact program runs the same period
program with $L$ as data (`mechanics.CompactMechanics`,
`lagrax._taylor.compact_stepper.CompactTaylorStepper`: two compact tapes,
`lagrax._taylor.compact`): its executable is the same for every Lagrangian whose
tapes are of one size class, compiled once per machine and kept on disk
(`lagrax._cache.executables.call`), so that a new $L$ costs the tracing of its
tapes, the load and the run. It runs several times slower per step, so it is
taken, like a JIT's first tier, for a Lagrangian's first eager sweeps, until the
time spent there with one Lagrangian and configuration, with the sweep at hand,
would reach the specialized compile's (a ski rental: the work repays the
compile), and then the specialized program takes over. A sweep whose specialized
program is compiled, or on disk, takes it at once. Where the process leaves a core
idle, a Lagrangian's second compact sweep instead starts the specialized compile
in a worker process there (`executables.compile_later`): the compact program runs
the sweeps meanwhile, without the rental, and the specialized one takes over once
on disk.

Taken only where nothing is traced (eager calls, and the forward passes of an
eager `jax.grad`: under a caller's `jit` the program being compiled is the
caller's), the stepper is the Taylor step, the executables are kept on disk (one
process, a CPU), and the Lagrangian's tapes can be built (scalar parameters,
primitives with a compact opcode). Its results agree with the specialized
program's to rounding, with the same statuses and error estimates.

`LAGRAX_COMPACT`: "1" or unset (the tiers above), "0" (the specialized program
only), "2" (the compact one wherever it applies: benchmarks, tests).
`LAGRAX_BACKGROUND=0`: no compile in a worker process (the rental only).
"""

import collections
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .._cache import executables
from .._jaxpr import scalarize as _scalarize
from .._jaxpr.fusion import fusion_off
from .._taylor import compact
from .._taylor.compact_stepper import CompactTaylorStepper
from .._taylor.stepper import TaylorStepper
from .._taylor.system import _eval_entries, _SystemProgram
from .._trajectory.batch import _compact_mode, _kept
from .quantities import AutodiffMechanics, CompactLagrangian, PeriodTapes


# Seconds the specialized program takes to trace and compile: a sweep's, one
# lane's (`lagrax.period`), and a sweep's forward-mode derivative's (one pinned
# CPU core, 1-DOF Lagrangians at order 20; `benchmarks/first_result.py`).
COMPILE_S = {"sweep": 10.0, "period": 3.0, "jacobian": 20.0}
# Seconds per amplitude on the compact program before one is measured here.
_RATE_PRIOR = 1e-4

# Tapes per (canonical L, dtype): `(CompactLagrangian, PeriodTapes)` or None.
_TAPES: collections.OrderedDict = collections.OrderedDict()
_MAX_TAPES = 256
# Seconds spent on the compact program per (canonical L, configuration), and the
# last measured seconds per amplitude per compact program.
_SPENT: collections.Counter = collections.Counter()
_RATE: dict = {}

# The smallest sizes of the tapes (`compact.build`'s `size`), so that most
# Lagrangians of one coordinate share one executable: the families of every
# period program, and sizes that hold the natural systems of `lagrax.systems`
# (the pendulum, the cycloid, the asymmetric well, rectilinear motion).
_FAMILIES = (compact.AFFINE, compact.RARE, compact.LOGIC, compact.SINCOS)
# Narrow blocks (Gc, Gl, G0 nodes per block): a 1-DOF tape has one or two real
# nodes where a block of 8 would pad them (`benchmarks/compact_steps.py`); inner
# sums a few orders a branch (`windows`: a smaller program, faster to load).
_SIZE = {
    "step": dict(
        families=_FAMILIES, S=128, NB0=64, H=32, U=32, NB=32, B1cau=16, B1slin=8,
        B1dlin=16, B00=16, B01=32, B02=8, B03=2, Gc=2, Gl=2, G0=4, windows=True,
    ),
    "point": dict(
        families=_FAMILIES, S=256, NB0=64, H=64, U=64, NB=64, B1cau=32, B1slin=32,
        B1dlin=32, B00=32, B01=32, B02=4, B03=2, Gc=2, Gl=2, G0=4, windows=True,
    ),
}  # fmt: skip
# Parameter inputs per tape: a multiple of this (the unused ones zero).
_PARAMS = 8


def _concrete(tree) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


def tapes_of(L_c, consts, dtype):
    """`(CompactLagrangian, PeriodTapes)` of the canonical `L_c`, or None where it
    has no compact tape; built once per canonical function (its constants are the
    tapes' parameters)."""

    def make():
        try:
            return _build(L_c, consts, dtype)
        except (NotImplementedError, TypeError, ValueError):
            return None

    return _kept(_TAPES, (L_c, np.dtype(dtype).name), make, _MAX_TAPES)


def n_params(n):
    """Parameter inputs for `n` constants: a multiple of `_PARAMS`."""
    return _PARAMS * max(1, -(-n // _PARAMS))


def _tape(fn, n_series, n_params, dtype, size):
    """The compact tape of `fn(*scalars)`: its first `n_series` inputs `(t, y...)`,
    then `n_params` parameters; its outputs a tuple of scalars. Its program is
    built entry by entry, as `System`'s (a Lagrangian of particles computes with
    their position vectors)."""
    scalar = jax.ShapeDtypeStruct((), dtype)
    specs = [scalar] * (n_series + n_params)
    with fusion_off():  # (an identity for XLA; no opcode for it)
        closed = jax.make_jaxpr(fn)(*specs)

        def entries(*args):
            args = [_scalarize._filled((), [a]) for a in args]
            outs = _eval_entries(closed.jaxpr, closed.consts, args)
            return tuple(jnp.asarray(o.reshape(()).item(), dtype) for o in outs)

        closed = jax.make_jaxpr(entries)(*specs)
    prog = _SystemProgram(closed, n_series, n_params)
    return compact.build(prog, prog.inputs, prog.params, prog.outs, dtype, size=size)


def _build(L_c, consts, dtype):
    if any(np.size(c) != 1 for c in consts):
        raise NotImplementedError("a compact tape takes scalar parameters")
    P = n_params(len(consts))
    shaped = lambda params: [
        jnp.reshape(p, np.shape(c)) for p, c in zip(params, consts)
    ]
    mech = lambda params: AutodiffMechanics(L_c, shaped(params))
    one = lambda u: jnp.reshape(u, (1,))

    def step(s, x, v, q0, Qs, tau, *params):
        accel = mech(params).scaled_acceleration(fuse=False)
        return v, accel(q0, Qs, tau, s, x, v)

    def point(t, q, qdot, *params):
        m = mech(params)

        def accel(q, qdot, t):
            qddot, (M, ok) = m.accelerations(one(q), one(qdot), t, fuse=False)
            return qddot[0], (M[0, 0], ok)

        qddot, (M, ok) = accel(q, qdot, t)
        # The jerk along the flow, d/dt q̈ at (q̇, q̈, 1).
        tangents = (qdot, qddot, jnp.ones_like(t))
        _, jerk = jax.jvp(lambda *a: accel(*a)[0], (q, qdot, t), tangents)
        h, size = m.jacobi(one(q), one(qdot), t)
        value = lambda q: m.value(one(q), one(qdot), t)
        L, slope = jax.value_and_grad(value)(q)
        return qddot, M, ok.astype(q.dtype), h, size, L, slope, jerk

    tapes = PeriodTapes(
        step=_tape(step, 3, 3 + P, dtype, _SIZE["step"]),
        point=_tape(point, 3, P, dtype, _SIZE["point"]),
    )
    return CompactLagrangian((tapes.step.size, tapes.point.size), P), tapes


def applies(stepper) -> bool:
    """Whether the compact tier may be taken at all: a Taylor step, executables
    kept on disk (one process, a CPU), unless `LAGRAX_COMPACT=0`."""
    return (
        type(stepper) is TaylorStepper
        and _compact_mode() != "0"
        and executables.applies()
        and executables.cache_dir() is not None
    )


def always() -> bool:
    """`LAGRAX_COMPACT=2`: the compact program wherever it applies."""
    return _compact_mode() == "2"


class Plan:
    """How a compact call runs: its Lagrangian, constants and stepper; `record`
    after it ran (the time spent, for the ski rental)."""

    def __init__(self, L_t, consts, stepper, count):
        self.L, self.consts, self.stepper, self._count = L_t, consts, stepper, count
        self._start = time.perf_counter()

    def repeated(self) -> bool:
        """Whether the compact program has run with this Lagrangian and
        configuration before (a job that repeats)."""
        return _SPENT[self._count] > 0

    def start(self):
        self._start = time.perf_counter()

    def record(self, kind, n):
        """The seconds since `start` as spent with this Lagrangian and
        configuration, and per amplitude of `kind` (`COMPILE_S`)."""
        spent = time.perf_counter() - self._start
        _SPENT[self._count] += spent
        _RATE[kind] = spent / max(n, 1)


def plan(L_c, consts, stepper, key, n, dtype, kind="sweep", waiting=False):
    """The compact tier's `Plan` for this call, or None where the specialized
    program runs it (module docstring). `key`: the configuration, for the time
    spent with it; `n`: the amplitudes of the call; `kind`: which specialized
    compile it saves (`COMPILE_S`), whose last measured time per amplitude
    predicts this call's; `waiting`: the specialized program is being compiled in
    another process (`executables.compile_later`), so no ski rental."""
    if not applies(stepper) or not _concrete(consts):
        return None
    count = (L_c, key, kind)
    if _compact_mode() != "2" and not waiting:
        predicted = n * _RATE.get(kind, _RATE_PRIOR)
        if _SPENT[count] + predicted >= COMPILE_S[kind]:
            return None
    found = tapes_of(L_c, consts, dtype)
    if found is None:
        return None
    L_t, tapes = found
    dtype = tapes.step.values.dtype
    params = [np.asarray(c, dtype).reshape(()) for c in consts]
    params += [np.zeros((), dtype)] * (L_t.n_params - len(params))
    taped = CompactTaylorStepper(order=stepper.order, max_step=stepper.max_step)
    return Plan(L_t, [tapes, *params], taped, count)


# Specialized programs compiled in this process for a Lagrangian new to it, per
# kind: the second such Lagrangian compiles the compact program instead.
_COMPILED: collections.Counter = collections.Counter()
_NOTIFIED: set = set()


class Compact:
    """One call of the compact program (`Plan`): `jitted` its function, `static`
    what besides the arguments' shapes determines it (`executables.call`)."""

    def __init__(self, plan, jitted, static, out_tree, args):
        self.plan, self.jitted, self.static = plan, jitted, static
        self.out_tree, self.args = out_tree, args

    def ready(self) -> bool:
        """Whether the executable is compiled in this process or on disk."""
        return executables.call_available(self.static, *self.args)

    def run(self, kind, specialized):
        """The compact program where its executable is at hand, or where the
        process compiled a specialized program of this kind for another
        Lagrangian already (new Lagrangians come often: the compact one, compiled
        once per machine, serves them all) or `always()`; else `specialized()`
        (today's first call)."""
        ready = self.ready()
        if not (ready or always() or _COMPILED[kind]):
            _COMPILED[kind] += 1
            return specialized()
        if not ready:
            _notify(kind)
        self.plan.start()
        out = executables.call(self.jitted, self.static, self.out_tree, *self.args)
        jax.block_until_ready(out)
        if ready:
            # A call that compiled is not the compact program's running time: with
            # it, the ski rental would compile the specialized program next.
            self.plan.record(kind, self.args[0].shape[0])
        return out


def several_lagrangians(kind="sweep"):
    """The caller is about to run several new Lagrangians (the command line's
    systems): the first already takes the compact program, compiled once for all
    of them, instead of a specialized program of its own."""
    _COMPILED[kind] = max(_COMPILED[kind], 1)


def _notify(kind):
    """One line, once per kind, before the compact program's compile."""
    if kind in _NOTIFIED:
        return
    _NOTIFIED.add(kind)
    what = {"jacobian": "derivative of a period sweep"}.get(kind, "period sweep")
    warnings.warn(
        f"lagrax: compiling the {what} for Lagrangians as data, once per machine "
        "(tens of seconds); later processes load it, and a new Lagrangian then "
        "runs without compiling.",
        stacklevel=_caller_level(),
    )


def _caller_level() -> int:
    """The `stacklevel` of the first frame outside lagrax and JAX (the user's
    call, however deep the library's and JAX's transformations are)."""
    import sys

    level, frame = 1, sys._getframe(1)
    while frame is not None:
        module = frame.f_globals.get("__name__", "")
        if not module.startswith(("lagrax.", "jax.", "jax")):
            return level
        level, frame = level + 1, frame.f_back
    return 1
