"""Kept files: results a rerun reuses instead of recomputing (a sweep's shards and config
results), sealed with a content digest and checked like a checkpoint before they are reused.

A kept file is the user's as much as ours: it may have been edited, cut short or copied from
elsewhere. Reusing one unchecked would put its numbers in a report silently, so each carries a
SHA-256 of its content, checked on reuse, and its values are checked as well (finite, in range,
counts whole and consistent), because a digest proves integrity, not origin. A file that fails
is refused in one line naming it and saying that ``--force`` recomputes it (``reusable``).

- ``check_digest``: the shared digest check (shards' ``metrics_digest`` and ``json_digest``);
- ``dumps_sealed`` / ``read_sealed``: a JSON results dict with its digest under ``DIGEST_KEY``;
- ``check_values``: the value checks of a kept JSON results dict;
- ``reusable``: whether a kept file is to be reused, recomputed (``force``) or refused.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from factorq_trainers.runner import results as result_files

#: What to do about a kept file that fails its checks (the sweep's and paper's ``--force``).
REMEDY = "pass --force to recompute it"
#: Where a sealed JSON results file keeps the SHA-256 of the rest of its content.
DIGEST_KEY = "content_sha256"


def check_digest(path: Path, what: str, stored: str, actual: str, remedy: str = REMEDY) -> None:
    """A ValueError naming ``path`` (a ``what``: "shard file", ...) and ``remedy`` unless
    ``stored`` (the digest written with it; empty when it has none) equals ``actual`` (that of
    its content)."""
    if not stored:
        raise ValueError(f"{what} {path} has no digest (an older factorq wrote it): {remedy}")
    if stored != actual:
        raise ValueError(f"{what} {path} does not match its digest (edited or damaged): {remedy}")


def json_digest(results: dict[str, Any]) -> str:
    """SHA-256 of ``results`` (``DIGEST_KEY`` left out) as canonical JSON: sorted keys, numbers
    as Python writes them (floats round-trip exactly, so the digest survives a read and write)."""
    content = {key: value for key, value in results.items() if key != DIGEST_KEY}
    text = json.dumps(content, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def dumps_sealed(results: dict[str, Any]) -> str:
    """``results_file.dumps(results)`` with the digest of what a reader will parse added."""
    parsed = json.loads(result_files.dumps(results))  # tuples as lists, non-finite as null
    parsed[DIGEST_KEY] = json_digest(parsed)
    return result_files.dumps(parsed)


#: Leaf keys (or the key of their list) whose numbers are counts or sizes: never negative.
_NON_NEGATIVE = re.compile(
    r"\w*collisions\w*|steps\w*|\w*_steps\w*|episodes\w*|seeds\w*|samples_\w+|wall_s|"
    r"\w*path_length|shortest_path|threshold|hamming\w*|reopened\w*|wrong_commitments\w*|"
    r"success_rate|fraction\w*|ratio|runs"
)
#: ... and whose numbers are whole as well.
_WHOLE = re.compile(r"seeds_reached|samples_target|shortest_path|steps_to_threshold_per_seed|runs")
#: ... and whose numbers are fractions, in [0, 1].
_FRACTION = re.compile(r"fraction\w*|success_rate")
#: Subtrees that hold settings and descriptions, not measured numbers (the digest covers them).
_SETTINGS = ("config", "software", "world", "methods", "timing")
#: Keys that only label a number by the measure above them.
_GENERIC = re.compile(r"mean|low|high|ci|ci95|n|\d+")


def check_values(path: Path, what: str, results: dict[str, Any], remedy: str = REMEDY) -> None:
    """A ValueError naming ``path`` unless every number of ``results`` is finite, those of
    counts (collisions, steps, episodes, seeds, samples, ...) are >= 0, fractions are in
    [0, 1], whole counts are whole, and a compare result's ``seeds_reached`` is the number of
    its seeds that reached the threshold, ``steps_to_threshold_per_seed`` one per seed."""
    stack: list[tuple[Any, str, str]] = [
        (value, key, key) for key, value in results.items() if key not in (DIGEST_KEY,)
    ]
    while stack:  # no recursion: read_json bounded the depth, this stays iterative anyway
        value, where, measure = stack.pop()
        if isinstance(value, dict):
            if where in _SETTINGS:
                continue
            for key, item in value.items():
                named = measure if _GENERIC.fullmatch(str(key)) else str(key)
                stack.append((item, f"{where}/{key}", named))
            continue
        if isinstance(value, list):
            stack.extend((item, f"{where}[{i}]", measure) for i, item in enumerate(value))
            continue
        if value is None:
            continue  # a missing number (a non-finite one is written as null)
        if isinstance(value, str | bool) and not _NON_NEGATIVE.fullmatch(measure):
            continue  # a label, a verdict
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise ValueError(f"{what} {path}: {where} holds {value!r}, not a number: {remedy}")
        problem = None
        if not math.isfinite(value):
            problem = "not a finite number"
        elif _NON_NEGATIVE.fullmatch(measure) and value < 0:
            problem = "negative"
        elif _FRACTION.fullmatch(measure) and value > 1:
            problem = "not a fraction in [0, 1]"
        elif _WHOLE.fullmatch(measure) and value != math.floor(value):
            problem = "not a whole count"
        if problem is not None:
            raise ValueError(f"{what} {path}: {where} holds {value!r}, {problem}: {remedy}")
    _check_compare_counts(path, what, results, remedy)


def _check_compare_counts(path: Path, what: str, results: dict[str, Any], remedy: str) -> None:
    """A compare result's per-seed counts agree with its config and with each other."""
    if results.get("command") != "compare" or not isinstance(results.get("results"), dict):
        return
    config = results.get("config")
    seeds = config.get("seeds") if isinstance(config, dict) else None
    for method, worlds in results["results"].items():
        for world, entry in worlds.items() if isinstance(worlds, dict) else ():
            if not isinstance(entry, dict) or "steps_to_threshold_per_seed" not in entry:
                continue
            per_seed = entry["steps_to_threshold_per_seed"]
            if not isinstance(per_seed, list) or (seeds is not None and len(per_seed) != seeds):
                count = len(per_seed) if isinstance(per_seed, list) else "no"
                raise ValueError(
                    f"{what} {path}: results/{method}/{world} holds {count} seeds' steps to "
                    f"the threshold, not {seeds}: {remedy}"
                )
            reached = sum(step is not None for step in per_seed)
            if entry.get("seeds_reached") != reached:
                raise ValueError(
                    f"{what} {path}: results/{method}/{world}/seeds_reached is "
                    f"{entry.get('seeds_reached')!r}, but {reached} seeds reached the threshold: "
                    f"{remedy}"
                )


def read_sealed(path: Path, what: str, remedy: str = REMEDY, values: bool = True) -> dict[str, Any]:
    """The results dict kept at ``path`` once its digest and (``values``) its values are
    checked (the digest key removed); a ValueError naming ``path`` and ``remedy`` otherwise."""
    try:
        results = result_files.read_json(path, (), remedy)
    except (ValueError, OSError) as error:
        raise ValueError(f"{what} {path} is unreadable ({error}): {remedy}") from None
    stored = results.pop(DIGEST_KEY, "")
    actual = json_digest(results)
    check_digest(path, what, stored if isinstance(stored, str) else "", actual, remedy)
    if values:
        check_values(path, what, results)
    return results


def reusable(path: Path, check: Callable[[Path], Any], force: bool) -> bool:
    """Whether the kept file at ``path`` is to be reused: False when there is none, True when
    ``check(path)`` (a ``read_sealed`` or ``shards.load``) accepts it; when it refuses it, False
    with ``force`` (the caller recomputes and replaces it), else its ValueError."""
    if not path.exists() and not path.is_symlink():
        return False
    try:
        check(path)
    except ValueError:
        if force:
            return False
        raise
    return True
