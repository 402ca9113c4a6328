"""Checkpoint files of ``factorq paper`` (and, in their format ``COMPARE_FORMAT``, of ``factorq
compare``): a run's whole state, saved atomically, loaded safely.

A checkpoint is one file written by ``torch.save`` and read back by ``torch.load(...,
weights_only=True)``: plain tensors, numbers, strings, lists and dicts, never pickled code. It holds

    format, version     what the file is ("factorq-paper-checkpoint", FORMAT_VERSION)
    sha256              digest of the content, tensor bytes included: torch's reader does not
                        notice a flipped bit inside a tensor, this does
    content:
      config            the run's config (``paper.config_dict``); a resumed run takes it from here
      backend           the driver that wrote the state ("fast" or "modular"; each reads its own)
      every             the checkpoint interval the run was started with ("5000", "30s")
      finished          {algorithm: metrics [W * S, runs, episodes]} of the algorithms done
      running           {"algorithm", "state"} of the one in progress (None between algorithms):
                        for the fast backend ``ExperimentBatch.state_dict()``, that is tables,
                        counts, world state, stream positions (counter-based streams: their state
                        is one integer each), run and episode counters and partial metrics; for
                        the modular one ``OnlineCollector.state_dict()`` (tables, policy stream
                        counters, counters, metrics, the observation the next step acts on) and
                        the env's ``world_state``
      episodes_completed, experiments_finished, elapsed_s, saved_utc

Files, in ``<out>/checkpoint/``: ``checkpoint.pt`` (the newest) and ``checkpoint.prev.pt`` (the
one before it). A save writes a temporary next to them, flushes and fsyncs it, hard-links the
current newest file to the previous name (through a temporary link and ``os.replace``), renames
the temporary onto the newest name and fsyncs the directory: at every instant both names hold
complete files, so a kill at any moment loses at most the work since the last save, and a
damaged newest file still leaves the previous one. The directory is removed once the run's
results are written.

Loading reads ``checkpoint.pt``, or ``checkpoint.prev.pt`` when there is no newest file. A damaged
newest file is an error, not a silent fall-back: the message says whether the previous file is
intact and how to resume from it (move the damaged one away), and nothing is changed on disk.

>>> every = parse_every("30s")
>>> every.seconds, every.episodes, str(every)
(30.0, None, '30s')
>>> parse_every(5000)
Every(episodes=5000, seconds=None)
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import torch

from factorq_trainers.runner import outdir, reading, resources, results

FORMAT = "factorq-paper-checkpoint"
#: ``factorq compare``'s checkpoints: the methods finished so far and the running one's state.
COMPARE_FORMAT = "factorq-compare-checkpoint"
FORMAT_VERSION = 1
DIRECTORY = "checkpoint"
LATEST = "checkpoint.pt"
PREVIOUS = "checkpoint.prev.pt"
_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0}
_TEMPORARY = re.compile(
    r"^\.(checkpoint\.pt|checkpoint\.prev\.pt)\.\d+" + re.escape(outdir.TEMPORARY_SUFFIX) + "$"
)


def is_int(value: Any) -> bool:
    """An int that is not a bool (``True`` is an int to Python, never to a checkpoint)."""
    return isinstance(value, int) and not isinstance(value, bool)


def to_device(tree: Any, device: torch.device | str) -> Any:
    """``tree`` (nested dicts and lists of tensors) with every tensor on ``device``: a state
    saved from any device, restored on the run's."""
    if isinstance(tree, torch.Tensor):
        return tree.to(device)
    if isinstance(tree, dict):
        return type(tree)((key, to_device(value, device)) for key, value in tree.items())
    if isinstance(tree, list):
        return [to_device(value, device) for value in tree]
    return tree


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: missing, damaged, or not this run's. One line, naming
    the file and what to do."""


# --------------------------------------------------------------------------------------------
# The interval


class Every(NamedTuple):
    """Save every ``episodes`` episodes (summed over all experiments) or every ``seconds``."""

    episodes: int | None = None
    seconds: float | None = None

    def __str__(self) -> str:
        return str(self.episodes) if self.episodes is not None else f"{self.seconds:g}s"


def parse_every(value: Any) -> Every:
    """``5000`` or ``"5000"`` (episodes), ``"30s"``, ``"10m"``, ``"1h"`` (time) as an ``Every``."""
    if isinstance(value, Every):
        return value
    usage = "a number of episodes (e.g. 5000) or of seconds with a unit (e.g. 30s, 10m, 1h)"
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise TypeError(f"checkpoint_every must be {usage}, got {value!r}")
    text = str(value).strip().lower()
    if re.fullmatch(r"[+-]?\d+", text):
        episodes = int(text)
        if not 1 <= episodes <= 2**63 - 1:  # counted in int64 alongside the kernel's counters
            raise ValueError(
                f"checkpoint_every={value!r} is out of range: must be in [1, 2**63 - 1] episodes"
            )
        return Every(episodes=episodes)
    match = re.fullmatch(r"([+-]?[0-9.e+-]+)\s*([smh])", text)
    try:
        seconds = float(match[1]) * _UNITS[match[2]] if match else math.nan
    except ValueError:
        seconds = math.nan
    if match is None or math.isnan(seconds):
        raise ValueError(f"checkpoint_every={value!r} is not {usage}")
    if not 0 < seconds < math.inf:
        raise ValueError(
            f"checkpoint_every={value!r} is out of range: must be > 0 seconds and finite"
        )
    return Every(seconds=seconds)


# --------------------------------------------------------------------------------------------
# Files


def directory_of(out: str | os.PathLike) -> Path:
    """Where the checkpoints of a run writing to ``out`` live."""
    return Path(out) / DIRECTORY


def exists(out: str | os.PathLike) -> bool:
    """Whether ``out`` holds a checkpoint (of a run that has not finished)."""
    directory = directory_of(out)
    return (directory / LATEST).is_file() or (directory / PREVIOUS).is_file()


def check_none_in(out: str | os.PathLike) -> None:
    """Refuse to start a new run in ``out`` over an unfinished run's checkpoint."""
    if exists(out):
        raise CheckpointError(
            f"out='{out}' holds the checkpoint of an unfinished run ({directory_of(out)}): "
            f"continue it with --resume {out}, or delete {directory_of(out)} to start afresh"
        )


def digest(value: Any) -> str:
    """SHA-256 of a checkpoint's content: structure, types, shapes and every tensor's bytes."""
    hasher = hashlib.sha256()
    _feed(hasher, value)
    return hasher.hexdigest()


def _feed(hasher: Any, value: Any) -> None:
    if isinstance(value, torch.Tensor):
        tensor = value.detach().cpu().contiguous()
        hasher.update(f"T{tensor.dtype}{tuple(tensor.shape)};".encode())
        if tensor.numel():  # (an empty tensor has no bytes, and may not be viewed as bytes)
            hasher.update(tensor.reshape(-1).view(torch.uint8).numpy())
    elif isinstance(value, dict):
        hasher.update(f"D{len(value)};".encode())
        for key in sorted(value, key=repr):
            hasher.update(f"{key!r}:".encode())
            _feed(hasher, value[key])
    elif isinstance(value, list | tuple):
        hasher.update(f"L{len(value)};".encode())
        for item in value:
            _feed(hasher, item)
    else:
        hasher.update(f"{type(value).__name__}:{value!r};".encode())


def save(out: str | os.PathLike, content: dict[str, Any], kind: str = FORMAT) -> Path:
    """Write ``content`` as the newest checkpoint of ``out``, keeping the one before it
    (``kind``: the file's format name, ``FORMAT`` or ``COMPARE_FORMAT``)."""
    directory = directory_of(out)
    if directory.is_symlink():  # (claim refuses it first; a library caller gets it here)
        raise outdir.LinkRefused(directory)
    made = not directory.exists()
    directory.mkdir(parents=True, exist_ok=True)
    latest, previous = directory / LATEST, directory / PREVIOUS
    pid = os.getpid()
    temporary = directory / outdir.temporary_name(LATEST, pid)
    link = directory / outdir.temporary_name(PREVIOUS, pid)
    record = {"format": kind, "version": FORMAT_VERSION, "sha256": digest(content)}
    try:
        with os.fdopen(outdir.create_new(temporary), "wb") as file:  # never through a link
            try:
                torch.save({**record, "content": content}, file)
                file.flush()
                os.fsync(file.fileno())
            except (RuntimeError, OSError) as error:  # (torch's zip writer: a RuntimeError)
                raise results.WriteError(latest, error, WRITE_KEPT) from None
        if latest.exists():
            try:  # previous := newest, while the newest name keeps its file
                os.link(latest, link)
                os.replace(link, previous)
            except OSError:  # no hard links here: a moment without a newest file
                os.replace(latest, previous)
        os.replace(temporary, latest)
        _sync_directory(directory)
    except BaseException:
        if made:  # the first save failed: no half checkpoint directory left behind
            with contextlib.suppress(OSError):
                temporary.unlink(missing_ok=True)
                directory.rmdir()
        raise
    finally:
        temporary.unlink(missing_ok=True)
        link.unlink(missing_ok=True)
    return latest


#: What a failed save keeps (``results.WriteError``): the newest checkpoint is replaced last.
WRITE_KEPT = "the checkpoint before it, if any, is kept"


def _sync_directory(directory: Path) -> None:
    """Make the renames in ``directory`` durable (where the platform allows it)."""
    try:
        descriptor = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def remove(out: str | os.PathLike) -> None:
    """Delete the checkpoints of ``out`` (after its results are written)."""
    directory = directory_of(out)
    for name in (LATEST, PREVIOUS):
        (directory / name).unlink(missing_ok=True)
    remove_temporaries(directory)
    try:
        directory.rmdir()
    except OSError:  # missing, or holds files that are not ours: leave them
        pass


def remove_temporaries(directory: Path) -> None:
    """Delete temporaries left by a save that was killed midway."""
    if directory.is_dir():
        for path in directory.iterdir():
            if _TEMPORARY.match(path.name) and not path.is_dir():
                path.unlink(missing_ok=True)


class Checkpoint(NamedTuple):
    """A loaded checkpoint: its file and the fields of its content (see the module doc)."""

    path: Path
    config: dict[str, Any]
    backend: str
    every: str | None
    finished: dict[str, dict[str, torch.Tensor]]
    running: dict[str, Any] | None
    episodes_completed: int
    experiments_finished: int
    elapsed_s: float
    saved_utc: str


def read(path: str | os.PathLike) -> Checkpoint:
    """Read and check one checkpoint file; ``CheckpointError`` saying why it is unusable."""
    path = Path(path)
    content = read_content(path, FORMAT)
    unknown = sorted(map(str, set(content) - set(Checkpoint._fields[1:])))
    if unknown:
        raise CheckpointError(
            f"checkpoint {path} is not usable: unknown fields {', '.join(unknown)}"
        )
    try:
        loaded = Checkpoint(
            path=path, **{field: content[field] for field in Checkpoint._fields[1:]}
        )
    except (KeyError, TypeError) as error:
        raise CheckpointError(f"checkpoint {path} lacks a field: {error}") from None
    _check_field_types(loaded)
    return loaded


def max_checkpoint_bytes() -> int:
    """The largest checkpoint file read: what this machine's memory allows (a checkpoint is read
    whole, and the run it resumes holds at least as much), 1 TiB where that is unknown."""
    limit, _ = resources.available_memory()
    return limit if limit is not None else 2**40


def read_content(path: Path, kind: str) -> dict[str, Any]:
    """The content of the checkpoint file ``path`` of format ``kind``, its digest checked."""
    try:
        record = reading.load_torch(path, "checkpoint", max_checkpoint_bytes())
    except reading.FileMissing:
        raise CheckpointError(f"checkpoint {path} is missing") from None
    except reading.ReadError as error:  # a link, a FIFO, a device, too large, compressed
        raise CheckpointError(str(error)) from None
    except Exception as error:  # torch raises many kinds on a damaged file: all mean the same
        raise CheckpointError(
            f"checkpoint {path} is corrupted or truncated ({_why(error)})"
        ) from None
    if not isinstance(record, dict) or record.get("format") != kind:
        command = "compare" if kind == COMPARE_FORMAT else "paper"
        raise CheckpointError(f"checkpoint {path} is not a factorq {command} checkpoint")
    if record.get("version") != FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint {path} has format version {record.get('version')!r}; this factorq "
            f"reads version {FORMAT_VERSION}: resume it with the factorq that wrote it"
        )
    content = record.get("content")
    if reading.deeper_than(content, reading.MAX_DEPTH):  # before the digest walk recurses
        raise CheckpointError(
            f"checkpoint {path} nests deeper than {reading.MAX_DEPTH} levels: not a checkpoint "
            f"factorq wrote"
        )
    if not isinstance(content, dict) or digest(content) != record.get("sha256"):
        raise CheckpointError(
            f"checkpoint {path} is corrupted or truncated (its content does not match its digest)"
        )
    return content


#: The type of every field of a checkpoint's content (its digest proves integrity, not origin:
#: anyone can edit a file and sign it again, so nothing in it is trusted before these checks and
#: the run's own, ``resume_checks.check_checkpoint``, against its config).
_FIELD_TYPES: dict[str, tuple[type, ...]] = {
    "config": (dict,),
    "backend": (str,),
    "every": (str, type(None)),
    "finished": (dict,),
    "running": (dict, type(None)),
    "episodes_completed": (int,),
    "experiments_finished": (int,),
    "elapsed_s": (float, int),
    "saved_utc": (str,),
}


def _check_field_types(loaded: Checkpoint) -> None:
    for field, types in _FIELD_TYPES.items():
        value = getattr(loaded, field)
        if isinstance(value, bool) or not isinstance(value, types):
            expected = " or ".join(
                "None" if kind is type(None) else kind.__name__ for kind in types
            )
            raise CheckpointError(
                f"checkpoint {loaded.path} is not usable: its {field} is a "
                f"{type(value).__name__}, not a {expected}"
            )
    if not all(isinstance(key, str) for key in loaded.config):
        raise CheckpointError(
            f"checkpoint {loaded.path} is not usable: its config has non-text keys"
        )
    if loaded.every is not None:
        try:
            parse_every(loaded.every)
        except (ValueError, TypeError) as error:
            raise CheckpointError(f"checkpoint {loaded.path} is not usable: {error}") from None
    if not math.isfinite(loaded.elapsed_s) or loaded.elapsed_s < 0:
        raise CheckpointError(
            f"checkpoint {loaded.path} is not usable: elapsed_s={loaded.elapsed_s!r} must be a "
            f"finite number >= 0"
        )


def _why(error: BaseException) -> str:
    """The first line of a loader's error, short (torch's run to several sentences)."""
    text = str(error).strip().splitlines()[0] if str(error).strip() else ""
    text = text.split(". ")[0].rstrip(".")
    if len(text) > 100:
        text = text[:97] + "..."
    return f"{type(error).__name__}: {text}" if text else f"{type(error).__name__}: file ends early"


def load(out: str | os.PathLike, reader: Callable[[Path], Any] = read) -> Any:
    """The checkpoint to resume the run of ``out`` from (its newest one).

    Raises ``CheckpointError`` with one line saying what is wrong and what to do: ``out`` is not a
    directory, holds no checkpoint (or the run finished), or its newest checkpoint is damaged
    (then whether the previous one is intact and how to continue from it).
    """
    out_path = Path(out)
    where = "give the --out directory of an interrupted run"
    if not out_path.exists():
        raise CheckpointError(f"resume='{out}' does not exist: {where}")
    if not out_path.is_dir():
        raise CheckpointError(f"resume='{out}' is a file: {where} (it holds {DIRECTORY}/{LATEST})")
    directory = directory_of(out)
    latest, previous = directory / LATEST, directory / PREVIOUS
    if not latest.exists() and not previous.exists():
        if (out_path / "results.json").exists():
            raise CheckpointError(
                f"resume='{out}' holds no checkpoint: its run finished (results.json is there; "
                f"checkpoints are removed when a run finishes)"
            )
        raise CheckpointError(
            f"resume='{out}' holds no checkpoint ({latest} is missing): was the run started "
            f"with --checkpoint-every, and had it saved one yet?"
        )
    if not latest.exists():  # the newest was moved away (or a save was cut between renames)
        try:
            return reader(previous)
        except CheckpointError as error:
            raise CheckpointError(
                f"{error}; no other checkpoint is left: start the run again"
            ) from None
    try:
        return reader(latest)
    except CheckpointError as error:
        if not previous.exists():
            raise CheckpointError(
                f"{error}; there is no previous checkpoint ({previous}): start the run again"
            ) from None
        try:
            fallback = reader(previous)
        except CheckpointError as second:
            raise CheckpointError(
                f"{error}; the previous one is unusable too ({second}): start the run again"
            ) from None
        done = getattr(fallback, "progress", None) or f"{fallback.episodes_completed} episodes done"
        raise CheckpointError(
            f"{error}; the previous checkpoint {previous} is intact ({done}): move the damaged "
            f"file away (e.g. mv {latest} {latest}.damaged) and resume again to continue from it"
        ) from None
