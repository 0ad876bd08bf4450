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
