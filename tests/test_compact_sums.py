"""The inner sums of the compact coefficient programs (`lagrax._taylor.compact`):
the window's sums as whole arrays pair their terms as the tree of `_tree_sum`
does, so that the program's numbers do not depend on how it is written."""

import jax
import numpy as np
import pytest

from lagrax._taylor import compact


@pytest.mark.parametrize("n", [1, 3, 4, 6, 7, 12, 20])
def test_tree_sum_of_an_array_pairs_as_the_list_does(n):
    # Terms of mixed magnitudes and signs: another pairing rounds differently.
    rng = np.random.default_rng(n)
    x = rng.standard_normal((n, 3, 5)) * 10.0 ** rng.integers(-8, 9, (n, 1, 1))
    listed = compact._tree_sum([x[i] for i in range(n)])
    whole = compact._tree_sum0(x)
    np.testing.assert_array_equal(np.asarray(whole), np.asarray(listed))
    jitted = jax.jit(compact._tree_sum0)(x)
    np.testing.assert_array_equal(np.asarray(jitted), np.asarray(listed))


def test_window_sums_over_parts_of_the_rows_are_those_of_the_rows():
    rng = np.random.default_rng(0)
    p, q = rng.standard_normal((2, 8, 5, 4))
    plain, weighted = compact._window_sums(p, q)
    parts = compact._window_sums(p, q, slice(0, 3), slice(2, None))
    np.testing.assert_array_equal(np.asarray(parts[0]), np.asarray(plain[:3]))
    np.testing.assert_array_equal(np.asarray(parts[1]), np.asarray(weighted[2:]))
    # The weighted sum weighs the i-th product by i + 1.
    terms = [(i + 1) * p[i] * q[i] for i in range(8)]
    np.testing.assert_allclose(np.asarray(weighted), sum(terms), rtol=1e-12)


def test_operand_sums_are_the_cauchy_sums_of_each_row():
    # Rows sharing operands read them from one history per distinct operand: the
    # sums are each row's own, sum_{0<j<k} (u0 + u1 j / k) P_j Q_{k-j}, for the
    # rows of the chunks in use (the others zero).
    K, H, U, W, C = 7, 12, 5, 3, 4
    rng = np.random.default_rng(1)
    Hu = rng.standard_normal((K, U, W))
    hidx = rng.integers(0, U, (2, H)).astype(np.int32)
    u0, u1 = rng.standard_normal((2, H, W))
    sums = compact._operand_sums(K, C, 2)  # (rows 0..7 in use)
    for k in range(1, K):
        got = np.asarray(jax.jit(sums)(k, Hu, hidx, u0, u1))
        P, Q = Hu[:, hidx[0]], Hu[:, hidx[1]]
        want = sum(((u0 + u1 * j / k) * P[j] * Q[k - j] for j in range(1, k)), 0 * u0)
        np.testing.assert_allclose(got[:8], want[:8], rtol=1e-12, atol=1e-14)
        np.testing.assert_array_equal(got[8:], 0.0)


def test_a_tape_keeps_each_operand_once():
    import jax.numpy as jnp

    import lagrax
    from lagrax._jaxpr.canonical import canonical_lagrangian
    from lagrax._trajectory.batch import _system

    def positions(q, t):
        return jnp.stack([jnp.cumsum(jnp.sin(q)), -jnp.cumsum(jnp.cos(q))], axis=1)

    L = lagrax.particle_lagrangian(
        jnp.ones(3), positions, lambda r, t: 9.81 * jnp.sum(r[:, 1])
    )
    L_c, consts = canonical_lagrangian(L, jnp.float64, 3)
    prog = _system(L_c, consts, None, jnp.zeros(3), jnp.zeros(3)).prog
    tape = compact.build(prog, prog.inputs, prog.params, prog.outs, jnp.float64)
    rows = int(tape.blocks[2])
    hist, hnode, hidx = (np.asarray(x) for x in (tape.hist, tape.hnode, tape.hidx))
    # Every row's operands through the indices, each distinct operand once.
    np.testing.assert_array_equal(hnode[hidx[:, :rows]], hist[:, :rows])
    kept = np.unique(np.concatenate([[0], hist[:, :rows].ravel()]))  # (0: padding)
    np.testing.assert_array_equal(hnode[: kept.size], kept)
    assert kept.size < 2 * rows  # (shared operands: fewer histories than rows)
