r"""The Taylor recurrence of the mass-matrix solve $M\ddot q = f$, for any $n$.

With $M(t)$, $f(t)$ and $x(t) = \ddot q(t)$ series, $\sum_{j=0}^k M_j x_{k-j} = f_k$,

$$M_0\, x_k = f_k - \sum_{j=1}^{k} M_j\, x_{k-j},$$

so every order solves with the same $M_0$: one Cholesky factorization per step (at
order 0) and two triangular substitutions per order, $O(n^2)$, after the Cauchy sums
$\sum_j M_j x_{k-j}$, $O(k n^2)$. For $n \le 2$ the accelerations are a closed form of
the entries and need none of this.

`lagrax.accelerations` marks its solve for $n \ge 3$ as a call of
`definite_solve` (`jax.jit` of the array solve, named); the Taylor program's builder
(`lagrax._taylor.system`) evaluates the rest of the equations entry by entry and turns
each marked call into one `definite_solve_p` node on the entries of $M$ and $f$,
whose coefficients come from `solve_rule`.
"""

import functools

import jax
import jax.numpy as jnp
from jax.extend import core as jex_core


# The name of the marked call in a jaxpr (`pjit` equations carry their function's).
MARK = "lagrax_definite_solve"


def definite_solve(M, rhs):
    """`(x, ok)` with `M x = rhs` (see `_eom.mechanics._solve_definite`), as a named
    call that the Taylor program recognizes."""
    return _marked(M, rhs)


def _solve_array(M, rhs):
    from .._eom.mechanics import _solve_definite

    return _solve_definite(M, rhs)


_solve_array.__name__ = MARK
_marked = jax.jit(_solve_array)


# A primitive on the scalar entries: n*n entries of M (row-major), n of rhs -> the n
# entries of x and ok. Only traced (its abstract evaluation) and read by the Taylor
# program; `entries_solve` evaluates it.
definite_solve_p = jex_core.Primitive("lagrax_definite_solve")
definite_solve_p.multiple_results = True


@definite_solve_p.def_abstract_eval
def _abstract(*args, n):
    aval = jax.core.ShapedArray((), args[0].dtype)
    return [aval] * n + [jax.core.ShapedArray((), jnp.bool_)]


def _cholesky(A, n):
    """The lower Cholesky factor of `A` (entries `A[a][b]`, arrays of one shape) and
    the reciprocals of its diagonal, entry by entry (fused by XLA, no library call)."""
    Lf = [[None] * n for _ in range(n)]
    inv = [None] * n
    for j in range(n):
        d = A[j][j]
        for k in range(j):
            d = d - Lf[j][k] * Lf[j][k]
        d = jnp.sqrt(d)  # NaN where A is not positive definite
        Lf[j][j] = d
        inv[j] = 1.0 / d
        for i in range(j + 1, n):
            s = A[i][j]
            for k in range(j):
                s = s - Lf[i][k] * Lf[j][k]
            Lf[i][j] = s * inv[j]
    return Lf, inv


def _substitute(Lf, inv, rhs, n):
    """`x` with `L L^T x = rhs`, entries as lists."""
    z = [None] * n
    for a in range(n):
        s = rhs[a]
        for b in range(a):
            s = s - Lf[a][b] * z[b]
        z[a] = s * inv[a]
    x = [None] * n
    for a in reversed(range(n)):
        s = z[a]
        for b in range(a + 1, n):
            s = s - Lf[b][a] * x[b]
        x[a] = s * inv[a]
    return x


def factor(M, n):
    r"""The factorization of $\sigma M$ (symmetrized, $\sigma$ the sign of $M_{00}$)
    and `ok`, as `_solve_definite` decides it: definite, finite, and
    $\min_j L_{jj}^2 > n\varepsilon \max_j L_{jj}^2$."""
    one = jnp.ones_like(M[0][0])
    sign = jnp.where(M[0][0] < 0, -one, one)
    A = [[sign * 0.5 * (M[a][b] + M[b][a]) for b in range(n)] for a in range(n)]
    Lf, inv = _cholesky(A, n)
    diag = [Lf[j][j] for j in range(n)]
    eps = jnp.finfo(M[0][0].dtype).eps
    d2 = [d * d for d in diag]
    ok = functools.reduce(jnp.logical_and, [jnp.isfinite(d) for d in diag])
    ok = ok & (
        functools.reduce(jnp.minimum, d2) > n * eps * functools.reduce(jnp.maximum, d2)
    )
    for row in M:
        for m in row:
            ok = ok & jnp.isfinite(m)
    return sign, Lf, inv, ok


def entries_solve(Ms, rs, n):
    """The marked solve on entries: `Ms` the n*n entries of M (row-major), `rs` those
    of rhs -> (x entries, ok)."""
    M = [list(Ms[a * n : (a + 1) * n]) for a in range(n)]
    sign, Lf, inv, ok = factor(M, n)
    x = _substitute(Lf, inv, [sign * r for r in rs], n)
    return x, ok


def solve_rule(st, node):
    r"""$x_k$ from $M_0 x_k = f_k - \sum_{j \ge 1} M_j x_{k-j}$, the factorization of
    $\sigma M_0$ computed once per step (`st.zero.once`)."""
    n = node.params["n"]
    zero = st.zero
    series = zero.prog.series
    M_ids, r_ids = node.ins[: n * n], node.ins[n * n :]
    x_ids = node.outs[:n]

    def factorize():
        M = [[zero.lanes(M_ids[a * n + b]) for b in range(n)] for a in range(n)]
        sign, Lf, inv, _ = factor(M, n)
        return sign, Lf, inv

    sign, Lf, inv = zero.once((node.outs[0], "factor"), factorize)
    s = []
    for a in range(n):
        acc = st.get(r_ids[a]) if r_ids[a] in series else None
        for b in range(n):
            m = M_ids[a * n + b]
            if m in series:
                term = st.conv(m, x_ids[b])
                acc = -term if acc is None else acc - term
        s.append(jnp.zeros_like(sign) if acc is None else acc)
    x = _substitute(Lf, inv, [sign * v for v in s], n)
    return x  # (and no coefficients for `ok`, decided at order 0)
