"""Compiles one exported program and writes its serialized executable: run as a
script by `lagrax._cache.apart` (in a process of its own, with an XLA thread pool of
one thread), never imported. Imports JAX only, not lagrax, so that it starts fast.

stdin: a pickle of `(exported program, compile options)`, the program serialized by
`jax.export`; stdout: a pickle of the executable's bytes
(`jax.experimental.serialize_executable`). Its environment says the rest (the 64-bit
mode as the parent's, no persistent compilation cache, the CPU)."""

import pickle
import sys


def main():
    import jax
    from jax.experimental import serialize_executable

    blob, options = pickle.loads(sys.stdin.buffer.read())
    exported = jax.export.deserialize(blob)
    args, kwargs = jax.tree.unflatten(exported.in_tree, exported.in_avals)
    lowered = jax.jit(exported.call, compiler_options=options).lower(*args, **kwargs)
    payload = serialize_executable.serialize(lowered.compile())[0]
    sys.stdout.buffer.write(pickle.dumps(payload))


if __name__ == "__main__":
    main()
