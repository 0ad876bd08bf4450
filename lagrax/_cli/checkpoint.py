"""Checkpoints of a sweep, and files written whole or not at all.

`lagrax sweep --out T.npz` keeps each finished block of amplitudes in `T.npz.partial/`
until the whole output is written, so that an interrupted or killed run resumes where
it stopped when the same command is run again.
"""

import hashlib
import io
import json
import os
import re
import sys
import tempfile

from .processes import broadcast


# A checkpoint block: this many times the lanes of every device.
BLOCK_LANE_WIDTHS = 4


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


class DamagedPiece(Exception):
    """A checkpoint piece that cannot be trusted (its message says why)."""


_ARRAYS = ("period", "status", "steps")  # one entry per amplitude of the block


class Blocks:
    """Where each block of amplitudes stands: computed here, or resumed from disk.

    Each finished block is a piece `<system>-<block>.npz` in the checkpoint directory,
    and `manifest.json` there holds the settings that change the numbers and the
    SHA-256 of every piece: a piece is trusted only if its bytes match. Only process 0
    touches the directory; it tells the others which blocks are done (a broadcast), so
    that every process skips the same ones.
    """

    def __init__(self, args, targets, devices):
        import jax
        import numpy as np

        self.writer = jax.process_index() == 0
        # The library's default lanes and size classes: `sweep_periods` with its
        # defaults and `lagrax sweep` share their compiled programs (on disk too).
        from .._checks import lane_count
        from .._period.sweep import CPU_LANES, size_class

        share = -(-size_class(args.count) // len(devices))
        self.lanes = lane_count(
            args.lanes,
            "lanes",
            devices,
            share,
            cpu=CPU_LANES,
            accelerator=1 << 18,
        )
        self.block = self.lanes * len(devices) * BLOCK_LANE_WIDTHS
        self.count = args.count
        self.n_blocks = {t.name: -(-args.count // self.block) for t in targets}
        self.dir = None if args.out is None else args.out + ".partial"
        self.sums = {}  # piece file name -> SHA-256 of its bytes
        done = []
        if self.dir is not None and self.writer:
            self._prepare(args, targets, devices)
        for t in targets:
            for b in range(self.n_blocks[t.name]):
                done.append(self.dir is not None and self.writer and self._usable(t, b))
        self.done = broadcast(np.array(done, dtype=np.int64)).astype(bool)
        self.resumed = int(self.done.sum())

    def _prepare(self, args, targets, devices):
        import shutil

        # Keyed by everything that changes the numbers: a rerun of the same command
        # resumes; a different one restarts.
        settings = {
            k: getattr(args, k)
            for k in ("count", "solver", "rtol", "atol", "max_steps")
        }
        settings["lanes"] = self.lanes
        settings["devices"] = len(devices)
        settings["targets"] = {
            t.name: [list(t.extra["range"]), t.method] for t in targets
        }
        settings["params"] = args.params
        self.settings = json.loads(json.dumps(settings))
        if os.path.isdir(self.dir):
            try:
                with open(self._manifest()) as f:
                    manifest = json.load(f)
                same = manifest["settings"] == self.settings
                sums = {str(k): str(v) for k, v in manifest["pieces"].items()}
            except (OSError, ValueError, KeyError, TypeError, AttributeError):
                same = False
            if same:
                self.sums = sums
            else:
                shutil.rmtree(self.dir)
        if not os.path.isdir(self.dir):
            os.makedirs(self.dir)
            self._write_manifest()

    def _manifest(self):
        return os.path.join(self.dir, "manifest.json")

    def _write_manifest(self):
        def write(p):
            with open(p, "w") as f:
                json.dump({"settings": self.settings, "pieces": self.sums}, f)

        atomic_write(self._manifest(), write)

    def path(self, target, b):
        return os.path.join(self.dir, f"{_safe(target.name)}-{b:05d}.npz")

    def save(self, target, b, part):
        """Writes a finished block, then its checksum into the manifest (killed in
        between, the piece has no checksum and is computed again)."""
        import numpy as np

        path = self.path(target, b)
        digest = []

        def write(p):
            np.savez(p, **part)
            with open(p, "rb") as f:
                digest.append(hashlib.sha256(f.read()).hexdigest())

        atomic_write(path, write)
        self.sums[os.path.basename(path)] = digest[0]
        self._write_manifest()

    def load(self, target, b):
        """The arrays of block `b`, or None if it was not written; `DamagedPiece` if
        its bytes do not match the manifest's checksum or do not hold the block."""
        import numpy as np

        path = self.path(target, b)
        name = os.path.basename(path)
        if name not in self.sums:
            return None
        try:
            with open(path, "rb") as f:
                data = f.read()
        except OSError as e:
            raise DamagedPiece(e.strerror or "unreadable") from None
        if hashlib.sha256(data).hexdigest() != self.sums[name]:
            raise DamagedPiece("its bytes do not match the manifest's checksum")
        try:
            with np.load(io.BytesIO(data)) as f:
                part = {k: f[k] for k in f.files}
        except Exception:  # noqa: BLE001 - any way a file fails to be an .npz
            raise DamagedPiece("not a readable .npz") from None
        n = min(self.block, self.count - b * self.block)
        if not all(part.get(k, np.empty(0)).shape == (n,) for k in _ARRAYS):
            raise DamagedPiece(f"it does not hold the {n} amplitudes of its block")
        return part

    def _usable(self, target, b):
        try:
            return self.load(target, b) is not None
        except DamagedPiece as e:
            path = self.path(target, b)
            print(
                f"lagrax: warning: checkpoint {path} is damaged ({e}); computing it "
                "again",
                file=sys.stderr,
            )
            del self.sums[os.path.basename(path)]
            if os.path.exists(path):
                os.remove(path)
            return False

    def is_done(self, targets, target, b):
        index = 0
        for t in targets:
            if t is target:
                return bool(self.done[index + b])
            index += self.n_blocks[t.name]
        raise KeyError(target.name)
