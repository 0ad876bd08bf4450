"""What a new user meets first: the diagnosis of common mistakes, readable help."""

import inspect
import pydoc
import types

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


def _unpacked(q, qdot, t):
    a, b = q
    return 0.5 * (qdot[0] ** 2 + qdot[1] ** 2) + jnp.cos(a) + jnp.cos(b)


def _indexed(q, qdot, t):
    return 0.5 * (qdot[0] ** 2 + qdot[1] ** 2) + jnp.cos(q[0]) + jnp.cos(q[1])


def _matrix(q, qdot, t):
    M = jnp.array([[2.0, 0.5], [0.5, 1.0]])
    return 0.5 * qdot @ M @ qdot - 0.5 * q @ q


def _three(q, qdot, t):
    x, y, z = q
    return 0.5 * qdot @ qdot - x * y * z


@pytest.mark.parametrize(
    "L, n", [(_unpacked, 2), (_indexed, 2), (_matrix, 2), (_three, 3)]
)
def test_a_lagrangian_of_more_coordinates_is_named_so(L, n):
    # Whatever way L reads q, the sweep says how many coordinates it has.
    for call in (
        lambda: lagrax.sweep_periods(L, jnp.array([0.5, 1.0])),
        lambda: lagrax.period(L, 0.5),
    ):
        with pytest.raises(ValueError, match=f"it has {n} coordinates") as info:
            call()
        assert "one coordinate, q of shape (1,)" in str(info.value)


def _public(module):
    return {n: getattr(module, n) for n in dir(module) if not n.startswith("_")}


def test_help_prints_short_signatures():
    # Type aliases print by name: no expanded unions of jaxtyping forms in help().
    functions = {n: f for n, f in _public(lagrax).items() if inspect.isfunction(f)}
    assert {"simulate", "period", "accelerations", "energy"} <= set(functions)
    for name, f in functions.items():
        signature = str(inspect.signature(f))
        assert "jaxtyping" not in signature and "Union[" not in signature, name
    text = pydoc.render_doc(lagrax.simulate, renderer=pydoc.plaintext)
    # (Annotations as their source text: diffrax's types by their public names.)
    assert "simulate(L: 'Lagrangian', q0: 'Coordinates', qdot0: 'Coordinates'" in text
    assert "t0: 'RealScalarLike'" in text and "solver: 'dfx.AbstractSolver'" in text


def test_the_package_says_what_it_is_and_shows_only_its_own_names():
    assert "Lagrangian" in lagrax.__doc__ and "sweep_periods" in lagrax.__doc__
    for module in (lagrax, lagrax.systems):
        for name, obj in _public(module).items():
            where = (
                obj.__name__
                if isinstance(obj, types.ModuleType)
                else getattr(obj, "__module__", None) or "lagrax"
            )
            assert where.startswith("lagrax"), (module.__name__, name, where)
