"""The examples in the public docstrings run, and the values their comments claim hold.

Every ```python block in the docstring of a public object (of `lagrax`, its classes'
methods, `lagrax.systems` and its modules) runs with `lagrax`, `jax` and `jnp` in
scope, statement by statement. A comment at the end of an expression statement is a
claim about its value: a Python expression (`# -sin(0.5)`, `# [[4.0]]`, with `sin`,
`cos`, `sqrt`, `pi` and the block's names available), up to the first top-level `,`,
`;` or ` (` that ends a valid expression, compared to 1e-12 relative (or to the
tolerance a later "to 1e-9" gives, "to ~1e-9" for its order of magnitude); or a decimal
with `...` (`# 6.69997...`: the value agrees to the digits shown). Comments elsewhere
are prose.
"""

import ast
import inspect
import io
import re
import textwrap
import tokenize
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax


def _public(module):
    for name in dir(module):
        if name.startswith("_"):
            continue
        obj = getattr(module, name)
        if isinstance(obj, types.ModuleType):
            continue
        yield f"{module.__name__}.{name}", obj
        if inspect.isclass(obj):
            for attr, value in vars(obj).items():
                if not attr.startswith("_"):
                    yield f"{module.__name__}.{name}.{attr}", value


def _examples():
    modules = [lagrax, lagrax.systems, *lagrax.systems.SYSTEMS.values()]
    seen, out = set(), []
    for name, obj in [(m.__name__, m) for m in modules] + [
        item for m in modules for item in _public(m)
    ]:
        doc = getattr(obj, "__doc__", None)
        if not isinstance(doc, str) or doc in seen:
            continue
        seen.add(doc)
        blocks = re.findall(r"```python\n(.*?)```", doc, re.S)
        for i, block in enumerate(blocks):
            out.append((f"{name}[{i}]" if len(blocks) > 1 else name, block))
    return out


EXAMPLES = _examples()
_CLAIM_NAMES = {"sin": np.sin, "cos": np.cos, "sqrt": np.sqrt, "pi": np.pi}
_TRUNCATED = re.compile(r"^(-?\d+\.(\d+))\.\.\.")


def _claim(comment, namespace):
    """The claimed value of a comment, and the tolerance of the comparison: `(value,
    ("digits", d))` for a truncated decimal, else `(value, ("rtol", r))`."""
    m = _TRUNCATED.match(comment)
    if m:
        return float(m.group(1)), ("digits", 10.0 ** -len(m.group(2)))
    cuts = [m.start() for m in re.finditer(r",|;| \(", comment)] + [len(comment)]
    for cut in cuts:  # the shortest prefix that is an expression
        try:
            tree = ast.parse(comment[:cut].strip(), mode="eval")
        except SyntaxError:
            continue
        value = eval(compile(tree, "<claim>", "eval"), {**namespace, **_CLAIM_NAMES})
        # "to 1e-9": that relative tolerance; "to ~1e-9": its order of magnitude.
        tol = re.search(r"\bto (~?)(\d(?:\.\d+)?e-\d+)", comment[cut:])
        rtol = 1e-12 if tol is None else float(tol[2]) * (10 if tol[1] else 1)
        return value, ("rtol", rtol)
    raise AssertionError(
        f"a comment on an expression is not a checkable value: {comment}"
    )


def test_the_public_examples_are_found():
    names = {name.split("[")[0].rsplit(".", 1)[-1] for name, _ in EXAMPLES}
    assert {"period", "sweep_periods", "simulate", "accelerations"} <= names
    # The recipe for parameter scans and gradients of a sweep.
    sweeps = [code for name, code in EXAMPLES if "sweep_periods" in name]
    assert any("for g in" in code and "jax.grad(" in code for code in sweeps)


def _marks(code):
    # A batch through the period kernel or simulate_batch's Taylor loop compiles for
    # 10-90 s of CPU: slow. The rebuilt-L and gradient paths the recipe shows and the
    # batched trajectories are tested in the default run (tests/test_canonical.py,
    # tests/test_gradients.py, tests/test_simulate_batch.py).
    slow = ("sweep_periods(", "simulate_batch(")
    return [pytest.mark.slow] if any(s in code for s in slow) else []


@pytest.mark.parametrize(
    "code", [pytest.param(c, marks=_marks(c), id=n) for n, c in EXAMPLES]
)
def test_docstring_example(code):
    code = textwrap.dedent(code)
    comments = {
        tok.start[0]: tok.string[1:].strip()
        for tok in tokenize.generate_tokens(io.StringIO(code).readline)
        if tok.type == tokenize.COMMENT
    }
    namespace = {"lagrax": lagrax, "jax": jax, "jnp": jnp}
    for stmt in ast.parse(code).body:
        comment = comments.get(stmt.end_lineno)
        if isinstance(stmt, ast.Expr) and comment:
            value = eval(
                compile(ast.Expression(stmt.value), "<example>", "eval"), namespace
            )
            claimed, (kind, tol) = _claim(comment, namespace)
            if kind == "digits":
                assert abs(float(value) - claimed) < tol, (comment, value)
            elif isinstance(claimed, (str, bool)):
                assert value == claimed, (comment, value)
            else:
                np.testing.assert_allclose(
                    np.asarray(value), np.asarray(claimed), rtol=tol, atol=0,
                    err_msg=comment,
                )  # fmt: skip
        else:
            exec(compile(ast.Module([stmt], []), "<example>", "exec"), namespace)
    jax.block_until_ready([v for v in namespace.values() if isinstance(v, jax.Array)])
