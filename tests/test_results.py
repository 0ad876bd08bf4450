"""One status enumeration for every period: its fixed int view, and its messages
surviving `jit`."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax.systems import pendulum


PENDULUM = pendulum.lagrangian()

# The int view is a public contract (CSV/NPZ files, users' code): fixed.
FIXED = {
    0: "success",
    1: "not_oscillating",
    2: "max_steps",
    3: "singular_mass",
    4: "root_find_failed",
    5: "energy_drift",
    6: "solver_failed",
    7: "nonfinite_input",
    8: "unresolved",
    9: "not_natural",
    10: "escapes",
    11: "nonfinite_period",
    12: "tolerance_not_met",
    13: "coordinate_singularity",
    14: "not_symmetric",
}


def test_int_view_is_fixed():
    assert lagrax.STATUS_CODES == FIXED
    for code, name in FIXED.items():
        member = getattr(lagrax.PeriodStatus, name)
        assert int(lagrax.status_code(member)) == code
        back = lagrax.status_member(code)
        assert isinstance(back, lagrax.PeriodStatus)
        assert bool(back == member)
        assert lagrax.status_message(code) == lagrax.PeriodStatus[member]
    # The old per-module names are the same codes.
    period, quadrature = lagrax._period.period, lagrax._period.quadrature
    assert period.SINGULAR_MASS == quadrature.SINGULAR_MASS == 3
    assert quadrature.EQUILIBRIUM == period.NOT_OSCILLATING


def test_messages():
    assert lagrax.status_message(0) == "success"
    assert "singular" in lagrax.status_message(3)
    assert "reparametrize" in lagrax.status_message(13)
    assert "rtol" in lagrax.status_message(12)
    assert len(set(map(lagrax.status_message, FIXED))) == len(FIXED)
    assert lagrax.status_message(np.int32(5)) == lagrax.status_message(5)
    with pytest.raises(ValueError, match="code"):
        lagrax.status_message(99)


def test_period_error_under_jit_names_the_reason():
    # Released at the equilibrium: the reason, not a generic failure, under jit too.
    # (One compiled program for both: the release is checked before any step.)
    f = eqx.filter_jit(lambda a: lagrax.period(PENDULUM, a, max_steps=3))
    with pytest.raises(Exception, match="does not oscillate"):
        jax.block_until_ready(f(jnp.array(0.0)))
    with pytest.raises(Exception, match="max_steps reached"):
        jax.block_until_ready(f(jnp.array(1.0)))


def test_quadrature_error_under_jit_names_the_first_reason():
    f = jax.jit(lambda a: lagrax.quadrature_period(PENDULUM, a).periods)
    np.testing.assert_allclose(
        f(jnp.array([0.5, 1.0])), pendulum.period(jnp.array([0.5, 1.0]))
    )
    # q0 = 0 is an equilibrium; q0 = 1.0 is fine.
    with pytest.raises(Exception, match="does not oscillate: released at rest"):
        jax.block_until_ready(f(jnp.array([1.0, 0.0])))


def test_quadrature_statuses_are_the_shared_codes():
    res = lagrax.quadrature_period(
        PENDULUM, jnp.array([1.0, 0.0, jnp.pi - 1e-12]), throw=False
    )
    assert list(np.asarray(res.status)) == [0, 1, 8]
    names = [lagrax.STATUS_CODES[int(c)] for c in res.status]
    assert names == ["success", "not_oscillating", "unresolved"]
    assert res.messages()[2] == lagrax.status_message(8)
