"""A Lagrangian keyed on what it computes (`lagrax._jaxpr.canonical`)."""

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import lagrax
from lagrax._jaxpr.canonical import canonical_lagrangian
from lagrax._period import sweep as sweep_module
from lagrax.systems import asymmetric_well, pendulum


f64 = np.float64
z1, z0 = np.zeros((1,)), np.zeros(())


def test_same_body_new_values_is_the_same_function():
    L1, c1 = canonical_lagrangian(pendulum.lagrangian(g=1.0), f64)
    L2, c2 = canonical_lagrangian(pendulum.lagrangian(g=2.5, r=0.5), f64)
    assert L1 is L2
    assert [float(c) for c in c1] != [float(c) for c in c2]
    q, qd = np.array([0.7]), np.array([-0.3])
    for L, c in ((pendulum.lagrangian(g=2.5, r=0.5), c2), (pendulum.lagrangian(), c1)):
        np.testing.assert_allclose(L1(q, qd, z0, *c), L(q, qd, z0), rtol=0, atol=0)


def test_another_body_is_another_function():
    Lp, _ = canonical_lagrangian(pendulum.lagrangian(), f64)
    Lw, _ = canonical_lagrangian(asymmetric_well.lagrangian(), f64)
    # The same operations but an integer exponent changed: a structural difference.
    Lc, _ = canonical_lagrangian(lambda q, qd, t: 0.5 * qd[0] ** 2 - q[0] ** 4, f64)
    Ld, _ = canonical_lagrangian(lambda q, qd, t: 0.5 * qd[0] ** 2 - q[0] ** 2, f64)
    assert len({Lp, Lw, Lc, Ld}) == 4


def test_module_parameters_and_tracers_are_lifted():
    class Well(eqx.Module):
        k: jax.Array

        def __call__(self, q, qdot, t):
            return 0.5 * qdot[0] ** 2 - 0.5 * self.k * q[0] ** 2

    L1, c1 = canonical_lagrangian(Well(jnp.asarray(1.0)), f64)
    L2, c2 = canonical_lagrangian(Well(jnp.asarray(4.0)), f64)
    assert L1 is L2 and float(c1[0]) == 1.0 and float(c2[0]) == 4.0

    def value(g):
        L = pendulum.lagrangian(g=g)
        L_c, consts = canonical_lagrangian(L, f64)
        return L_c(np.array([0.5]), z1, z0, *consts)

    # d/dg of g cos(q) through the lifted tracer.
    assert np.isclose(jax.grad(value)(2.0), np.cos(0.5), rtol=1e-15)


def test_rebuilt_lagrangian_reuses_the_compiled_sweep():
    q0 = jnp.linspace(0.1, 3.0, 32)
    kw = dict(method="quarter", solver=dfx.Dopri8(), error_estimate=False)
    first = lagrax.sweep_periods(pendulum.lagrangian(g=1.0), q0, **kw)
    misses = sweep_module._sweep_jit.cache_info().misses
    second = lagrax.sweep_periods(pendulum.lagrangian(g=4.0), q0, **kw)
    assert sweep_module._sweep_jit.cache_info().misses == misses
    assert np.all(first.ok) and np.all(second.ok)
    # T scales as 1/sqrt(g).
    np.testing.assert_allclose(second.periods, first.periods / 2, rtol=1e-11)
    np.testing.assert_allclose(second.periods, pendulum.period(q0, g=4.0), rtol=1e-11)


def test_new_values_change_the_outcome():
    # The values reach the compiled program as arguments, none is kept from the
    # first call: upside down (g = -1) the pendulum swings about pi, and without
    # gravity it does not swing at all. (The shape and options of the test above:
    # its compiled program.)
    q0 = jnp.linspace(0.2, 2.9, 32)
    kw = dict(method="quarter", solver=dfx.Dopri8(), error_estimate=False)
    flipped = lagrax.sweep_periods(pendulum.lagrangian(g=-1.0), q0, **kw)
    exact = pendulum.period(jnp.pi - q0)
    np.testing.assert_allclose(flipped.periods, exact, rtol=1e-11)
    still = lagrax.sweep_periods(pendulum.lagrangian(g=0.0), q0, **kw)
    assert not np.any(still.ok)


STRENGTH = 9.81


def _reads_a_global(q, qdot, t):
    return 0.5 * qdot[0] ** 2 + STRENGTH * jnp.cos(q[0])


def test_a_global_changed_between_calls_is_seen(monkeypatch):
    # The same function object, a value it reads changed: the next call uses it (no
    # constants remembered per function object).
    q0, v0 = jnp.array([1.0]), jnp.array([0.0])
    a = lagrax.accelerations(_reads_a_global, q0, v0)
    s = lagrax.simulate(_reads_a_global, q0, v0, 0.0, 1.0).ys[0]
    monkeypatch.setitem(globals(), "STRENGTH", 1.62)
    b = lagrax.accelerations(_reads_a_global, q0, v0)
    t = lagrax.simulate(_reads_a_global, q0, v0, 0.0, 1.0).ys[0]
    np.testing.assert_allclose(a, -9.81 * np.sin(1.0), rtol=1e-14)
    np.testing.assert_allclose(b, -1.62 * np.sin(1.0), rtol=1e-14)
    fresh = pendulum.lagrangian(g=1.62)
    np.testing.assert_array_equal(t, lagrax.simulate(fresh, q0, v0, 0.0, 1.0).ys[0])
    assert not np.array_equal(s, t)


def test_a_function_is_traced_once_while_what_it_reads_stays():
    L = pendulum.lagrangian(g=2.0)
    L1, c1 = canonical_lagrangian(L, f64)
    L2, c2 = canonical_lagrangian(L, f64)
    # The kept result: the same constant objects, no new trace.
    assert L1 is L2 and all(a is b for a, b in zip(c1, c2, strict=True))
    _, c3 = canonical_lagrangian(L, np.float32)
    assert not any(a is b for a, b in zip(c1, c3))


class _Holder:
    strength = 1.0


_HELPER_STRENGTH = 1.0


def _helper(q):
    return _HELPER_STRENGTH * jnp.cos(q[0])


def _changed_reads():
    """(L, change) pairs: `change()` changes something `L` reads."""
    cases = {}

    def closure_cell():
        k = 1.0

        def L(q, qd, t):
            return 0.5 * qd[0] ** 2 - k * q[0] ** 2

        def change():
            nonlocal k
            k = 3.0

        return L, change

    def helper_global():
        def L(q, qd, t):
            return 0.5 * qd[0] ** 2 + _helper(q)

        def change():
            globals()["_HELPER_STRENGTH"] = 2.5

        return L, change

    def array_in_place():
        a = np.array([1.0, 2.0])

        def L(q, qd, t):
            return 0.5 * qd[0] ** 2 - a[1] * q[0] ** 2

        def change():
            a[1] = 7.0

        return L, change

    def default_list():
        def L(q, qd, t, p=[1.0]):  # noqa: B006 -- the mutable default is the case
            return 0.5 * qd[0] ** 2 - p[0] * q[0] ** 2

        def change():
            L.__defaults__[0][0] = 4.0

        return L, change

    def signed_zero():
        z = 0.0

        def L(q, qd, t):
            return 0.5 * qd[0] ** 2 + jnp.arctan2(z, -1.0 - q[0] ** 2)

        def change():
            nonlocal z
            z = -0.0

        return L, change

    def object_attribute():
        h = _Holder()

        def L(q, qd, t):
            return 0.5 * qd[0] ** 2 - h.strength * q[0] ** 2

        def change():
            h.strength = 6.0

        return L, change

    for make in (
        closure_cell,
        helper_global,
        array_in_place,
        default_list,
        signed_zero,
        object_attribute,
    ):
        cases[make.__name__] = make
    return cases


def test_every_changed_read_is_seen(monkeypatch):
    monkeypatch.setitem(globals(), "_HELPER_STRENGTH", 1.0)
    q, qd = np.array([0.7]), np.array([-0.3])
    for name, make in _changed_reads().items():
        L, change = make()
        L_c, c = canonical_lagrangian(L, f64)
        before = float(L_c(q, qd, z0, *c))
        assert before == float(L(q, qd, z0)), name
        canonical_lagrangian(L, f64)  # kept, if it can be
        change()
        L_c, c = canonical_lagrangian(L, f64)
        after = float(L_c(q, qd, z0, *c))
        assert after == float(L(q, qd, z0)) and after != before, name
