"""The results file's schema: versioned, and checked field by field before anything reads it.

A ``results.json`` handed to ``factorq report`` is untrusted (hand-edited, truncated, of another
version or shape): read with size and nesting limits (``runner.results.read_json``), then
``results_problem`` checks every field the report reads (type, range, lengths that must agree), so
that the figure and the Markdown cannot fail on it; a problem is one line naming the file, the
field's path and what was expected. A file without ``SCHEMA_VERSION`` or of a newer one is refused.
"""

from __future__ import annotations

import re
from typing import Any

from factorq_envs.regimes import REGIMES
from factorq_torch.base.config import ALGORITHMS as ALGORITHM_NAMES
from factorq_torch.base.keys import EPISODE_METRICS
from factorq_trainers.analysis.claims import CLAIM_STATEMENTS, MEASURES
from factorq_trainers.runner.kept import COUNT, FINITE, FLAG, NUMBER, POSITIVE, TEXT, schema_problem
from factorq_trainers.runner.results import SCHEMA_VERSION

#: The per-episode curves a results file holds per cell (task return is reported per run).
CURVE_NAMES = EPISODE_METRICS[:3]
CLAIM_NAMES = tuple(CLAIM_STATEMENTS)

SUMMARY_MEASURES = (*MEASURES, "task_return")


_SCALAR = (None, NUMBER, TEXT, FLAG)
_INTERVAL = (None, [NUMBER, 2])
#: The config's entries the report reads; its other settings are numbers, texts, flags or lists.
_CONFIG = {
    **{name: POSITIVE for name in ("seeds", "runs", "episodes", "size")},
    "obstacles": COUNT,
    "regimes": [frozenset(REGIMES)],
    "methods": [frozenset(ALGORITHM_NAMES)],
    "*": (*_SCALAR, [_SCALAR]),
}
_CLAIM = {
    "statement": TEXT,
    "threshold": TEXT,
    "detail": TEXT,
    # a number, or one per algorithm (C4) with its interval per algorithm (``_claims_problem``)
    "value": (None, NUMBER, {f"{name}?": NUMBER for name in ALGORITHM_NAMES}),
    "ci95": (*_INTERVAL, {f"{name}?": _INTERVAL for name in ALGORITHM_NAMES}),
    "pass": (None, FLAG),
    "measures": [{"name": TEXT, "value": NUMBER, "ci95": _INTERVAL, "pass": (None, FLAG)}],
}


def results_schema(config: dict[str, Any]) -> dict[str, Any]:
    """``results.json``'s schema (``runner.kept``'s terms) for a checked ``config``: per-seed
    lists of ``seeds`` numbers, curves of ``episodes`` (never null: the figure draws them)."""
    curves = {name: [FINITE, config["episodes"]] for name in CURVE_NAMES}
    bands = {name: (None, [FINITE, config["episodes"]]) for name in CURVE_NAMES}
    cell = {
        "world?": TEXT,
        "algorithm?": TEXT,
        "obstacle_period?": COUNT,
        "per_seed": {"*": [NUMBER, config["seeds"]]},
        "summary": {name: {"mean": NUMBER, "ci95": _INTERVAL} for name in SUMMARY_MEASURES},
        "curves": curves,
        "curves_ci_low": bands,
        "curves_ci_high": bands,
    }
    return {
        "schema_version": POSITIVE,
        "command?": TEXT,
        "config": _CONFIG,
        "cells": {"*": cell},
        "claims": {f"{name}?": _CLAIM for name in CLAIM_NAMES},
        "statistics?": {"*": _SCALAR},
        "software?": {"*": _SCALAR},
        "timing?": {
            "wall_s": FINITE,  # >= 0: ``check_values``, by its name
            "threads": POSITIVE,
            "env_steps": COUNT,
            "backend": TEXT,
            "*": _SCALAR,
        },
    }


def results_problem(results: Any) -> str | None:
    """What is wrong with a ``results.json`` dict against the paper's schema (every field the
    report reads), in one line, or None: ``factorq report`` refuses the file with it before
    drawing (``reports.check_results``), as it does with any command's ``results_problem``."""
    if not isinstance(results, dict):
        return "the file holds no JSON object"
    missing = [key for key in ("config", "cells", "claims") if key not in results]
    if missing:
        return f"{', '.join(missing)} missing in the file"
    if "schema_version" not in results:
        return (
            "schema_version missing: written before results files were versioned (rerun "
            "`factorq paper` to write it again)"
        )
    version = results["schema_version"]
    if isinstance(version, int) and not isinstance(version, bool) and version > SCHEMA_VERSION:
        return (
            f"schema_version {version} is newer than this factorq-torch reads "
            f"({SCHEMA_VERSION}): upgrade factorq-torch to read it"
        )
    config = results["config"]
    problem = schema_problem(config, _CONFIG, "results/config")
    if problem is not None:
        return problem
    for name in ("regimes", "methods"):
        if not config[name]:
            return f"results/config/{name} is empty"
    problem = schema_problem(results, results_schema(config), "results")
    if problem is not None:
        return problem
    for world in config["regimes"]:
        for algorithm in config["methods"]:
            if f"{world}/{algorithm}" not in results["cells"]:
                return f"results/cells lacks {world}/{algorithm} (config/regimes x config/methods)"
    for name, claim in results["claims"].items():
        value, ci = claim["value"], claim["ci95"]
        if isinstance(value, dict) and ci is not None and set(ci) != set(value):
            return f"results/claims/{name}/ci95 must be null or name the algorithms of its value"
        if isinstance(ci, dict) != isinstance(value, dict) and ci is not None:
            return f"results/claims/{name}/ci95 does not fit its value"
    return None


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
