"""Command-line options from config dataclasses: docs from field metadata, lists, choices."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import pytest

from factorq_trainers.commands.compare.config import CompareConfig
from factorq_trainers.commands.paper.config import PaperConfig
from factorq_trainers.runner import options
from factorq_trainers.runner.options import option


@dataclass(frozen=True)
class Inner:
    rate: float = option(0.5, "A nested rate.")


@dataclass(frozen=True)
class Example:
    count: int = option(3, "How many, at 100% or less.")
    names: tuple[str, ...] = option(("a", "b"), "Names to use.")
    mode: str = option("fast", "How to run.", choices=("fast", "slow"))
    threads: int | None = option(None, "Threads.")
    inner: Inner = option(Inner(), "Not an option: a nested config.")


def parser() -> argparse.ArgumentParser:
    made = argparse.ArgumentParser(prog="example", exit_on_error=False)
    options.add_options(made, Example)
    return made


def test_every_plain_field_is_an_option_with_its_doc_and_default():
    text = " ".join(parser().format_help().split())
    assert "--count COUNT How many, at 100% or less. (default: 3)" in text
    assert "--names NAME[,NAME] Names to use. Repeatable. (default: a,b)" in text
    assert "--threads THREADS Threads. (default: auto)" in text
    assert "--inner" not in text and "--rate" not in text


def test_only_given_options_are_returned_with_lists_split_and_typed():
    args = parser().parse_args(["--names", "c,d", "--names", "e", "--count", "4"])
    assert options.given_options(args, Example) == {"count": 4, "names": ["c", "d", "e"]}
    assert options.given_options(parser().parse_args([]), Example) == {}


def test_an_optional_field_takes_auto_for_none_and_its_type_otherwise():
    # the help shows "(default: auto)": a user can give that word back, as for any default
    assert options.given_options(parser().parse_args(["--threads", "auto"]), Example) == {
        "threads": None
    }
    assert options.given_options(parser().parse_args(["--threads", "2"]), Example) == {"threads": 2}
    with pytest.raises(argparse.ArgumentError, match="invalid int value: 'two'"):
        parser().parse_args(["--threads", "two"])
    with pytest.raises(argparse.ArgumentError, match="invalid int value: 'auto'"):
        parser().parse_args(["--count", "auto"])  # not optional: no auto


def test_choices_come_from_the_field():
    with pytest.raises(argparse.ArgumentError, match="invalid choice: 'medium'"):
        parser().parse_args(["--mode", "medium"])


@pytest.mark.parametrize("config", [PaperConfig, CompareConfig])
def test_every_option_of_the_commands_has_a_one_line_doc(config):
    for field in options.option_fields(config):
        doc = field.metadata.get("doc")
        assert doc and "\n" not in doc, field.name
