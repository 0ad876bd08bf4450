"""The compact coefficient program (`lagrax._taylor.compact`): the same Taylor
coefficients as the unrolled program, one compiled program for every tape of a size
class, and the equations of motion where no unrolled reference applies."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.experimental import jet

import lagrax
from lagrax._jaxpr.canonical import canonical_lagrangian
from lagrax._taylor import compact
from lagrax._trajectory.batch import _system as batch_system


G = 9.81
K = 6
W = 3


def chain(n):
    def positions(q, t):
        return jnp.stack([jnp.cumsum(jnp.sin(q)), -jnp.cumsum(jnp.cos(q))], axis=1)

    return lagrax.particle_lagrangian(
        jnp.ones(n), positions, lambda r, t: G * jnp.sum(r[:, 1])
    )


def double_pendulum(q, qd, t):
    t1, t2, w1, w2 = q[0], q[1], qd[0], qd[1]
    T = w1**2 + 0.5 * w2**2 + w1 * w2 * jnp.cos(t1 - t2)
    return T + 2 * G * jnp.cos(t1) + G * jnp.cos(t2)


def pendulum(q, qd, t):
    return 0.5 * qd[0] ** 2 + G * jnp.cos(q[0])


def velocity_dependent(q, qd, t):
    """A charged particle in a magnetic field, in a well."""
    A = 0.7 * (q[0] * qd[1] - q[1] * qd[0])
    return 0.5 * jnp.sum(qd**2) + A - jnp.cosh(0.3 * q[0]) - q[1] ** 2


def velocity_dependent_accel(q, qd, t):
    return jnp.stack(
        [1.4 * qd[1] - 0.3 * jnp.sinh(0.3 * q[0]), -1.4 * qd[0] - 2 * q[1]]
    )


def time_dependent(q, qd, t):
    """A pendulum of time-dependent inertia in a decaying field."""
    m = 1 + 0.1 * jnp.sin(2 * t)
    return 0.5 * m * qd[0] ** 2 + G * jnp.cos(q[0]) * jnp.exp(-0.01 * t)


def time_dependent_accel(q, qd, t):
    m = 1 + 0.1 * jnp.sin(2 * t)
    force = -G * jnp.sin(q[0]) * jnp.exp(-0.01 * t) - 0.2 * jnp.cos(2 * t) * qd[0]
    return (force / m)[None]


def particle(q, qd, t):
    """A particle in 3-D: a constant mass matrix, n = 3."""
    return 0.5 * jnp.sum(qd**2) - G * q[2] - 0.1 * jnp.sum(q**2) ** 2


def particle_accel(q, qd, t):
    return -(G * jnp.eye(3)[2] + 0.4 * jnp.sum(q**2) * q)


def _system(L, n):
    """The program of $q' = w$, $w' = \\ddot q(\\sigma \\tau, q, \\sigma w)$, as
    `simulate_batch` builds it (its own builder)."""
    L_c, consts = canonical_lagrangian(L, jnp.float64, n)
    return batch_system(L_c, consts, None, jnp.zeros(n), jnp.zeros(n))


def _point(n, seed=0):
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 1, W)
    ys = rng.uniform(-0.5, 0.5, (2 * n, W))
    sigma = np.where(rng.uniform(size=W) < 0.5, -1.0, 1.0)
    return t, ys, sigma


def _compact(system, K, t, ys, sigma, tape=None):
    prog = system.prog
    if tape is None:
        tape = compact.build(prog, prog.inputs, prog.params, prog.outs, jnp.float64)
    out = compact.compact_coefficients(
        tape, K, jnp.asarray(t), [jnp.asarray(y) for y in ys], [jnp.asarray(sigma)]
    )
    return np.asarray([[np.asarray(c) for c in cs] for cs in out])  # (2n, K + 1, W)


def _unrolled(system, K, t, ys, sigma, n):
    out = system.coefficients(
        K, jnp.asarray(t), [jnp.asarray(ys[:n].T), jnp.asarray(ys[n:].T)],
        [jnp.asarray(sigma)], unrolled=True,
    )  # fmt: skip
    return np.asarray([[np.asarray(c) for c in cs] for cs in out])


def _jet(accel, n, K, t, ys, sigma):
    """Normalized coefficients by repeated `jax.experimental.jet` of a hand-written
    acceleration, lane by lane (an independent reference)."""

    def f(tau, y, s):
        q, w = y[:n], y[n:]
        return jnp.concatenate([w, accel(q, s * w, s * tau)])

    out = np.zeros((2 * n, K + 1, W))
    for lane in range(W):
        cs = [ys[:, lane]]
        for k in range(K):
            if k == 0:
                fk = f(t[lane], jnp.asarray(cs[0]), sigma[lane])
            else:
                series = [
                    jnp.asarray(cs[j] * math.factorial(j)) for j in range(1, k + 1)
                ]
                tser = [jnp.asarray(1.0)] + [jnp.asarray(0.0)] * (k - 1)
                _, outs = jet.jet(
                    lambda tt, yy: f(tt, yy, sigma[lane]),
                    (jnp.asarray(t[lane]), jnp.asarray(cs[0])),
                    (tser, series),
                )
                fk = outs[k - 1] / math.factorial(k)
            cs.append(np.asarray(fk) / (k + 1))
        out[:, :, lane] = np.stack(cs, axis=1)
    return out


def _close(a, b, tol=1e-13):
    """Per entry and order, relative to the largest magnitude over the lanes."""
    scale = np.maximum(np.abs(b).max(axis=2, keepdims=True), 1e-300)
    err = np.abs(a - b) / scale
    assert np.all(np.isfinite(a))
    assert np.max(err) < tol, np.max(err)


# Every system of the default tests in one size class: one compiled program.
CASES = {
    "pendulum": (pendulum, None, 1),
    "double_pendulum": (double_pendulum, None, 2),
    "velocity_dependent": (velocity_dependent, velocity_dependent_accel, 2),
    "chain3": (chain(3), None, 3),
    "time_dependent": (time_dependent, time_dependent_accel, 1),
    "particle_3d": (particle, particle_accel, 3),
}


@pytest.fixture(scope="module")
def shared():
    """`(systems, tapes, compiled)`: every case's tape padded to one size class,
    and the coefficient program compiled once for it (a state of n = 3 entries;
    smaller systems take zero entries beyond theirs)."""
    systems = {name: _system(L, n) for name, (L, _, n) in CASES.items()}
    build = lambda s, size=None: compact.build(
        s.prog, s.prog.inputs, s.prog.params, s.prog.outs, jnp.float64, size=size
    )
    size = compact.join(*(build(s).sizes() for s in systems.values()))
    tapes = {name: build(s, size) for name, s in systems.items()}
    sizes = {tape.size for tape in tapes.values()}
    return systems, tapes, sizes


def _run(tape, t, ys, sigma):
    return compact.compact_coefficients(tape, K, t, list(ys), [sigma])


# chain3's unrolled reference (a program of its own) with -m slow; n = 3 every time
# against hand-written equations (particle_3d).
@pytest.mark.parametrize(
    "name",
    [
        "pendulum",
        "double_pendulum",
        "velocity_dependent",
        pytest.param("chain3", marks=pytest.mark.slow),
    ],
)
def test_equals_the_unrolled_program(shared, name):
    systems, tapes, _ = shared
    n = CASES[name][2]
    point = _point(n)
    got = np.asarray(jax.jit(_run)(tapes[name], *point))
    _close(got, _unrolled(systems[name], K, *point, n))


@pytest.mark.parametrize(
    "blocks",
    [
        dict(Gc=2, Gl=2, G0=4),
        dict(Gc=1, Gl=1, G0=1),
        dict(Gc=2, Gl=2, G0=4, windows=True),
    ],
)
def test_narrow_blocks_equal_the_unrolled_program(blocks):
    """Blocks of fewer nodes (`build`'s `size`): the inner sums and the histories
    run over the rows in use in chunks of a Cauchy block's rows, several here (from
    histories per operand, or per row a few orders a branch: `windows`)."""
    system = _system(double_pendulum, 2)
    prog = system.prog
    tape = compact.build(
        prog, prog.inputs, prog.params, prog.outs, jnp.float64, size=blocks
    )
    assert tape.cgat.shape[2] == blocks["Gc"] and tape.op0.shape[1] == blocks["G0"]
    assert tape.windows == blocks.get("windows", False)
    assert int(tape.blocks[2]) > 2 * blocks["Gc"]
    point = _point(2, seed=4)
    _close(_compact(system, K, *point, tape=tape), _unrolled(system, K, *point, 2))


def test_signs_and_constant_factors_cost_no_node_above_order_0():
    """The same anharmonic oscillator written plainly and through negations and
    constant factors: the same coefficients, from as many nodes at orders >= 1
    (each sign and factor folded into the coefficients of what reads it)."""

    def plain(q, qd, t):
        return 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2 - 0.25 * q[0] ** 4

    def signed(q, qd, t):
        x, y = -(2.0 * q[0]), 3.0 * q[0]
        return 0.5 * (-qd[0]) ** 2 - x**2 / 8.0 - 0.25 * (-y / 3.0) ** 4

    systems = [_system(L, 1) for L in (plain, signed)]
    tapes = [
        compact.build(s.prog, s.prog.inputs, s.prog.params, s.prog.outs, jnp.float64)
        for s in systems
    ]
    nodes = [int(np.asarray(t.seq1)[: int(t.blocks[1]), 2].sum()) for t in tapes]
    assert nodes[1] == nodes[0], nodes
    point = _point(1, seed=2)
    _close(_compact(systems[1], K, *point), _unrolled(systems[0], K, *point, 1))


@pytest.mark.slow
@pytest.mark.parametrize("n", [2, 4, 6, 8])
def test_chains_equal_the_unrolled_program(n):
    system = _system(chain(n), n)
    point = _point(n, seed=n)
    _close(_compact(system, 12, *point), _unrolled(system, 12, *point, n), 1e-12)


@pytest.mark.parametrize(
    "name", ["time_dependent", "particle_3d", "velocity_dependent"]
)
def test_equals_hand_written_equations(shared, name):
    """Against repeated `jet` of the hand-derived acceleration: a time-dependent L
    (the unrolled program's coefficients of t above order 1 were wrong until
    recently, see the next test), and n = 3 with a constant mass matrix."""
    systems, tapes, _ = shared
    _, accel, n = CASES[name]
    point = _point(n, seed=1)
    got = np.asarray(jax.jit(_run)(tapes[name], *point))
    _close(got, _jet(accel, n, K, *point), 1e-12)


@pytest.mark.parametrize("order", [1, 2])
def test_low_orders_are_the_leading_coefficients(shared, order):
    """Orders 1 and 2 (the acceleration alone; no Cauchy term inside a sum): the
    leading coefficients of order K's."""
    _, tapes, _ = shared
    point = _point(2, seed=2)
    low = compact.compact_coefficients(
        tapes["double_pendulum"], order, *map(jnp.asarray, point[:1]),
        [jnp.asarray(y) for y in point[1]], [jnp.asarray(point[2])],
    )  # fmt: skip
    full = jax.jit(_run)(tapes["double_pendulum"], *point)
    np.testing.assert_allclose(
        np.asarray(low), np.asarray(full)[:, : order + 1], rtol=1e-13, atol=1e-15
    )


def test_unrolled_time_dependent_coefficients():
    """The unrolled program reads $t$'s coefficient $k$ afresh at every order
    ($t_k = 0$ for $k \\ge 2$)."""
    point = _point(1, seed=2)
    system = _system(time_dependent, 1)
    reference = _jet(time_dependent_accel, 1, K, *point)
    _close(_unrolled(system, K, *point, 1), reference, 1e-12)


def test_one_program_serves_a_size_class(shared):
    """Lagrangians of one size class run through ONE compiled program, the tapes
    being its arguments (only the number of state entries differs: a class per n)."""
    systems, tapes, _ = shared
    by_n = {}
    for name, (_, _, n) in CASES.items():
        by_n.setdefault(n, []).append(name)
    for n, names in by_n.items():
        assert len({tapes[name].size[1:] for name in names}) == 1
        t, ys, sigma = _point(n, seed=3)
        compiled = jax.jit(_run).lower(tapes[names[0]], t, ys, sigma).compile()
        for name in names:
            got = compiled(tapes[name], t, ys, sigma)
            got = np.asarray([[np.asarray(c) for c in cs] for cs in got])
            if CASES[name][1] is None:
                _close(got, _unrolled(systems[name], K, t, ys, sigma, n))
            else:
                _close(got, _jet(CASES[name][1], n, K, t, ys, sigma), 1e-12)


def test_non_scalar_program_raises():
    """A program whose variables are arrays (not scalarized) has no compact tape:
    callers then take the unrolled program."""
    from lagrax._taylor.program import _Program

    def accel(s, x, v):
        return jnp.sum(jnp.sin(jnp.stack([x, v])))

    scalar = jax.ShapeDtypeStruct((), jnp.float64)
    prog = _Program(jax.make_jaxpr(accel)(scalar, scalar, scalar), 0)
    with pytest.raises(NotImplementedError, match="scalars"):
        compact.build(prog, [0, 1, 2], [], [prog.out], jnp.float64)
