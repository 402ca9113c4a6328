"""Reading a file the user names, safely: a regular file, not a link, of bounded size, read once.

``read_regular(path, what, max_bytes)`` opens ``path`` with ``O_NOFOLLOW`` and checks the open
descriptor (``fstat``): a symbolic link, a FIFO, a device or a directory is refused with one
line naming it, before anything is read, and what was checked is what is read (no window between
a check and the open). ``digest(value)`` is the SHA-256 of nested plain data and tensors, tensor
bytes included (torch's reader does not notice a flipped bit inside a tensor; this does).

>>> digest({"a": [1, "x"]}) == digest({"a": [1, "x"]}) != digest({"a": [1, "y"]})
True
"""

from __future__ import annotations

import hashlib
import os
import stat
from typing import Any

import torch

_OPEN_FLAGS = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)


def read_regular(path: str | os.PathLike, what: str, max_bytes: int) -> bytes:
    """The bytes of ``path``; a ``ValueError`` (``FileNotFoundError`` when it is missing) of one
    line naming the path when it is a link, not a regular file or larger than ``max_bytes``.

    Args:
        path: the file.
        what: what the file should be, for the messages (``"a saved agent"``).
        max_bytes: the largest size accepted.
    """
    if os.path.islink(path):
        raise ValueError(f"{os.fspath(path)} is a symbolic link, not {what}: name the file itself")
    try:
        descriptor = os.open(path, _OPEN_FLAGS | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        where = os.fspath(path)
        raise FileNotFoundError(f"{where} does not exist (expected {what} there)") from None
    except OSError as error:  # ELOOP: a link planted after the check above
        raise ValueError(
            f"{os.fspath(path)} cannot be opened as {what} ({error.strerror})"
        ) from None
    try:
        status = os.fstat(descriptor)
        if not stat.S_ISREG(status.st_mode):
            raise ValueError(f"{os.fspath(path)} is not a regular file: not {what}")
        if status.st_size > max_bytes:
            raise ValueError(
                f"{os.fspath(path)} is {status.st_size} bytes, more than {what}'s {max_bytes}"
            )
        chunks, left = [], max_bytes
        while left > 0 and (chunk := os.read(descriptor, min(left, 1 << 24))):
            chunks.append(chunk)
            left -= len(chunk)
        return b"".join(chunks)
    finally:
        os.close(descriptor)


def digest(value: Any) -> str:
    """SHA-256 of nested dicts, lists, tuples, plain values and tensors (dtype, shape, bytes).

    Args:
        value: the data.
    """
    hasher = hashlib.sha256()
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, torch.Tensor):
            tensor = item.detach().cpu().contiguous()
            hasher.update(f"T{tensor.dtype}{tuple(tensor.shape)};".encode())
            if tensor.numel():  # (an empty tensor has no bytes to view)
                hasher.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
        elif isinstance(item, dict):
            hasher.update(f"D{len(item)};".encode())
            for key in sorted(item, key=repr, reverse=True):  # popped in sorted order
                stack.extend((item[key], _Key(key)))
        elif isinstance(item, list | tuple):
            hasher.update(f"{type(item).__name__[0]}{len(item)};".encode())
            stack.extend(reversed(item))
        elif isinstance(item, _Key):
            hasher.update(f"{item.key!r}:".encode())
        else:
            hasher.update(f"{type(item).__name__}:{item!r};".encode())
    return hasher.hexdigest()


class _Key:
    """A dict key on ``digest``'s stack (hashed before its value)."""

    __slots__ = ("key",)

    def __init__(self, key: Any) -> None:
        self.key = key
