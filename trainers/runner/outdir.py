"""One writer per output directory, checked before any work starts: ``claim(out, outputs=...)``,
entered first by every command that writes a results directory, creates ``out`` and proves it
writable (a probe byte), takes an exclusive non-blocking ``flock`` on ``out/.factorq.lock``
(dropped by the kernel when its process dies; local to one machine), refuses the results of an
earlier run unless ``force`` or ``resume``, and removes the temporaries of killed writers
(``.NAME.PID.factorq-tmp``). No file of ours is opened through a link: the lock, the probe and
every temporary are created ``O_NOFOLLOW`` (``O_EXCL`` where new: ``create_new``), and a link
where the lock or an output belongs is refused (``LinkRefused``). Why: docs/decisions.md, "One
writer per ``--out``" and "Hardening: one reader, no writes through links, peers proven".
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import re
import shutil
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path

from factorq_trainers.runner import reading

LOCK_FILE = ".factorq.lock"
#: The suffix of every temporary factorq writes (``temporary_name``): a name no user writes, so
#: ``remove_temporaries`` deletes only ours (a user's ``.backup.2024.tmp`` is left alone).
TEMPORARY_SUFFIX = ".factorq-tmp"
#: What ``write_all_atomic`` (and compare's staging logs) leave behind when killed mid-write.
_TEMPORARY = re.compile(r"^\..+\.\d+" + re.escape(TEMPORARY_SUFFIX) + "$")
#: The folders factorq writes into directly under an output directory (a sweep's configuration
#: results, a runner command's kept units, compare's logs): a link at one of these names is
#: refused by ``claim`` before any work, as a file's is.
OWN_DIRECTORIES = ("configs", "units", "logs")


def temporary_name(name: str, pid: int | None = None) -> str:
    """``.NAME.PID.factorq-tmp``: where a file (or staging folder) ``name`` is written before it
    is renamed into place."""
    return f".{name}.{os.getpid() if pid is None else pid}{TEMPORARY_SUFFIX}"


class OutputDirError(ValueError):
    """An output directory that cannot be used, with the reason and what to do instead."""


def checked_out(out: object, error: type[ValueError] = ValueError, files: bool = False) -> str:
    """A config's ``out`` option as a path string, checked when the config is made: ``error``
    (a ValueError) where it is no path or (unless ``files``: compare's ``run`` writes nothing,
    ``/dev/null`` will do) names an existing file."""
    if not isinstance(out, str | os.PathLike) or not str(out):
        raise error(f"out={out!r} must be a directory path")
    if not files and Path(out).exists() and not Path(out).is_dir():
        raise error(f"out={out!r} is an existing file: give a directory")
    return str(out)


class LinkRefused(OutputDirError):
    """A symbolic link where factorq writes a file of its own (a lock, a temporary, an output)."""

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(
            f"'{path}' is a symbolic link where factorq writes its own files: remove the link "
            f"(factorq never writes through links; its target was left as it is)"
        )


#: Flags of every file of ours: never through a link, never inherited by a child process.
_OWN = getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)


def create_new(path: str | os.PathLike) -> int:
    """Create ``path`` as a new empty file and return its descriptor (write-only).

    ``O_CREAT | O_EXCL | O_NOFOLLOW``: the file is new, so nothing another process planted there
    (a link to a user's file) is opened or truncated. A link at ``path`` raises ``LinkRefused``;
    a regular file there (a temporary of a killed writer whose pid was reused) is replaced.
    """
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | _OWN
    try:
        return os.open(path, flags, 0o644)
    except FileExistsError:
        if os.path.islink(path):
            raise LinkRefused(path) from None
        if not os.path.isfile(path):
            raise OutputDirError(
                f"'{path}' is in the way and not a regular file: remove it"
            ) from None
        os.unlink(path)
        return os.open(path, flags, 0o644)


def _open_lock(lock_path: Path) -> int:
    """The lock file's descriptor (read-write), created new where missing; a link there is
    refused (following it would truncate its target), and so is anything but a regular
    file."""
    with contextlib.suppress(FileExistsError):
        return os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_EXCL | _OWN, 0o644)
    if lock_path.is_symlink():
        raise LinkRefused(lock_path)
    try:
        descriptor = os.open(lock_path, os.O_RDWR | _OWN)
    except OSError as error:  # a directory, a link swapped in meanwhile (ELOOP), no access
        raise OutputDirError(
            f"out='{lock_path.parent}' cannot be locked: {lock_path.name} "
            f"{error.strerror or type(error).__name__}"
        ) from None
    if not stat.S_ISREG(os.fstat(descriptor).st_mode):
        os.close(descriptor)
        raise OutputDirError(
            f"out='{lock_path.parent}' cannot be locked: {lock_path.name} is not a regular "
            f"file: remove it"
        )
    return descriptor


def _prepare(path: Path) -> None:
    """Create ``path`` and prove it writable, or raise an OutputDirError naming why."""
    if path.exists() and not path.is_dir():
        raise OutputDirError(f"out='{path}' is not a directory")
    created = not path.exists()
    probe = path / temporary_name("factorq-probe")
    try:
        path.mkdir(parents=True, exist_ok=True)
        descriptor = create_new(probe)
        try:  # one byte, so a full disk is found here (an empty file needs no space)
            os.write(descriptor, b"p")
        finally:
            os.close(descriptor)
            probe.unlink()
    except OSError as error:
        reason = error.strerror or type(error).__name__
        if created:
            with contextlib.suppress(OSError):
                path.rmdir()
        raise OutputDirError(f"out='{path}' is not writable: {reason}") from None


def _holder(lock_path: Path) -> str:
    """The pid recorded by the run that holds the lock, for the message."""
    try:
        text = reading.read_text(lock_path, "lock", 64).strip()
    except (OSError, ValueError):
        return "another factorq run"
    return f"another factorq run (pid {text})" if text.isdigit() else "another factorq run"


def remove_temporaries(path: Path) -> list[Path]:
    """Delete the ``.NAME.PID.factorq-tmp`` files (and staging directories) directly in
    ``path``, never following a link; return what was deleted."""
    removed = []
    for entry in path.iterdir():
        if not _TEMPORARY.match(entry.name) or entry.is_symlink():
            continue
        if entry.is_file():
            entry.unlink(missing_ok=True)
        elif entry.is_dir():  # factorq compare's staging logs (.logs.PID.factorq-tmp/)
            shutil.rmtree(entry, ignore_errors=True)
        else:
            continue
        removed.append(entry)
    return removed


@contextlib.contextmanager
def claim(
    out: str | os.PathLike,
    *,
    outputs: Iterable[str] = (),
    force: bool = False,
    resume: bool = False,
) -> Iterator[Path]:
    """Hold ``out`` as its only writer for the duration of the ``with`` block.

    Args:
        out: the output directory (created if missing).
        outputs: file names the run will write; if one exists already the claim is refused unless
            ``force`` or ``resume``.
        force: replace the results of an earlier run.
        resume: the run continues the one that wrote ``out`` (its files are its own).

    Raises:
        OutputDirError: ``out`` is not a writable directory, another run holds it, or it holds
            results that ``force`` was not given to replace.
    """
    path = Path(out)
    created = not path.exists()
    _prepare(path)
    lock_path = path / LOCK_FILE
    descriptor = _open_lock(lock_path)
    try:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise OutputDirError(f"out='{path}' cannot be locked: {error.strerror}") from None
            action = "resume it" if resume else "write to it"
            raise OutputDirError(
                f"out='{path}' is in use by {_holder(lock_path)}: wait for it to finish, or "
                f"choose another --out (refusing to {action} at the same time)"
            ) from None
        try:
            os.ftruncate(descriptor, 0)
            os.write(descriptor, str(os.getpid()).encode())
        except OSError as error:  # a disk that filled since the probe
            if created:
                with contextlib.suppress(OSError):
                    lock_path.unlink()
                    path.rmdir()
            raise OutputDirError(
                f"out='{path}' is not writable: {error.strerror or type(error).__name__}"
            ) from None
        outputs = tuple(outputs)
        links = [name for name in (*outputs, *OWN_DIRECTORIES) if (path / name).is_symlink()]
        if links:  # renaming over a link would not follow it, but it is not ours to remove
            raise LinkRefused(path / links[0])
        for name in outputs:  # --force replaces files, never a directory in a file's place
            target = path / name
            if name not in OWN_DIRECTORIES and target.exists() and not target.is_file():
                raise OutputDirError(
                    f"out='{path}' holds {name}, which is not a regular file, where factorq "
                    f"writes its {name}: remove or rename it (--force replaces files only)"
                )
        existing = [name for name in outputs if (path / name).exists()]
        if existing and not (force or resume):
            raise OutputDirError(
                f"out='{path}' already holds {', '.join(existing)} from an earlier run: pass "
                f"--force to replace them, or choose another --out"
            )
        remove_temporaries(path)
        try:
            yield path
        finally:
            # A run that made the directory and wrote nothing in it (it failed, or was
            # interrupted, before any output) leaves no directory holding just a lock file.
            with contextlib.suppress(OSError):
                if created and [entry.name for entry in path.iterdir()] == [LOCK_FILE]:
                    lock_path.unlink()
                    path.rmdir()
    finally:
        os.close(descriptor)  # closing releases the lock
