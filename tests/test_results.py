"""Result files: strict JSON with number lists on one line, atomic writes, schema versions."""

from __future__ import annotations

import json

import pytest

from factorq_trainers.runner.results import SCHEMA_VERSION, read_json, write_atomic
from factorq_trainers.runner.results import dumps as dumps_results


def test_results_json_keeps_number_lists_on_one_line_and_is_strict_json():
    text = dumps_results({"a": [1.0, 2.5], "b": {"c": [float("inf"), 3]}, "d": "x"})
    assert '"a": [1.0, 2.5]' in text
    assert json.loads(text) == {"a": [1.0, 2.5], "b": {"c": [None, 3]}, "d": "x"}


def test_write_atomic_leaves_the_old_file_when_writing_fails(tmp_path):
    target = tmp_path / "results.json"
    target.write_text("old")

    def broken(path):
        path.write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_atomic(target, broken)
    assert target.read_text() == "old"
    assert [path.name for path in tmp_path.iterdir()] == ["results.json"]


def test_json_without_a_schema_version_is_read_as_it_is_and_a_newer_one_is_refused(tmp_path):
    path = tmp_path / "results.json"
    path.write_text(dumps_results({"config": {}, "cells": {}}))
    assert read_json(path, ("config", "cells"), "make it") == {"config": {}, "cells": {}}
    path.write_text(dumps_results({"config": {}, "schema_version": SCHEMA_VERSION + 1}))
    with pytest.raises(ValueError, match=r"schema_version=2, newer than this factorq reads \(1\)"):
        read_json(path, ("config",), "make it")


def test_reading_names_what_is_wrong_with_the_file(tmp_path):
    path = tmp_path / "results.json"
    with pytest.raises(FileNotFoundError, match="results.json does not exist: make it"):
        read_json(path, (), "make it")
    path.write_text("[1, 2]")
    with pytest.raises(ValueError, match="is not a results file: it holds no JSON object"):
        read_json(path, (), "make it")
    path.write_text('{"config": {}}')
    with pytest.raises(ValueError, match="is not a results file: cells, claims missing"):
        read_json(path, ("config", "cells", "claims"), "make it")
