"""One method vocabulary (``factorq_trainers.analysis.vocabulary``): every command's ``--methods``
takes names from it, every name in it is some command's, and one name is one label everywhere."""

from __future__ import annotations

import dataclasses
import re

import pytest

from factorq_trainers.analysis import vocabulary
from factorq_trainers.runner import registry


def command_methods() -> dict[str, tuple[str, ...]]:
    """Each command's method names: what its config's ``methods`` accepts."""
    found = {}
    for name in registry.commands():
        module = registry.load(name)
        field = next(f for f in dataclasses.fields(module.CONFIG) if f.name == "methods")
        with pytest.raises(ValueError) as refused:
            module.CONFIG(methods="no-such-method")
        choices = re.search(r"choose (?:from|one or more of) (.*)", str(refused.value))
        assert choices, f"{name}: {refused.value}"
        allowed = choices.group(1).split(", ")
        assert field.default and set(field.default) <= set(allowed), name
        found[name] = tuple(allowed)
    return found


def test_every_command_takes_its_methods_from_the_vocabulary_and_uses_every_name():
    methods = command_methods()
    assert set(methods) == set(registry.commands())
    used = {method for names in methods.values() for method in names}
    assert used <= set(vocabulary.METHODS), used - set(vocabulary.METHODS)
    assert set(vocabulary.METHODS) <= used, set(vocabulary.METHODS) - used
    # the agents several commands share have one name in all of them
    assert all("factor-q" in methods[name] for name in ("paper", "compare", "dependencies"))
    assert all("factor-q" in methods[name] for name in ("minigrid", "transfer"))
    assert all("dqn" in methods[name] for name in ("compare", "gym", "minigrid", "risk"))


def test_among_refuses_a_name_outside_the_vocabulary():
    assert vocabulary.among("factor-q", "dqn") == ("factor-q", "dqn")
    with pytest.raises(ValueError, match="'oracle'"):
        vocabulary.among("factor-q", "oracle")


def test_labels_are_one_per_name_and_an_unknown_name_draws_as_itself():
    labels = list(vocabulary.METHODS.values())
    assert len(set(labels)) == len(labels)
    assert vocabulary.label("factor-q") == "Factor-Q"  # the paper's figure and report
    assert vocabulary.label("edited-by-hand") == "edited-by-hand"
