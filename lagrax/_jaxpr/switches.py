r"""Whether a function switches branch with its inputs (`jnp.where` on a comparison,
`abs`, `max`, `floor`, ...): where it does, a Taylor step, whose coefficients follow
the branches taken at the step's start, must check the step's end.

A forward pass over the jaxpr marks every value that depends on the marked inputs;
a switch is a primitive below whose output jumps or kinks as such a value varies.
Traced once, nothing is evaluated. `is_finite` is not a switch: it changes only
where the value stops being finite, which a step sees anyway.
"""

import jax
import numpy as np

from . import interpreter


# Primitives whose output jumps or kinks as a floating-point input varies (the
# boolean ones they feed, `and`, `select_n`'s predicate, ..., only pass it on).
_SWITCHES = frozenset(
    "eq ne lt le gt ge sign floor ceil round nextafter argmax argmin "
    "max min reduce_max reduce_min abs clamp rem sort".split()
    # control flow on a marked value (the interpreter inlines calls only)
    + ["cond", "while"]
)


def _switch(eqn, marked) -> bool:
    name = eqn.primitive.name
    if name in _SWITCHES:
        return any(marked)
    if name == "convert_element_type":  # a float truncated to an integer or bool
        src = eqn.invars[0].aval.dtype
        dst = eqn.params["new_dtype"]
        floating = np.issubdtype(src, np.floating)
        return marked[0] and floating and not np.issubdtype(dst, np.floating)
    return False


def switches(fn, marked_args, other_args=()) -> bool:
    """Whether `fn(*marked_args, *other_args)` has a switch in a value that depends on
    `marked_args` (arrays or shape-dtype specs)."""
    spec = lambda x: jax.ShapeDtypeStruct(jax.numpy.shape(x), jax.numpy.result_type(x))
    marked_args, other_args = jax.tree.map(spec, (marked_args, other_args))
    closed = jax.make_jaxpr(fn)(*marked_args, *other_args)
    n_marked = len(jax.tree.leaves(marked_args))
    found = []

    def rule(eqn, ins):
        if _switch(eqn, ins):
            found.append(eqn.primitive.name)
        return [any(ins)] * len(eqn.outvars)

    flags = [i < n_marked for i in range(len(closed.jaxpr.invars))]
    interpreter.evaluate(
        closed.jaxpr,
        closed.consts,
        flags,
        rule,
        const=lambda value, aval: False,
        custom=True,
    )
    return bool(found)
