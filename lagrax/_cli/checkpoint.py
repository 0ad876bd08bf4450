"""Checkpoints of a sweep, and files written whole or not at all.

`lagrax sweep --out T.npz` keeps each finished block of amplitudes in `T.npz.partial/`
until the whole output is written, so that an interrupted or killed run resumes where
it stopped when the same command is run again.
"""

import json
import os
import re
import tempfile

from .processes import broadcast


BLOCK_CHUNKS = 4  # chunks per device in a checkpoint/progress block


def _umask():
    mask = os.umask(0o022)  # reading the umask means setting it: set it back at once
    os.umask(mask)
    return mask


def atomic_write(path, write):
    """`write(tmp_path)`, then rename over `path`: never a half-written file.

    The file gets the mode any other tool would create it with (0666 less the umask),
    not the 0600 of the temporary file it is renamed from."""
    directory = os.path.dirname(os.path.abspath(path))
    suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=".lagrax-", suffix=suffix)
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~_umask())
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _safe(name):
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


class Blocks:
    """Where each block of amplitudes stands: computed here, or resumed from disk.

    Only process 0 touches the checkpoint directory; it tells the others which blocks
    are done (a broadcast), so that every process skips the same ones.
    """

    def __init__(self, args, targets, devices):
        import jax
        import numpy as np

        self.writer = jax.process_index() == 0
        # A sweep smaller than one chunk per device would mostly run padding.
        self.chunk_size = min(args.chunk_size, -(-args.count // len(devices)))
        self.block = self.chunk_size * len(devices) * BLOCK_CHUNKS
        self.n_blocks = {t.name: -(-args.count // self.block) for t in targets}
        self.dir = None if args.out is None else args.out + ".partial"
        done = []
        if self.dir is not None and self.writer:
            self._prepare(args, targets, devices)
        for t in targets:
            for b in range(self.n_blocks[t.name]):
                done.append(self.dir is not None and self.writer and self.exists(t, b))
        self.done = broadcast(np.array(done, dtype=np.int64)).astype(bool)
        self.resumed = int(self.done.sum())

    def _prepare(self, args, targets, devices):
        import shutil

        # Keyed by everything that changes the numbers: a rerun of the same command
        # resumes; a different one restarts.
        manifest = {
            k: getattr(args, k)
            for k in ("count", "solver", "rtol", "atol", "max_steps")
        }
        manifest["chunk_size"] = self.chunk_size
        manifest["devices"] = len(devices)
        manifest["targets"] = {
            t.name: [list(t.extra["range"]), t.method] for t in targets
        }
        manifest["params"] = args.params
        manifest_path = os.path.join(self.dir, "manifest.json")
        if os.path.isdir(self.dir):
            try:
                with open(manifest_path) as f:
                    same = json.load(f) == json.loads(json.dumps(manifest))
            except (OSError, ValueError):
                same = False
            if not same:
                shutil.rmtree(self.dir)
        if not os.path.isdir(self.dir):
            os.makedirs(self.dir)

            def write(p):
                with open(p, "w") as f:
                    json.dump(manifest, f)

            atomic_write(manifest_path, write)

    def path(self, target, b):
        return os.path.join(self.dir, f"{_safe(target.name)}-{b:05d}.npz")

    def exists(self, target, b):
        return os.path.exists(self.path(target, b))

    def is_done(self, targets, target, b):
        index = 0
        for t in targets:
            if t is target:
                return bool(self.done[index + b])
            index += self.n_blocks[t.name]
        raise KeyError(target.name)
