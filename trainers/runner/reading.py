"""The one way factorq reads a file (results, sweep files, kept units and configurations). Every
file is untrusted, so each read refuses before any parsing:

- a link (opened ``O_NOFOLLOW``; the message names its target, to pass instead);
- anything but a regular file (opened ``O_NONBLOCK``, so a FIFO with no writer does not block,
  and ``fstat``-ed on the descriptor that is then read: nothing can be swapped in between);
- more than ``max_bytes`` (``fstat`` before reading, and at most ``max_bytes + 1`` bytes read);
- nesting deeper than ``MAX_DEPTH``: JSON's and TOML's counted on the text before a recursive
  parser sees it (TOML's dotted keys too), YAML's while it is composed, the parsed value walked
  without recursion (``deeper_than``).

Errors are ``ReadError`` (a ``ValueError``) in one line naming the file; ``FileMissing`` where
nothing is there.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

#: Nesting deeper than this is refused before parsing (a results file nests 6 levels, a sweep
#: file 3, a checkpoint 8).
MAX_DEPTH = 32
#: Flags of every read: never through a link, never blocking on a FIFO, never inherited.
_FLAGS = (
    os.O_RDONLY
    | getattr(os, "O_NOFOLLOW", 0)
    | getattr(os, "O_NONBLOCK", 0)
    | getattr(os, "O_CLOEXEC", 0)
)
_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


class ReadError(ValueError):
    """A file that is refused before or while it is parsed, in one line naming it."""


class FileMissing(ReadError):
    """Nothing at the file's name (not even a dangling link)."""


def _name(path: Path, what: str) -> str:
    return f"{what} {path}" if what else str(path)


@contextlib.contextmanager
def open_regular(path: str | os.PathLike, what: str, max_bytes: int) -> Iterator[BinaryIO]:
    """``path`` opened for reading as a binary file, once it is proven a regular file (not a
    link) of at most ``max_bytes`` bytes (``what``: the kind of file, for messages)."""
    path = Path(path)
    name = _name(path, what)
    try:
        descriptor = os.open(path, _FLAGS)
    except FileNotFoundError:
        raise FileMissing(f"{name} does not exist") from None
    except OSError as error:
        if error.errno == errno.ELOOP or path.is_symlink():
            target = os.readlink(path) if path.is_symlink() else "?"
            raise ReadError(
                f"{name} is a symbolic link (to {target}): factorq reads no file through a "
                f"link; give the file itself"
            ) from None
        reason = error.strerror or type(error).__name__
        raise ReadError(f"{name} cannot be read: {reason}") from None
    try:
        status = os.fstat(descriptor)
        if not stat.S_ISREG(status.st_mode):
            kind = next((n for test, n in _KINDS if test(status.st_mode)), "not a regular file")
            raise ReadError(f"{name} is not a regular file ({kind})")
        if status.st_size > max_bytes:
            raise ReadError(f"{name} is {status.st_size} bytes, more than the {max_bytes} allowed")
        os.set_blocking(descriptor, True)  # a regular file: blocking reads, as usual
        handle = os.fdopen(descriptor, "rb")
    except BaseException:
        os.close(descriptor)
        raise
    with handle:
        yield handle


def read_bytes(path: str | os.PathLike, what: str, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``max_bytes`` of them (``open_regular``)."""
    with open_regular(path, what, max_bytes) as handle:
        data = handle.read(max_bytes + 1)
    if len(data) > max_bytes:  # it grew after the size check
        raise ReadError(f"{_name(Path(path), what)} is more than the {max_bytes} bytes allowed")
    return data


def read_text(path: str | os.PathLike, what: str, max_bytes: int) -> str:
    """``read_bytes`` as UTF-8 text."""
    try:
        return read_bytes(path, what, max_bytes).decode("utf-8")
    except UnicodeDecodeError:
        raise ReadError(f"{_name(Path(path), what)} is not UTF-8 text") from None


# --------------------------------------------------------------------------------------------
# Depth, counted before a recursive parser sees the text


#: JSON's strings (skipped) and brackets.
_BRACKETS = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{}]')
#: TOML's strings, comments and brackets.
TOML_TOKENS = re.compile(
    r'"""[\s\S]*?"""'
    r"|'''[\s\S]*?'''"
    r'|"(?:[^"\\\n]|\\.)*"'
    r"|'[^'\n]*'"
    r"|#[^\n]*"
    r"|[\[\]{}]"
)
#: A TOML key of one or more parts (``a.b."c d".e``: bare or quoted parts joined by dots); a
#: number (``1.5``) reads as two parts, which is harmless (one level).
_TOML_KEY_PART = r'(?:[A-Za-z0-9_-]+|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\')'
_TOML_CHAINS = re.compile(
    r'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|#[^\n]*'
    rf"|{_TOML_KEY_PART}(?:[ \t]*\.[ \t]*{_TOML_KEY_PART})*"
)


def nesting_depth(text: str, tokens: re.Pattern = _BRACKETS) -> int:
    """The deepest ``[``/``{`` nesting of JSON ``text`` (brackets inside strings do not count;
    ``tokens``: the strings and brackets of another syntax, e.g. ``TOML_TOKENS``)."""
    depth = deepest = 0
    for token in tokens.findall(text):
        if token in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif token in "]}":
            depth -= 1
    return deepest


def toml_depth(text: str) -> int:
    """An upper bound of the nesting of TOML ``text``: its bracket nesting plus its longest
    dotted key (``[a.b]`` and ``a.b.c = 1`` nest by their dots). Linear in the text."""
    longest = 0
    for match in _TOML_CHAINS.finditer(text):
        token = match.group()
        if token[0] == "#" or token[:3] in ('"""', "'''"):
            continue
        longest = max(longest, len(re.findall(_TOML_KEY_PART, token)))
    return nesting_depth(text, TOML_TOKENS) + longest


def deeper_than(value: Any, limit: int) -> bool:
    """Whether ``value``'s dicts, lists and tuples nest more than ``limit`` levels, found without
    recursion (a walk that recursed would raise RecursionError on a hostile file first)."""
    stack = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        children: Iterable[Any]
        if isinstance(item, dict):
            children = item.values()
        elif isinstance(item, list | tuple):
            children = item
        else:
            continue
        if depth >= limit:
            return True
        stack.extend((child, depth + 1) for child in children)
    return False


def _too_deep(path: Path, what: str) -> ReadError:
    return ReadError(f"{_name(path, what)} nests deeper than {MAX_DEPTH} levels")


# --------------------------------------------------------------------------------------------
# Documents


def read_json(path: str | os.PathLike, what: str, max_bytes: int) -> Any:
    """The JSON document in ``path``: a regular file, bounded in size and nesting."""
    path = Path(path)
    text = read_text(path, what, max_bytes)
    if nesting_depth(text) > MAX_DEPTH:
        raise _too_deep(path, what)
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise ReadError(f"{_name(path, what)} is not valid JSON ({error})") from None
    except RecursionError:  # (the count above makes this unreachable; kept as a refusal)
        raise _too_deep(path, what) from None
    return value


def read_toml(path: str | os.PathLike, what: str, max_bytes: int) -> Any:
    """The TOML document in ``path``: a regular file, bounded in size, in bracket nesting and in
    dotted-key depth before ``tomllib`` parses it."""
    import tomllib

    path = Path(path)
    text = read_text(path, what, max_bytes)
    if toml_depth(text) > MAX_DEPTH:
        raise _too_deep(path, what)
    try:
        value = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ReadError(f"{path}: not valid TOML ({error})") from None
    if deeper_than(value, MAX_DEPTH):
        raise _too_deep(path, what)
    return value


def _yaml_loader() -> type:
    """PyYAML's safe loader refusing aliases (a 433-byte alias bomb took a minute and gigabytes)
    and nesting past ``MAX_DEPTH`` (checked before the composer recurses)."""
    import yaml

    class Loader(yaml.SafeLoader):
        depth = 0

        def compose_node(self, parent: Any, index: Any) -> Any:  # PyYAML's (untyped) signature
            if self.check_event(yaml.AliasEvent):
                mark = self.peek_event().start_mark
                raise yaml.YAMLError(f"aliases (*name) are not allowed (line {mark.line + 1})")
            if self.depth >= MAX_DEPTH:
                raise yaml.YAMLError(f"it nests deeper than {MAX_DEPTH} levels")
            self.depth += 1
            try:
                return super().compose_node(parent, index)
            finally:
                self.depth -= 1

    return Loader


def read_yaml(path: str | os.PathLike, what: str, max_bytes: int) -> Any:
    """The YAML document in ``path`` (PyYAML, safe, no aliases): a regular file, bounded in size
    and nesting."""
    import yaml

    path = Path(path)
    text = read_text(path, what, max_bytes)
    try:
        value = yaml.load(text, Loader=_yaml_loader())  # noqa: S506 - a safe loader
    except yaml.YAMLError as error:
        raise ReadError(f"{path}: not valid YAML ({' '.join(str(error).split())})") from None
    if deeper_than(value, MAX_DEPTH):
        raise _too_deep(path, what)
    return value
