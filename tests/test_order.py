"""`lagrax.Taylor(order=None)` (its default): `simulate_batch` takes the order its
docstring gives for the tolerance; an order given is kept."""

import dataclasses

import diffrax as dfx
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax._trajectory import batch


# The docstring's table: 12 down to 1e-9, 14 to 1e-11, 16 to 1e-13, 18 at 1e-14,
# 20 from 1e-15 on and where the tolerances are traced.
DOCUMENTED = [
    (1e-4, 12), (1e-8, 12), (1e-9, 12), (1e-10, 14), (1e-11, 14), (1e-12, 16),
    (1e-13, 16), (1e-14, 18), (1e-15, 20), (1e-16, 20),
]  # fmt: skip


@pytest.mark.parametrize("tol, order", DOCUMENTED)
def test_chosen_order_follows_the_documented_rule(tol, order):
    rtol = atol = np.full((3,), tol)
    assert batch._order(lagrax.Taylor(), rtol, atol) == order


def test_the_tightest_release_and_the_looser_of_rtol_atol_decide():
    T = lagrax.Taylor()
    # Per release max(rtol, atol): 1e-8, 1e-12; the tightest, 1e-12, decides.
    rtol, atol = np.array([1e-8, 1e-12]), np.array([1e-16, 1e-16])
    assert batch._order(T, rtol, atol) == 16
    # A loose atol with a tight rtol: max(1e-12, 1e-8) = 1e-8.
    assert batch._order(T, np.array([1e-12]), np.array([1e-8])) == 12


def test_an_order_given_is_kept():
    tight, loose = np.array([1e-16]), np.array([1e-8])
    assert batch._order(lagrax.Taylor(order=20), loose, loose) == 20
    assert batch._order(lagrax.Taylor(order=7), tight, tight) == 7
    # Elsewhere (the period kernel, the diffrax solver) no order means 20, and
    # `Taylor()` equals itself rebuilt from its fields.
    T = lagrax.Taylor()
    assert T.order == 20 and T == lagrax.Taylor(order=None)
    assert T == lagrax.Taylor(order=T.order, max_step=T.max_step)
    assert batch._order(lagrax.Taylor(order=T.order), loose, loose) == 12
    # ... and so does `simulate_batch`'s copy without its fallback.
    plain = dataclasses.replace(lagrax.Taylor(fallback=dfx.Dopri8()), fallback=None)
    assert batch._order(plain, loose, loose) == 12


def test_simulate_batch_steps_at_the_chosen_order():
    def L(q, qdot, t):
        return 0.5 * qdot[0] ** 2 + jnp.cos(q[0])

    q0 = jnp.linspace(0.5, 2.5, 4)[:, None]
    run = lambda solver: lagrax.simulate_batch(
        L, q0, jnp.zeros_like(q0), 0.0, 5.0, solver=solver, rtol=1e-9, atol=1e-9
    )
    chosen, twelve = run(None), run(lagrax.Taylor(order=12))
    np.testing.assert_array_equal(chosen.ys[0], twelve.ys[0])
    np.testing.assert_array_equal(chosen.stats["num_steps"], twelve.stats["num_steps"])
    twenty = run(lagrax.Taylor(order=20))
    assert np.all(twenty.stats["num_steps"] < chosen.stats["num_steps"])


def test_the_default_has_a_pre_key():
    # The disk cache keys programs by a faithful text of their static arguments
    # (a sweep's default solver among them): no order, no text, no reuse.
    from lagrax._cache import faithful

    T = lagrax.Taylor()
    assert faithful.text(T) != faithful.text(lagrax.Taylor(order=20))
    assert faithful.text(T) == faithful.text(lagrax.Taylor(order=T.order))
