"""Kept work: results a rerun reuses instead of recomputing (a run's finished units in
``OUT/units/``, a sweep's configuration results in ``OUT/configs/``), written and read by this
module alone. A kept file may have been edited, cut short, resealed or copied from elsewhere, so
each carries a SHA-256 of its content (``DIGEST_KEY``) and what it was kept for (``TIE_KEY``: the
command, the configuration's digest, the unit), both checked on reuse, and has its values
checked (``UnitStore.finished`` against the command's ``UNIT_RESULT``, or ``check_values`` by the
names of a results dict's measures): a digest proves integrity, not origin. A file that fails is
refused in one line naming it (``reusable``: or, with ``--force``, recomputed). Why and what each
check catches: docs/decisions.md, "Finished units are kept, tied to their run and checked".
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import re
import shutil
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from factorq_trainers.runner import results as result_files

#: What to do about a kept file that fails its checks (the sweep's and paper's ``--force``).
REMEDY = "pass --force to recompute it"
#: Where a sealed JSON results file keeps the SHA-256 of the rest of its content.
DIGEST_KEY = "content_sha256"
#: Where a sealed file keeps what it was kept for: ``{"command", "config_sha256"}`` and, for a
#: unit, ``"unit"`` (the unit as ``units(config)`` gave it).
TIE_KEY = "kept_for"


def json_digest(results: dict[str, Any]) -> str:
    """SHA-256 of ``results`` (``DIGEST_KEY`` left out) as canonical JSON: sorted keys, numbers
    as Python writes them (floats round-trip exactly, so the digest survives a read and write)."""
    content = {key: value for key, value in results.items() if key != DIGEST_KEY}
    text = json.dumps(content, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def config_digest(config: dict[str, Any]) -> str:
    """SHA-256 of a configuration as its JSON dict (``json_digest``): what ties kept work to the
    configuration that computed it."""
    return json_digest(json.loads(result_files.dumps(config)))


def tie(command: str, config: Any) -> dict[str, Any]:
    """What a file kept by ``command`` for ``config`` (a JSON dict, or a digest of it already
    made: a sweep's ``config_digest``) carries; a unit's file adds its ``"unit"``
    (``UnitStore``)."""
    digest = config if isinstance(config, str) else config_digest(config)
    return {"command": command, "config_sha256": digest}


def dumps_sealed(
    results: dict[str, Any], kept_for: dict[str, Any] | None = None, parsed: bool = False
) -> str:
    """``results_file.dumps(results)`` with what it is kept for (``tie``) and the digest of what
    a reader will parse added (``parsed``: ``results`` and ``kept_for`` are JSON values already,
    as a reader will parse them)."""
    if not parsed:
        results = json.loads(result_files.dumps(results))  # tuples as lists, non-finite as null
    parsed_ = dict(results)
    if kept_for is not None:
        parsed_[TIE_KEY] = kept_for
    parsed_[DIGEST_KEY] = json_digest(parsed_)
    return result_files.dumps(parsed_)


def write_sealed(path: Path, results: dict[str, Any], kept_for: Any, parsed: bool = False) -> None:
    """``dumps_sealed``'s text written atomically at ``path``."""
    text = dumps_sealed(results, kept_for, parsed)
    result_files.write_atomic(path, lambda target: target.write_text(text))


def check_tie(
    path: Path, what: str, stored: Any, expected: dict[str, Any], remedy: str = REMEDY
) -> None:
    """A ValueError naming ``path`` and ``remedy`` unless the file was kept for ``expected``
    (``tie``'s dict): the same command, configuration and unit."""
    if not isinstance(stored, dict):
        raise ValueError(f"{what} {path} does not say what run it was kept for: {remedy}")
    if stored.get("command") != expected["command"]:
        raise ValueError(
            f"{what} {path} was kept by command {short(stored.get('command'))}, not "
            f"`factorq {expected['command']}`: {remedy}"
        )
    if stored.get("config_sha256") != expected["config_sha256"]:
        raise ValueError(
            f"{what} {path} was kept for another configuration (digest "
            f"{short(stored.get('config_sha256'))}, this run's {expected['config_sha256']!r}): "
            f"{remedy}"
        )
    if "unit" in expected and stored.get("unit") != expected["unit"]:
        unit = stored.get("unit")
        named = unit.get("id") if isinstance(unit, dict) else unit
        raise ValueError(
            f"{what} {path} was kept for unit {short(named)} ({short(unit)}), not "
            f"{expected['unit'].get('id')!r}: {remedy}"
        )
    if set(stored) != set(expected):
        raise ValueError(f"{what} {path} says it was kept for {short(stored)}: {remedy}")


def short(value: Any, width: int = 60) -> str:
    """``repr(value)``, cut to ``width`` characters (a kept file's value, shown in a message)."""
    shown = repr(value)
    return shown if len(shown) <= width else shown[: width - 3] + "..."


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
#: Keys of an interval's bounds: a t interval of a count may reach below 0, so only finite.
_BOUND = re.compile(r"ci95|\w*_ci95|curves_ci_low|curves_ci_high|low|high")
#: Keys that only label a number by the measure above them.
_GENERIC = re.compile(r"mean|low|high|ci|ci95|n|\d+")


def check_values(
    path: Path,
    what: str,
    results: dict[str, Any],
    remedy: str = REMEDY,
    check: Callable[[dict[str, Any]], str | None] | None = None,
) -> None:
    """A ValueError naming ``path`` unless every number of ``results`` is finite, those of
    counts (collisions, steps, episodes, seeds, samples, ...) are >= 0, fractions are in
    [0, 1], whole counts are whole, and ``check(results)`` (the command's own check, its report
    module's ``results_problem``: e.g. compare's per-seed counts) finds nothing wrong."""
    stack: list[tuple[Any, str, str]] = [
        (value, key, key) for key, value in results.items() if key not in (DIGEST_KEY, TIE_KEY)
    ]
    while stack:  # no recursion: read_json bounded the depth, this stays iterative anyway
        value, where, measure = stack.pop()
        if isinstance(value, dict):
            if where in _SETTINGS:
                continue
            for key, item in value.items():
                named = measure if _GENERIC.fullmatch(str(key)) else str(key)
                if measure == "bound" or _BOUND.fullmatch(str(key)):
                    named = "bound"  # an interval's bound: finite, of either sign (Student's t)
                stack.append((item, f"{where}/{key}", named))
            continue
        if isinstance(value, list):
            stack.extend((item, f"{where}[{i}]", measure) for i, item in enumerate(value))
            continue
        if value is None:
            continue  # a missing number (a non-finite one is written as null)
        if isinstance(value, str | bool) and (
            not _NON_NEGATIVE.fullmatch(measure) or where.startswith("claims/")
        ):
            continue  # a label, a verdict (a claim's threshold is its statement's words)
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise ValueError(f"{what} {path}: {where} holds {short(value)}, not a number: {remedy}")
        kind = next((kind for pattern, kind in _KINDS if pattern.fullmatch(measure)), NUMBER)
        problem = _leaf_problem(value, kind)
        if problem is not None:
            raise ValueError(f"{what} {path}: {where} holds {value!r}, {problem}: {remedy}")
    problem = None if check is None else check(results)  # the command's own (its report's)
    if problem is not None:
        raise ValueError(f"{what} {path}: {problem}: {remedy}")


def read_sealed(
    path: Path,
    what: str,
    remedy: str = REMEDY,
    values: bool = True,
    kept_for: dict[str, Any] | Callable[[dict[str, Any]], dict[str, Any]] | None = None,
    check: Callable[[dict[str, Any]], str | None] | None = None,
) -> dict[str, Any]:
    """The dict kept at ``path`` once its digest, (``kept_for``: ``tie``'s dict, or a function
    of the file's dict giving it) what it was kept for and (``values``) its values are checked,
    the digest and the tie removed; a ValueError naming ``path`` and ``remedy`` otherwise."""
    try:
        results = result_files.read_json(path, (), remedy)
    except (ValueError, OSError) as error:
        raise ValueError(f"{what} {path} is unreadable ({error}): {remedy}") from None
    stored = results.pop(DIGEST_KEY, "")
    if not stored or not isinstance(stored, str):
        raise ValueError(f"{what} {path} has no digest: {remedy}")
    if stored != json_digest(results):
        raise ValueError(f"{what} {path} does not match its digest (edited or damaged): {remedy}")
    stored_tie = results.pop(TIE_KEY, None)
    if callable(kept_for):
        kept_for = kept_for(results)
    if kept_for is not None:
        check_tie(path, what, stored_tie, kept_for, remedy)
    if values:
        check_values(path, what, results, remedy, check)
    return results


def reusable(path: Path, check: Callable[[Path], Any], force: bool) -> bool:
    """Whether the kept file at ``path`` is to be reused: False when there is none, True when
    ``check(path)`` (a ``read_sealed``) accepts it; when it refuses it, False
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


# --------------------------------------------------------------------------------------------
# A unit result against its command's declared schema
#
# A schema is data: a leaf kind (``NUMBER``, ``NON_NEGATIVE``, ``FRACTION``, ``FINITE``,
# ``COUNT``, ``POSITIVE``, ``TEXT``, ``FLAG``) or a frozenset of the texts allowed; ``{"key":
# schema, "key?": schema}`` a dict with exactly these keys (``?``: may be absent), and with
# ``"*": schema`` beside them any other text keys; ``{"*": schema}`` a dict of any text keys;
# ``[schema]`` a list, ``[schema, n]`` one of exactly ``n`` items; ``(None, schema)`` null or
# ``schema`` (a tuple: any of its options). Numbers of the three float kinds may be null (a
# non-finite number is written as null); the others only where ``(None, ...)`` says so.

NUMBER = "number"  # finite
NON_NEGATIVE = "non-negative number"
FRACTION = "fraction"  # in [0, 1]
FINITE = "finite number"  # never null
COUNT = "count"  # whole and >= 0
POSITIVE = "positive count"  # whole and >= 1
TEXT = "text"
FLAG = "flag"  # true or false
_NUMBER_KINDS = (NUMBER, NON_NEGATIVE, FRACTION, FINITE, COUNT, POSITIVE)
#: The kind of a number ``check_values`` meets, by its name alone: the first that matches, else
#: ``NUMBER``.
_KINDS = ((_FRACTION, FRACTION), (_WHOLE, COUNT), (_NON_NEGATIVE, NON_NEGATIVE))


def schema_problem(value: Any, schema: Any, where: str = "result") -> str | None:
    """Why ``value`` does not fit ``schema`` (``where`` it sits, e.g. ``result/summary``), or
    None when it does."""
    if isinstance(schema, tuple):
        problems = [schema_problem(value, option, where) for option in schema if option is not None]
        if (value is None and None in schema) or None in problems:
            return None
        return problems[-1]
    if isinstance(schema, dict):
        if not isinstance(value, dict):
            return f"{where} holds {short(value)}, not a mapping"
        declared = {key.rstrip("?"): key for key in schema if key != "*"}
        for key, item in value.items():
            if key in declared:
                continue
            if "*" not in schema:
                return f"{where} holds {short(key)}, not one of its keys ({', '.join(declared)})"
            problem = schema_problem(item, schema["*"], f"{where}/{key}")
            if problem is not None:
                return problem
        for name, key in declared.items():
            if name not in value:
                if key.endswith("?"):
                    continue
                return f"{where} lacks {name!r}"
            problem = schema_problem(value[name], schema[key], f"{where}/{name}")
            if problem is not None:
                return problem
        return None
    if isinstance(schema, list):
        if not isinstance(value, list):
            return f"{where} holds {short(value)}, not a list"
        if len(schema) == 2 and len(value) != schema[1]:
            return f"{where} holds {len(value)} items, not {schema[1]}"
        if isinstance(schema[0], str) and _plain_numbers(value, schema[0]):
            return None  # the common case, checked at C speed; the loop below says what is wrong
        for index, item in enumerate(value):
            problem = schema_problem(item, schema[0], f"{where}[{index}]")
            if problem is not None:
                return problem
        return None
    if isinstance(schema, frozenset):
        if isinstance(value, str) and value in schema:
            return None
        return f"{where} holds {short(value)}, not one of {', '.join(sorted(schema))}"
    problem = _leaf_problem(value, schema)
    return None if problem is None else f"{where} holds {short(value)}, {problem}"


def _plain_numbers(values: list[Any], kind: str) -> bool:
    """Whether every item of ``values`` is a plain number that fits ``kind`` (ints for a count;
    ints or floats, finite, in range, for the others): a quick yes, or no to look closer."""
    kinds = set(map(type, values))
    if kind == COUNT:
        return kinds <= {int} and (not values or min(values) >= 0)
    if kind not in (NUMBER, NON_NEGATIVE, FRACTION, FINITE) or not kinds <= {int, float}:
        return False
    if not all(map(math.isfinite, values)):
        return False
    low, high = (min(values), max(values)) if values else (0, 0)
    return (kind in (NUMBER, FINITE) or low >= 0) and (kind != FRACTION or high <= 1)


def _leaf_problem(value: Any, kind: str) -> str | None:
    if kind == TEXT:
        return None if isinstance(value, str) else "not a text"
    if kind == FLAG:
        return None if isinstance(value, bool) else "not true or false"
    if kind not in _NUMBER_KINDS:
        raise RuntimeError(f"a declared schema names the kind {kind!r}: not one of kept's")
    if value is None and kind in (NUMBER, NON_NEGATIVE, FRACTION):
        return None  # a missing number (a non-finite one is written as null)
    if isinstance(value, bool) or not isinstance(value, int | float):
        return "not a number"
    try:  # an int past a float's range (JSON reads any number of digits) is not finite either
        finite = math.isfinite(value)
    except OverflowError:
        finite = False
    if not finite:
        return "not a finite number"
    if kind not in (NUMBER, FINITE) and value < 0:
        return "negative"
    if kind == FRACTION and value > 1:
        return "not a fraction in [0, 1]"
    if kind in (COUNT, POSITIVE) and value != math.floor(value):
        return "not a whole count"
    if kind == POSITIVE and value < 1:
        return "not a count >= 1"
    return None


# --------------------------------------------------------------------------------------------
# The units of one run, kept in OUT/units/

UNITS_DIRECTORY = "units"
RUN_FILE = "run.json"
UNITS_FORMAT = "factorq-units"
UNIT_FILE = "unit file"


def unit_path(directory: Path, unit_id: str) -> Path:
    """Where unit ``unit_id``'s result is kept in ``directory`` (``OUT/units/``)."""
    return directory / f"{hashlib.sha256(unit_id.encode()).hexdigest()[:20]}.json"


class UnitStore:
    """The finished units of one run, in ``OUT/units/``: ``run.json`` (the command, its config
    and unit ids, sealed) and one ``<digest of the id>.json`` per finished unit (its result,
    sealed and tied to the command, the config's digest and the unit)."""

    def __init__(self, out: str | Path) -> None:
        self.directory = Path(out) / UNITS_DIRECTORY

    def exists(self) -> bool:
        return self.directory.exists()

    def start(self, command: str, config: dict[str, Any], unit_ids: Iterable[str]) -> None:
        """A fresh run of ``command`` with ``config`` (its JSON dict): an empty store."""
        shutil.rmtree(self.directory, ignore_errors=True)
        self.directory.mkdir(parents=True)
        record = {"format": UNITS_FORMAT, "command": command, "config": config}
        record["units"] = list(unit_ids)
        write_sealed(self.directory / RUN_FILE, record, tie(command, config))
        self.kept_for = tie(command, config)

    def saved_run(self, command: str) -> dict[str, Any]:
        """``run.json`` of an interrupted run of ``command``, sealed and consistent (a
        ValueError naming it and why not); its ``config`` ties the units read after it."""
        path = self.directory / RUN_FILE
        remedy = "start the run over with --force instead of --resume"
        if not path.is_file() and not path.exists():
            raise ValueError(
                f"{path} does not exist: nothing to resume: run `factorq {command}` without "
                f"--resume"
            )
        record = read_sealed(
            path, "run file", remedy, False, lambda saved: tie(command, saved.get("config"))
        )
        if record.get("format") != UNITS_FORMAT or record.get("command") != command:
            raise ValueError(
                f"run file {path} is not an interrupted `factorq {command}` run (command "
                f"{short(record.get('command'))}): {remedy}"
            )
        config = record.get("config")
        if not isinstance(config, dict):
            raise ValueError(f"run file {path}: its config is not a mapping: {remedy}")
        self.kept_for = tie(command, config)
        return record

    def finished(
        self,
        units: list[dict[str, Any]],
        schema: Any,
        force: bool,
        check: Callable[[dict[str, Any], Any], str | None] | None = None,
    ) -> dict[str, Any]:
        """Unit id -> its result, for every unit with a kept file that passes its checks (its
        digest, tie, ``schema`` and ``check(unit, result)``, the command's own: why it cannot be
        the unit's, or None); one that fails is refused (a ValueError naming it), or with
        ``force`` left to recompute. ``saved_run`` first: it says which run the units are of."""
        found = {}
        remedy = "pass --force (with --resume) to recompute it"

        def read(unit: dict[str, Any], path: Path) -> None:
            expected = {**self.kept_for, "unit": json.loads(result_files.dumps(unit))}
            record = read_sealed(path, UNIT_FILE, remedy, values=False, kept_for=expected)
            if set(record) != {"result"}:
                raise ValueError(
                    f"{UNIT_FILE} {path} holds {short(sorted(record))}, not a unit's result: "
                    f"{remedy}"
                )
            result = record["result"]
            problem = schema_problem(result, schema)
            for key, label in unit.items():  # the labels it repeats must be the unit's
                if problem is None and key != "id" and key in result and result[key] != label:
                    problem = (
                        f"its result's {key} is {short(result[key])}, but it is kept for unit "
                        f"{unit['id']!r}, whose {key} is {label!r}"
                    )
            if problem is None and check is not None:
                problem = check(unit, result)
            if problem is not None:
                raise ValueError(f"{UNIT_FILE} {path}: {problem}: {remedy}")
            found[unit["id"]] = result

        for unit in units:
            reusable(unit_path(self.directory, unit["id"]), functools.partial(read, unit), force)
        return found

    def keep(self, unit: dict[str, Any], result: Any) -> None:
        """Keep ``unit``'s ``result`` (as JSON gives it back: ``frame.unit_result``'s) after
        ``start`` or ``saved_run``."""
        unit = json.loads(result_files.dumps(unit))
        kept_for = {**self.kept_for, "unit": unit}
        write_sealed(unit_path(self.directory, unit["id"]), {"result": result}, kept_for, True)

    def remove(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)
