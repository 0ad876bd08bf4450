"""Each fact of `lagrax._compat` checked against the installed dependencies: these
tests fail when a dependency changes underneath (each also checks that its fact
can come out the other way, so that none passes vacuously)."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

from lagrax import _compat
from lagrax._jaxpr.fusion import ELEMENTAL, elemental_options
from lagrax._trajectory.simulate import elemental


# ------------------------------------------------ the library's calls and their hosts


def test_top_level_is_false_under_every_transformation():
    seen = []

    def f(x):  # (a new function per transformation: none reuses another's trace)
        seen.append(_compat.top_level())
        return x

    assert _compat.top_level()  # (False where JAX's opaque trace state is gone)
    jax.jit(lambda x: f(x))(1.0)
    jax.vmap(lambda x: f(x))(jnp.ones(2))
    jax.grad(lambda x: f(x))(1.0)
    jax.jvp(lambda x: f(x), (1.0,), (1.0,))
    jax.make_jaxpr(lambda x: f(x))(1.0)
    assert seen == [False] * 5
    assert _compat.top_level()


def test_xla_takes_the_elemental_emitters_option():
    # Fails when the installed XLA no longer knows `xla_cpu_use_fusion_emitters`:
    # then every eager CPU program compiles with XLA's default emitters (slower
    # Taylor steps, longer compiles); see `lagrax._jaxpr.fusion`.
    assert _compat.compiles_with(tuple(ELEMENTAL.items()))
    assert elemental_options() == ELEMENTAL


def test_an_option_xla_refuses_is_not_passed():
    refused = {"xla_cpu_no_such_option_in_any_xla": False}
    assert not _compat.compiles_with(tuple(refused.items()))
    assert _compat.accepted_options(refused) == {}
    assert _compat.accepted_options({**refused, **ELEMENTAL}) == {}


def test_an_elemental_call_inside_a_callers_transformation_runs():
    # JAX refuses compile options on a `jit` staged into a caller's `jit` or `grad`
    # (a ValueError); `elemental` then runs the function in the caller's program.
    f = lambda x: jnp.sin(x) * x
    fast = elemental(f)
    df = lambda x: jnp.cos(x) * x + jnp.sin(x)
    np.testing.assert_allclose(fast(0.5), f(0.5), rtol=1e-15)
    np.testing.assert_allclose(jax.jit(fast)(0.5), f(0.5), rtol=1e-15)
    np.testing.assert_allclose(jax.grad(fast)(0.5), df(0.5), rtol=1e-15)
    np.testing.assert_allclose(jax.vmap(fast)(jnp.ones(2)), f(jnp.ones(2)))
    # (The refusal itself, so that the above exercises the fallback.)
    options = jax.jit(f, compiler_options=ELEMENTAL)
    try:
        jax.jit(lambda x: options(x))(0.5)
    except ValueError:
        pass
    else:
        raise AssertionError("JAX took compile options on a nested jit")


_SEEN = []


class _Probe(dfx.AbstractSolver):
    """Euler's method that records what `diffeqsolve` hands it (in `_SEEN`, while
    tracing) and the direction of time (as its solver state)."""

    term_structure = dfx.AbstractTerm
    interpolation_cls = dfx.LocalLinearInterpolation

    def order(self, terms):
        return 1

    def init(self, terms, t0, t1, y0, args):
        inner, direction = _compat.unwrap_time(terms)
        _SEEN.append((terms, inner))
        return jnp.asarray(direction)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        y1 = y0 + terms.vf_prod(t0, y0, args, terms.contr(t0, t1))
        return y1, None, dict(y0=y0, y1=y1), solver_state, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def test_diffeqsolve_hands_solvers_the_term_through_a_time_wrapper():
    # Fails when diffrax's wrapper of terms changes: then `lagrax.Taylor` and the
    # variational integrators refuse every term (they name what they got).
    f = lambda t, y, args: -y
    term = dfx.ODETerm(f)
    saveat = dfx.SaveAt(t1=True, solver_state=True)
    for t1, sign in ((1.0, 1), (-1.0, -1)):
        _SEEN.clear()
        sol = dfx.diffeqsolve(
            term, _Probe(), 0.0, t1, 0.5 * sign, jnp.ones(()), saveat=saveat
        )
        assert _SEEN
        for terms, inner in _SEEN:
            # (Handed a wrapper, not the term: the unwrapping has work to do.)
            assert not isinstance(terms, dfx.ODETerm)
            assert type(inner) is dfx.ODETerm and inner.vector_field is f
        assert int(sol.solver_state) == sign
        np.testing.assert_allclose(sol.ys, 0.5**2 if sign > 0 else 1.5**2)
    assert _compat.unwrap_time(term) == (term, 1)
