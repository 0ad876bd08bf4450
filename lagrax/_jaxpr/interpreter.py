r"""One jaxpr interpreter for lagrax's transforms of user functions.

The vectorized sines (`trig.py`), the scalarizer (`scalarize.py`), the Taylor program
builder (`lagrax/_taylor/program.py`) and the index checks (`lagrax/_checks.py`) each
walk a jaxpr equation by equation. Here is what they share: the environment from
variables to values, and the descent into call-like primitives (`jax.jit` inside a
function, `jax.checkpoint`, custom derivatives), whose bodies are evaluated inline so
that each user sees only primitives. Each user supplies its rule for one equation.
"""

import functools
from collections.abc import Callable, Iterator

import jax
from jax.extend import core as jex_core


# Call-like primitives: name -> the parameter holding the body. Inlining a body gives
# the same values as binding the call.
CALLS = {
    "pjit": "jaxpr",
    "jit": "jaxpr",
    "closed_call": "call_jaxpr",
    "core_call": "call_jaxpr",
    "remat": "jaxpr",
    "checkpoint": "jaxpr",
}

# Calls with a custom derivative: inlining their primal body gives the same values
# but drops the custom rule from any derivative taken through the result, so only
# users that never differentiate their output ask for them (`custom=True`).
CUSTOM_DERIVATIVE_CALLS = {
    "custom_jvp_call": "call_jaxpr",
    "custom_vjp_call": "call_jaxpr",
    "custom_vjp_call_jaxpr": "fun_jaxpr",
}


@functools.cache
def mul_params() -> dict:
    """`lax.mul_p`'s parameters as JAX itself binds them (`out_dtype` in recent
    versions): a `mul` bound with fewer runs forward but fails under `jax.grad`,
    whose transpose rule requires them."""
    return dict(jax.make_jaxpr(jax.lax.mul)(1.0, 1.0).eqns[0].params)


def body(eqn, custom: bool = False):
    """`(jaxpr, consts)` of the body of a call-like equation, or None for any other
    equation (`custom`: custom-derivative calls count as calls)."""
    name = eqn.primitive.name
    key = CALLS.get(name)
    if key is None and custom:
        key = CUSTOM_DERIVATIVE_CALLS.get(name)
    sub = None if key is None else eqn.params.get(key)
    if sub is None:
        return None
    if isinstance(sub, jex_core.ClosedJaxpr):
        return sub.jaxpr, sub.consts
    return sub, ()


def supported_calls(custom: bool = False) -> list:
    """The names of the primitives `evaluate` inlines."""
    return sorted({**CALLS, **CUSTOM_DERIVATIVE_CALLS} if custom else CALLS)


def _identity(value, aval):
    return value


def evaluate(
    jaxpr,
    consts,
    args,
    rule: Callable,
    *,
    const: Callable = _identity,
    custom: bool = False,
) -> list:
    """The outputs of `jaxpr` at `args`, call-like equations inlined.

    **Arguments:**

    - `jaxpr`, `consts`, `args`: an open jaxpr, values for its constvars and invars.
    - `rule`: `rule(eqn, ins) -> outs`, the values of the outputs (a list) of an
        equation that is not a call, from the values of its inputs.
    - `const`: `const(value, aval)`, the value standing for a constvar's value or a
        literal's.
    - `custom`: inline the custom-derivative calls too.
    """
    env = {}

    def read(var):
        if isinstance(var, jex_core.Literal):
            return const(var.val, var.aval)
        return env[var]

    for var, c in zip(jaxpr.constvars, consts):
        env[var] = const(c, var.aval)
    for var, a in zip(jaxpr.invars, args):
        env[var] = a
    for eqn in jaxpr.eqns:
        ins = [read(var) for var in eqn.invars]
        sub = body(eqn, custom)
        if sub is None:
            outs = rule(eqn, ins)
        else:
            sub_jaxpr, sub_consts = sub
            # (The body's inputs are the call's last operands.)
            ins = ins[len(ins) - len(sub_jaxpr.invars) :]
            outs = evaluate(
                sub_jaxpr, sub_consts, ins, rule, const=const, custom=custom
            )
        for var, out in zip(eqn.outvars, outs):
            env[var] = out
    return [read(var) for var in jaxpr.outvars]


def equations(jaxpr, custom: bool = False) -> Iterator:
    """Every equation of `jaxpr` that `evaluate` hands to its rule, in order."""
    for eqn in jaxpr.eqns:
        sub = body(eqn, custom)
        if sub is None:
            yield eqn
        else:
            yield from equations(sub[0], custom)


def bind(eqn, ins) -> list:
    """The equation's primitive applied to `ins` as the jaxpr applies it: a list of
    outputs."""
    prim = eqn.primitive
    with eqn.ctx.manager:
        outs = prim.bind(*ins, **prim.get_bind_params(eqn.params))
    return list(outs) if prim.multiple_results else [outs]
