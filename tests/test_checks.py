"""Argument checks (`lagrax._checks`) through the public functions that use them, and
the hand-derived helpers of `lagrax.systems` against lagrax's own equations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax.systems import (
    asymmetric_well,
    charged_particle,
    cycloid,
    driven_pendulum,
    pendulum,
)


def test_integer_arguments_are_promoted_where_harmless():
    # Whole radians and an integer length or g: the same as the float call.
    T_int = pendulum.period(1, r=2, g=3)
    T_float = pendulum.period(1.0, r=2.0, g=3.0)
    assert jnp.issubdtype(jnp.result_type(T_int), jnp.floating)
    np.testing.assert_allclose(T_int, T_float, rtol=1e-15)
    np.testing.assert_allclose(cycloid.period(R=2, g=3), cycloid.period(R=2.0, g=3.0))


@pytest.mark.parametrize("bad", [object(), "1.0", None, 1 + 2j, True])
def test_non_numbers_are_rejected_naming_the_argument(bad):
    with pytest.raises(TypeError, match="`amplitude`"):
        pendulum.period(bad)


@pytest.mark.parametrize("name", ["r", "g"])
def test_non_positive_lengths_are_rejected(name):
    with pytest.raises(ValueError, match=f"`{name}` must be positive"):
        pendulum.period(1.0, **{name: 0})


@pytest.mark.parametrize("bad", ["up", None, len, (1.0, 2.0), 1j, [[0.0, 1.0]]])
def test_charged_particle_fields_are_checked(bad):
    with pytest.raises((TypeError, ValueError), match="`B` must be a real 3-vector"):
        charged_particle.lagrangian(B=bad)


def test_asymmetric_well_helpers_agree_with_lagrange():
    k, a, m = 2.0, 0.7, 1.5
    L = asymmetric_well.lagrangian(m=m, k=k, a=a)
    x = jnp.array([0.3])
    v = jnp.array([0.4])
    # V is the potential of L (kinetic part at zero velocity vanishes) ...
    np.testing.assert_allclose(
        -L(x, jnp.zeros(1), 0.0), asymmetric_well.potential(x[0], k=k, a=a)
    )
    # ... and the barrier top is a stationary point of V at the height given.
    xb, Vb = asymmetric_well.barrier(k=k, a=a)
    dV = jax.grad(lambda x: asymmetric_well.potential(x, k=k, a=a))(xb)
    assert abs(float(dV)) < 1e-12
    np.testing.assert_allclose(asymmetric_well.potential(xb, k=k, a=a), Vb)
    np.testing.assert_allclose(
        lagrax.accelerations(L, x, v),
        asymmetric_well.acceleration(x, v, m=m, k=k, a=a),
        rtol=1e-13,
    )


def test_cycloid_u_acceleration_agrees_with_lagrange():
    L = cycloid.lagrangian_u(R=0.7, g=2.0)
    u, udot = jnp.array([0.4]), jnp.array([-0.3])
    np.testing.assert_allclose(
        lagrax.accelerations(L, u, udot),
        cycloid.acceleration_u(u, udot, R=0.7, g=2.0),
        rtol=1e-13,
    )


def test_kapitza_frequency_scales_as_its_formula():
    w = driven_pendulum.kapitza_critical_frequency(a=0.1, l=1.0, g=9.81)
    np.testing.assert_allclose(w, np.sqrt(2 * 9.81) / 0.1)
    # Four times the length: twice the frequency; twice the amplitude: half.
    np.testing.assert_allclose(
        driven_pendulum.kapitza_critical_frequency(a=0.1, l=4.0, g=9.81), 2 * w
    )
    np.testing.assert_allclose(
        driven_pendulum.kapitza_critical_frequency(a=0.2, l=1.0, g=9.81), w / 2
    )


# Indexing inside branches and loop bodies is checked as well (q has one coordinate).
_SUM_SQUARES = {
    "cond": lambda q, t: jax.lax.cond(t > -1.0, lambda: q[2] ** 2, lambda: q[0] ** 2),
    "while_loop": lambda q, t: jax.lax.while_loop(
        lambda c: c[0] < 3, lambda c: (c[0] + 1, c[1] + q[c[0]] ** 2), (0, 0.0)
    )[1],
    "fori_loop": lambda q, t: jax.lax.fori_loop(0, 3, lambda i, a: a + q[i] ** 2, 0.0),
}


@pytest.mark.parametrize("name", sorted(_SUM_SQUARES))
def test_out_of_range_index_in_control_flow_is_an_error(name):
    V = _SUM_SQUARES[name]
    L = lambda q, qdot, t: 0.5 * jnp.sum(qdot**2) - V(q, t)
    with pytest.raises(ValueError, match="`L` must index its arguments") as info:
        lagrax.energy(L, jnp.ones(1), jnp.ones(1))
    assert "test_checks.py:" in str(info.value)  # the line that indexes
    # On as many coordinates as it indexes: E = T + V, V = 1 + 4 + 9 (or 9).
    E = lagrax.energy(L, jnp.array([1.0, 2.0, 3.0]), jnp.ones(3))
    np.testing.assert_allclose(E, 1.5 + (9.0 if name == "cond" else 14.0))


class _Accelerator:
    platform = "gpu"


def test_lanes_default_by_backend():
    # A CPU gets its own default whatever the batch; an accelerator every item of a
    # device's share up to its cap; a given value is checked and kept.
    from lagrax._checks import lane_count

    cpu, gpu = jax.devices("cpu"), (_Accelerator(),)
    kw = dict(cpu=256, accelerator=1 << 17)
    assert lane_count(None, "lanes", cpu, 10**6, **kw) == 256
    assert lane_count(None, "lanes", gpu, 10**4, **kw) == 10**4
    assert lane_count(None, "lanes", gpu, 10**6, **kw) == 1 << 17
    assert lane_count(7, "lanes", gpu, 10**6, **kw) == 7
    with pytest.raises(ValueError, match="`lanes`"):
        lane_count(0, "lanes", cpu, 10, **kw)


def test_sweep_runs_its_default_lanes_on_a_cpu():
    res = lagrax.sweep_periods(
        pendulum.lagrangian(), jnp.linspace(0.1, 1.0, 3), method="quarter"
    )
    assert res.lanes == 256
    assert np.isfinite(np.asarray(res.periods)).all()
