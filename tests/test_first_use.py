"""What a new user meets first: the diagnosis of common mistakes, readable help."""

import jax
import jax.numpy as jnp
import pytest

import lagrax


PENDULUM = lagrax.systems.pendulum.lagrangian()


def test_float32_is_named_with_the_line_that_enables_float64():
    # Without JAX's 64-bit mode the release points are float32, which cannot resolve
    # the default rtol: the error says so (not a separatrix, not a solver failure).
    with jax.enable_x64(False):
        q0 = jnp.linspace(0.1, 3.0, 8)
        assert q0.dtype == jnp.float32
        for call in (
            lambda: lagrax.sweep_periods(PENDULUM, q0),
            lambda: lagrax.period(PENDULUM, 1.0),
        ):
            with pytest.raises(ValueError, match="float32") as info:
                call()
            assert 'jax.config.update("jax_enable_x64", True)' in str(info.value)
            assert "separatrix" not in str(info.value)
