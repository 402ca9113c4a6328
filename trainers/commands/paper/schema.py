"""The results file's schema: versioned, and checked field by field before anything reads it.

A ``results.json`` handed to ``factorq report`` is untrusted input: it may be hand-edited,
truncated, of another version or of another shape altogether. ``factorq report`` reads it with
size and nesting limits (``runner.results.read_json``) and ``check_results`` checks every field the
report reads (type, range, lengths that must agree) so that drawing the figure and writing the
Markdown cannot fail on it; any problem is one line naming the file (``reports.check_results``),
the field's path and what was expected.

Versions: ``SCHEMA_VERSION`` is written into every results file and checked here: a file without
the field or of a newer version is refused.
"""

from __future__ import annotations

import math
import re
from typing import Any

from factorq_envs.regimes import REGIMES
from factorq_torch.base.config import ALGORITHMS as ALGORITHM_NAMES
from factorq_torch.base.keys import EPISODE_METRICS
from factorq_trainers.analysis.claims import CLAIM_STATEMENTS, MEASURES
from factorq_trainers.runner.results import SCHEMA_VERSION

#: The per-episode curves a results file holds per cell (task return is reported per run).
CURVE_NAMES = EPISODE_METRICS[:3]
CLAIM_NAMES = tuple(CLAIM_STATEMENTS)

SUMMARY_MEASURES = (*MEASURES, "task_return")


class ResultsFileError(ValueError):
    """A results file that cannot be read, with the field and what was expected."""


def _fail(where: str, expected: str, value: Any) -> None:
    shown = repr(value)
    shown = shown if len(shown) <= 40 else shown[:37] + "..."
    raise ResultsFileError(f"{where} must be {expected}, got {shown}")


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _mapping(value: Any, where: str, keys: tuple[str, ...] = ()) -> dict[str, Any]:
    if not isinstance(value, dict):
        _fail(where, "an object", value)
    missing = [key for key in keys if key not in value]
    if missing:
        raise ResultsFileError(f"{', '.join(missing)} missing in {where}")
    return value


def _number(value: Any, where: str, *, optional: bool = False, low: float = -math.inf) -> None:
    """A finite number (or null where ``optional``: non-finite values are written as null)."""
    if value is None and optional:
        return
    if not _is_number(value) or not math.isfinite(value) or value < low:
        _fail(where, "a finite number" + (f" >= {low:g}" if low > -math.inf else ""), value)


def _integer(value: Any, where: str, low: int, high: int = 2**63 - 1) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        _fail(where, f"an integer in [{low}, {high}]", value)
    return value


def _text(value: Any, where: str) -> None:
    if not isinstance(value, str):
        _fail(where, "a string", value)


def _numbers(value: Any, where: str, length: int | None, *, optional_items: bool = True) -> None:
    if not isinstance(value, list) or (length is not None and len(value) != length):
        _fail(where, "a list" + (f" of {length} numbers" if length is not None else ""), value)
    for index, item in enumerate(value):
        _number(item, f"{where}[{index}]", optional=optional_items)


def _interval(value: Any, where: str) -> None:
    if value is not None:
        _numbers(value, where, 2)


def _names(value: Any, where: str, allowed: tuple[str, ...]) -> list[str]:
    if not isinstance(value, list) or not value:
        _fail(where, f"a non-empty list of names from {', '.join(allowed)}", value)
    for index, item in enumerate(value):
        if item not in allowed:
            _fail(f"{where}[{index}]", f"one of {', '.join(allowed)}", item)
    return value


def _check_config(config: Any) -> dict[str, Any]:
    config = _mapping(
        config,
        "config",
        ("seeds", "runs", "episodes", "size", "obstacles", "regimes", "methods"),
    )
    for key, value in config.items():
        if not isinstance(key, str):
            _fail("config keys", "strings", key)
        scalars = (str, int, float, bool, type(None))
        if not isinstance(value, scalars) and not (
            isinstance(value, list) and all(isinstance(item, scalars) for item in value)
        ):
            _fail(f"config.{key}", "a number, string, boolean or list of them", value)
    _integer(config["seeds"], "config.seeds", 1)
    _integer(config["runs"], "config.runs", 1)
    _integer(config["episodes"], "config.episodes", 1)
    _integer(config["size"], "config.size", 1)
    _integer(config["obstacles"], "config.obstacles", 0)
    _names(config["regimes"], "config.regimes", REGIMES)
    _names(config["methods"], "config.methods", ALGORITHM_NAMES)
    return config


def _check_cell(cell: Any, where: str, seeds: int, episodes: int) -> None:
    cell = _mapping(
        cell, where, ("per_seed", "summary", "curves", "curves_ci_low", "curves_ci_high")
    )
    per_seed = _mapping(cell["per_seed"], f"{where}.per_seed")
    for measure, values in per_seed.items():
        _numbers(values, f"{where}.per_seed.{measure}", seeds)
    summary = _mapping(cell["summary"], f"{where}.summary", SUMMARY_MEASURES)
    for measure in SUMMARY_MEASURES:
        entry = _mapping(summary[measure], f"{where}.summary.{measure}", ("mean", "ci95"))
        _number(entry["mean"], f"{where}.summary.{measure}.mean", optional=True)
        _interval(entry["ci95"], f"{where}.summary.{measure}.ci95")
    curves = _mapping(cell["curves"], f"{where}.curves", CURVE_NAMES)
    for name in CURVE_NAMES:
        _numbers(curves[name], f"{where}.curves.{name}", episodes, optional_items=False)
    for band in ("curves_ci_low", "curves_ci_high"):
        bands = _mapping(cell[band], f"{where}.{band}", CURVE_NAMES)
        for name in CURVE_NAMES:
            if bands[name] is not None:
                _numbers(bands[name], f"{where}.{band}.{name}", episodes, optional_items=False)


def _check_claim_value(value: Any, ci: Any, where: str) -> None:
    """A claim's value and interval: numbers, or one of each per algorithm (C4)."""
    if not isinstance(value, dict):
        _number(value, f"{where}.value", optional=True)
        _interval(ci, f"{where}.ci95")
        return
    for key, item in value.items():
        if key not in ALGORITHM_NAMES:
            _fail(f"{where}.value keys", f"algorithm names ({', '.join(ALGORITHM_NAMES)})", key)
        _number(item, f"{where}.value.{key}", optional=True)
    if ci is not None:
        if not isinstance(ci, dict) or set(ci) != set(value):
            _fail(f"{where}.ci95", f"null or an object with keys {', '.join(value)}", ci)
        for key, item in ci.items():
            _interval(item, f"{where}.ci95.{key}")


def _check_claim(claim: Any, where: str) -> None:
    claim = _mapping(
        claim, where, ("statement", "threshold", "value", "ci95", "pass", "detail", "measures")
    )
    for key in ("statement", "threshold", "detail"):
        _text(claim[key], f"{where}.{key}")
    _check_claim_value(claim["value"], claim["ci95"], where)
    if claim["pass"] not in (True, False, None):
        _fail(f"{where}.pass", "true, false or null", claim["pass"])
    if not isinstance(claim["measures"], list):
        _fail(f"{where}.measures", "a list", claim["measures"])
    for index, measure in enumerate(claim["measures"]):
        at = f"{where}.measures[{index}]"
        measure = _mapping(measure, at, ("name", "value", "ci95", "pass"))
        _text(measure["name"], f"{at}.name")
        _number(measure["value"], f"{at}.value", optional=True)
        _interval(measure["ci95"], f"{at}.ci95")
        if measure["pass"] not in (True, False, None):
            _fail(f"{at}.pass", "true, false or null", measure["pass"])


def check_results(results: Any) -> dict[str, Any]:
    """Check every field the report reads; return ``results`` or raise a ResultsFileError."""
    results = _mapping(results, "the file", ("config", "cells", "claims"))
    if "schema_version" not in results:
        raise ResultsFileError(
            "schema_version missing: written before results files were versioned (rerun "
            "`factorq paper` to write it again)"
        )
    version = results["schema_version"]
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        _fail("schema_version", "a positive integer", version)
    if version > SCHEMA_VERSION:
        raise ResultsFileError(
            f"schema_version {version} is newer than this factorq-torch reads "
            f"({SCHEMA_VERSION}): upgrade factorq-torch to read it"
        )
    config = _check_config(results["config"])
    cells = _mapping(results["cells"], "cells")
    for world in config["regimes"]:
        for algorithm in config["methods"]:
            key = f"{world}/{algorithm}"
            if key not in cells:
                raise ResultsFileError(f"cells lacks {key} (config.regimes x config.methods)")
            _check_cell(cells[key], f"cells.{key}", config["seeds"], config["episodes"])
    claims = _mapping(results["claims"], "claims")
    for name, claim in claims.items():
        if name not in CLAIM_NAMES:
            _fail("claims keys", f"claim names ({', '.join(CLAIM_NAMES)})", name)
        _check_claim(claim, f"claims.{name}")
    for optional in ("statistics", "software"):
        for key, value in _mapping(results.get(optional, {}), optional).items():
            if not isinstance(value, str | int | float | bool | type(None)):
                _fail(f"{optional}.{key}", "a string or number", value)
    timing = _mapping(results.get("timing", {}), "timing")
    if timing:
        _mapping(timing, "timing", ("wall_s", "backend", "threads", "env_steps"))
        _number(timing["wall_s"], "timing.wall_s", low=0)
        _integer(timing["threads"], "timing.threads", 1)
        _integer(timing["env_steps"], "timing.env_steps", 0)
        _text(timing["backend"], "timing.backend")
    return results


_MARKDOWN_SPECIAL = str.maketrans({char: "\\" + char for char in "\\`*_|"})
#: ``<`` opens raw HTML only before a letter, ``/``, ``!`` or ``?`` (``<=`` stays as it is).
_HTML_OPENING = re.compile(r"<(?=[A-Za-z/!?])")


def escape_markdown(text: Any) -> str:
    """``text`` as literal Markdown table-cell text: specials escaped, line breaks as spaces."""
    escaped = " ".join(str(text).split()).translate(_MARKDOWN_SPECIAL)
    return _HTML_OPENING.sub("&lt;", escaped).replace("](", "]\\(")  # no link or image


def markdown_code(text: Any) -> str:
    """``text`` as one Markdown code span in a table cell, whatever backticks or pipes it holds."""
    text = " ".join(str(text).split()).replace("|", "\\|")
    longest = max((len(run) for run in re.findall(r"`+", text)), default=0)
    fence = "`" * (longest + 1)
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"
