"""The results file is untrusted input: checked field by field before the report reads it."""

from __future__ import annotations

import copy
import json
import random
import re

import pytest
from test_report import synthetic_results

from factorq_trainers.commands.paper import report
from factorq_trainers.commands.paper.schema import (
    escape_markdown,
    markdown_code,
    results_problem,
)
from factorq_trainers.reports import regenerate
from factorq_trainers.runner.reading import MAX_DEPTH
from factorq_trainers.runner.results import SCHEMA_VERSION

BAD_VALUES = (None, "x", -1, 0, 2.5, True, [], {}, [1, 2], {"a": 1}, float("nan"), 10**30)


@pytest.fixture(scope="module")
def results():
    return json.loads(json.dumps(synthetic_results(seeds=3, runs=1, episodes=4)))


def paths_of(value, prefix=()):
    """Every path to a field of a JSON tree (lists: the first, a middle and the last item)."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield (*prefix, key)
            yield from paths_of(item, (*prefix, key))
    elif isinstance(value, list) and value:
        for index in sorted({0, len(value) // 2, len(value) - 1}):
            yield (*prefix, index)
            yield from paths_of(value[index], (*prefix, index))


def set_at(tree, path, value):
    """``tree`` with the node at ``path`` replaced by ``value`` (deleted for ``KeyError``): the
    containers on the path are copied, the rest is shared with ``tree`` (a deep copy per mutation
    was half the test's time), so the tests below check that ``tree`` is unchanged at the end."""
    mutated = copy.copy(tree)
    node = mutated
    for step in path[:-1]:
        node[step] = copy.copy(node[step])
        node = node[step]
    if value is KeyError:
        if isinstance(node, dict):
            del node[path[-1]]
        else:
            node.pop(path[-1])
    else:
        node[path[-1]] = value
    return mutated


def test_a_real_results_file_passes(results):
    assert results_problem(results) is None


def test_every_mutated_field_is_refused_cleanly_or_still_renders(results):
    """Each field replaced by each wrong value, or deleted: a one-line problem, or a report."""
    before = json.dumps(results, sort_keys=True)
    refused = rendered = 0
    for path in paths_of(results):
        for value in (*BAD_VALUES, KeyError):
            mutated = set_at(results, path, value)
            problem = results_problem(mutated)
            if problem is not None:
                assert "\n" not in problem
                refused += 1
                continue
            report.markdown(mutated)  # must not raise: the check let it through
            rendered += 1
    assert refused > 1000 and rendered > 0
    assert json.dumps(results, sort_keys=True) == before  # nothing changed what set_at shares


def test_a_sample_of_accepted_mutations_draws_the_figure(results, tmp_path):
    chooser = random.Random(0)
    drawn = 0
    before = json.dumps(results, sort_keys=True)
    candidates = list(paths_of(results))
    while drawn < 5:
        mutated = set_at(results, chooser.choice(candidates), chooser.choice(BAD_VALUES))
        if results_problem(mutated) is not None:
            continue
        report.figure3(mutated, tmp_path / f"{drawn}.png")
        drawn += 1
    assert json.dumps(results, sort_keys=True) == before


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("5", "it holds no JSON object"),
        ("[]", "it holds no JSON object"),
        ('{"config": {}, "schema_version": 1}', "cells, claims missing"),
        ('{"config": {}, "cells": {}, "claims": {}}', "has no schema_version"),
        (
            '{"schema_version": 1, "config": {}, "cells": {}, "claims": {}}',
            "results/config lacks 'seeds'",
        ),
        (
            '{"schema_version": 1, "config": {}, "cells": {"x": {"collisions": -1}}, "claims": {}}',
            "cells/x/collisions holds -1, negative",
        ),
        ("{", "is not valid JSON"),
        ("[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1), f"nests deeper than {MAX_DEPTH} levels"),
        ("[" * 100_000, f"nests deeper than {MAX_DEPTH} levels"),
    ],
)
def test_malformed_files_get_one_line_naming_the_file(tmp_path, content, message):
    path = tmp_path / "results.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=message) as error:
        regenerate(tmp_path)
    assert str(path) in str(error.value) and "\n" not in str(error.value)
    assert sorted(child.name for child in tmp_path.iterdir()) == ["results.json"]  # nothing drawn


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        (("config", "seeds"), 0, r"results/config/seeds holds 0, not a count >= 1"),
        (("cells",), [], r"results/cells holds \[\], not a mapping"),
        (("cells", "static/q-learning", "curves", "steps"), [1.0], "steps holds 1 items, not 4"),
        (("claims", "C9"), {}, "results/claims holds 'C9', not one of its keys"),
        (("config", "regimes"), ["lava"], r"config/regimes\[0\] holds 'lava', not one of dynamic"),
        (("schema_version",), SCHEMA_VERSION + 1, "newer than this factorq-torch reads"),
        (("schema_version",), "1", "results/schema_version holds '1', not a number"),
    ],
)
def test_wrong_fields_are_named_with_what_was_expected(results, path, value, message):
    assert re.search(message, results_problem(set_at(results, path, value)) or "")


def test_a_file_written_before_versioning_is_refused(results):
    legacy = {key: value for key, value in results.items() if key != "schema_version"}
    assert "schema_version missing: written before" in (results_problem(legacy) or "")


def test_markdown_specials_are_escaped_and_lines_joined():
    assert escape_markdown("a|b `c` <script>\n*d* <= 1") == r"a\|b \`c\` &lt;script> \*d\* <= 1"
    assert escape_markdown("in [0.8, 1.25] ![x](http://e)") == r"in [0.8, 1.25] ![x]\(http://e)"


def test_code_spans_hold_backticks_and_pipes():
    assert markdown_code("a") == "`a`"
    assert markdown_code("x`` | y") == r"```x`` \| y```"
    assert markdown_code("`start") == "`` `start ``"
