"""Key files (spec section 5): load one safely, make one (``estop keygen``).

A key file holds 64 hex digits and an optional final newline, nothing else. It must be a
regular file that neither group nor others may read or write: :func:`load_key_file` refuses
anything else with a one-line :class:`KeyFileError`. :func:`write_key_file` creates a fresh
file with mode 0600 from the first moment (``O_CREAT | O_EXCL``: it never overwrites and
never follows a link left in its place; the umask can only narrow the mode).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import stat

from estop.protocol.auth import KEY_SIZE, KeyTextError, check_key, format_key, parse_key

__all__ = ["KeyFileError", "load_key_file", "new_key", "write_key_file"]

_MAX_READ = 4096  # a key file is 64 or 65 bytes; read a little more to say "too long"
_GROUP_OTHER_RW = stat.S_IRGRP | stat.S_IWGRP | stat.S_IROTH | stat.S_IWOTH

class KeyFileError(ValueError):
    """A key file that cannot be used or made. ``str()`` is one line naming the file."""


def new_key() -> bytes:
    """32 bytes from the operating system's cryptographic random source."""
    return secrets.token_bytes(KEY_SIZE)


def load_key_file(path: str | os.PathLike[str]) -> bytes:
    """The key in ``path``. Raises :class:`KeyFileError` (one line) when the file is missing
    or unreadable, not a regular file, readable or writable by group or others, or not
    exactly 64 hex digits with an optional final newline."""
    name = os.fspath(path)
    try:
        # O_NONBLOCK: a FIFO put in its place must not hang us (it is refused below)
        fd = os.open(name, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise KeyFileError(f"key file {name}: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise KeyFileError(f"key file {name}: not a regular file")
        mode = stat.S_IMODE(st.st_mode)
        if mode & _GROUP_OTHER_RW:
            raise KeyFileError(f"key file {name}: group or others may read or write it "
                               f"(mode {mode:04o}); chmod 600 {name}")
        chunks = []
        total = 0
        while total <= _MAX_READ:
            chunk = os.read(fd, _MAX_READ)
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    except OSError as exc:
        raise KeyFileError(f"key file {name}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    text = b"".join(chunks)
    if len(text) > 4 * KEY_SIZE:
        raise KeyFileError(f"key file {name}: too long ({len(text)}"
                           f"{'+' if total > _MAX_READ else ''} bytes; a key file is 64 hex "
                           f"digits and an optional newline)")
    try:
        return parse_key(text)
    except KeyTextError as exc:
        raise KeyFileError(f"key file {name}: {exc}") from None


def write_key_file(path: str | os.PathLike[str], key: bytes | None = None) -> bytes:
    """Create ``path`` (mode 0600, never overwriting) holding ``key`` (default: a new random
    key) as 64 hex digits and a newline; return the key. Raises :class:`KeyFileError`."""
    name = os.fspath(path)
    raw = new_key() if key is None else check_key(key)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(name, flags, 0o600)
    except FileExistsError:
        raise KeyFileError(f"{name} already exists; keygen never overwrites a file "
                           f"(remove it first, or choose another path)") from None
    except OSError as exc:
        raise KeyFileError(f"cannot create {name}: {exc.strerror or exc}") from None
    try:
        data = format_key(raw)
        written = 0
        while written < len(data):
            written += os.write(fd, data[written:])
        os.fsync(fd)
    except OSError as exc:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(name)
        raise KeyFileError(f"cannot write {name}: {exc.strerror or exc}") from None
    os.close(fd)
    return raw
