"""The disk cache's folder: where it is, whether it can be trusted, and its entries.

An entry is native code and pickled data that the process loads and runs, so the
folder is treated as ssh treats its keys: it is created readable and writable by its
owner only (0700), and one that another user owns, or that group or others can write
(or whose parent anyone can write, without the sticky bit), is refused with a warning
naming the path and the fix; nothing is then read from it or written to it. Each entry
is written whole (a temporary file renamed), by its owner for its owner (0600), with a
header recording its size, a SHA-256 digest of its contents and what it holds; it is
checked against all of them before it is read (`read`), so that a damaged or truncated
entry is compiled again instead of loaded.

`lagrax cache info` and `lagrax cache clear` show and empty the folder.
"""

import hashlib
import json
import os
import stat
import tempfile
import warnings


# The most the folder holds (bytes); past it the least recently used entries go.
MAX_BYTES = 1 << 30
# Every entry starts with this line, then a line of JSON (the header), then its data.
_MAGIC = b"lagrax cache entry 1\n"
# What the folder holds: executables, links from pre-keys, remembered answers, and
# temporary files of a write in progress (or one interrupted).
SUFFIXES = (".bin", ".key", ".tmp")


def location() -> str | None:
    """Where the cache is kept: `$LAGRAX_CACHE_DIR` (empty: off), else
    `$XDG_CACHE_HOME/lagrax/executables` (default `~/.cache/...`)."""
    env = os.environ.get("LAGRAX_CACHE_DIR")
    if env is not None:
        return env or None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")
    return os.path.join(base, "lagrax", "executables")


_WARNED: set = set()


def folder() -> str | None:
    """The cache folder (created at the first write, `write`); None where the cache
    is off, or the folder exists and cannot be trusted (warned once)."""
    path = location()
    if path is None:
        return None
    try:
        reason = untrusted(path) if os.path.lexists(path) else None
    except OSError as e:
        reason = f"cannot be read ({e.strerror})"
    if reason is None:
        return path
    if path not in _WARNED:
        _WARNED.add(path)
        warnings.warn(
            f"lagrax: the cache folder {path} {reason}; nothing is loaded from it or "
            f"written to it. Fix: `chmod 700 {path}` if it is yours, or set "
            "LAGRAX_CACHE_DIR to a folder of your own (LAGRAX_CACHE_DIR= turns the "
            "cache off).",
            RuntimeWarning,
            stacklevel=3,
        )
    return None


def untrusted(path) -> str | None:
    """Why the folder `path` cannot be trusted (read as a sentence's predicate), or
    None where only its owner, this user, can write it."""
    if not hasattr(os, "getuid"):  # (no owners to check: not a POSIX system)
        return None
    real = os.path.realpath(path)
    st = os.stat(real)
    if not stat.S_ISDIR(st.st_mode):
        return "is not a folder"
    if st.st_uid != os.getuid():
        return f"is owned by another user (uid {st.st_uid})"
    if st.st_mode & 0o022:
        return f"can be written by group or others (mode {st.st_mode & 0o777:o})"
    parent = os.path.dirname(real)
    pst = os.stat(parent)
    if pst.st_mode & 0o002 and not pst.st_mode & stat.S_ISVTX:
        return f"is in {parent}, which anyone can write"
    return None


def write(path, data: bytes, record: dict | None = None) -> bool:
    """Writes an entry: `data` with a header holding `record`, its size and digest,
    whole or not at all. False where it cannot (a read-only or full disk)."""
    header = dict(record or {})
    header.update(size=len(data), sha256=hashlib.sha256(data).hexdigest())
    blob = _MAGIC + json.dumps(header, sort_keys=True).encode() + b"\n" + data
    where = os.path.dirname(path)
    try:
        if not os.path.isdir(where):
            os.makedirs(where, mode=0o700, exist_ok=True)
            os.chmod(where, 0o700)  # (whatever the umask)
        if untrusted(where) is not None:
            return False
        fd, tmp = tempfile.mkstemp(dir=where, suffix=".tmp")  # (mode 0600)
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
        os.replace(tmp, path)
        return True
    except OSError:
        return False


def read(path) -> tuple[dict, bytes] | None:
    """`(record, data)` of the entry at `path`, or None where there is none or it
    fails a check: not a regular file of this user's that only they can write,
    larger than the folder may hold, or a header that does not match its data (a
    damaged or truncated entry). Marks it recently used."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    except OSError:
        return None
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode) or st.st_size > MAX_BYTES:
            return None
        if hasattr(os, "getuid") and (st.st_uid != os.getuid() or st.st_mode & 0o022):
            return None
        blob = fh.read()
    if not blob.startswith(_MAGIC):
        return None
    line, sep, data = blob[len(_MAGIC) :].partition(b"\n")
    try:
        header = json.loads(line)
    except ValueError:
        return None
    if not (sep and isinstance(header, dict)) or header.get("size") != len(data):
        return None
    if header.get("sha256") != hashlib.sha256(data).hexdigest():
        return None
    try:
        os.utime(path)  # (recently used: kept longest)
    except OSError:
        pass
    return header, data


def remove(path):
    try:
        os.remove(path)
    except OSError:  # (gone already)
        pass


def entries(path):
    """`(mtime, size, path)` of every file of the cache in the folder `path`."""
    found = []
    try:
        scan = list(os.scandir(path))
    except OSError:
        return found
    for e in scan:
        if e.name.endswith(SUFFIXES) and e.is_file(follow_symlinks=False):
            try:
                st = e.stat(follow_symlinks=False)
            except OSError:
                continue
            found.append((st.st_mtime, st.st_size, e.path))
    return found


def evict(path, limit=None):
    """Removes the least recently used entries until the folder `path` holds at most
    `limit` (default `MAX_BYTES`) bytes."""
    limit = MAX_BYTES if limit is None else limit
    found = entries(path)
    total = sum(size for _, size, _ in found)
    for _, size, name in sorted(found):
        if total <= limit:
            break
        remove(name)
        total -= size


def info() -> dict:
    """The cache's state: `folder`, `state` ("on", "off", or why it is refused),
    `entries` (files), `bytes` and `max_bytes`."""
    path = location()
    out = {"folder": path, "entries": 0, "bytes": 0, "max_bytes": MAX_BYTES}
    if path is None:
        return {**out, "state": "off (LAGRAX_CACHE_DIR is empty)"}
    if not os.path.isdir(path):
        return {**out, "state": "on (empty: the folder is created at first use)"}
    reason = untrusted(path)
    found = entries(path)
    out.update(entries=len(found), bytes=sum(size for _, size, _ in found))
    return {**out, "state": "on" if reason is None else f"refused: the folder {reason}"}


def clear() -> tuple[int, int]:
    """Removes every file of the cache from its folder: `(files, bytes)` removed."""
    path = location()
    if path is None or not os.path.isdir(path):
        return 0, 0
    found = entries(path)
    for _, _, name in found:
        remove(name)
    return len(found), sum(size for _, size, _ in found)
