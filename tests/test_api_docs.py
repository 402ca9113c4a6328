"""Every name a package exports (its ``__all__``, and the public functions of a module it
exports) that takes arguments documents them in an ``Args:`` section (issue 28: the API
reference reads them; a class may keep them in its own docstring or its ``__init__``'s)."""

import importlib
import inspect

import pytest

PACKAGES = ("factorq_torch", "factorq_envs")


def _exported(package: str) -> list[tuple[str, object]]:
    """The names of ``package.__all__``; for an exported module (``factorq_torch.functional``),
    the public functions and classes defined in it."""
    module = importlib.import_module(package)
    found = []
    for name in module.__all__:
        obj = getattr(module, name)
        if inspect.ismodule(obj):
            found += [
                (f"{name}.{inner}", value)
                for inner, value in vars(obj).items()
                if not inner.startswith("_") and getattr(value, "__module__", None) == obj.__name__
            ]
        else:
            found.append((name, obj))
    return found


def _arguments(obj: object) -> list[str]:
    try:
        signature = inspect.signature(obj)  # a class: its constructor's
    except (TypeError, ValueError):  # a builtin without a signature
        return []
    return [name for name in signature.parameters if name not in ("self", "cls")]


def _docstrings(obj: object) -> str:
    text = inspect.getdoc(obj) or ""
    if inspect.isclass(obj) and "__init__" in vars(obj):
        text += "\n" + (inspect.getdoc(vars(obj)["__init__"]) or "")
    return text


@pytest.mark.parametrize("package", PACKAGES)
def test_every_exported_name_that_takes_arguments_has_an_args_section(package):
    missing = [
        name
        for name, obj in _exported(package)
        if (inspect.isclass(obj) or inspect.isfunction(obj))
        and _arguments(obj)
        and "Args:" not in _docstrings(obj)
    ]
    assert not missing, f"{package} exports names without an Args: section: {missing}"


def test_the_check_sees_a_missing_section():
    """The check itself: a function with arguments and no ``Args:`` is caught, one without
    arguments or with the section is not."""

    def documented(x):
        """Doubles.

        Args:
            x: a number.
        """

    def undocumented(x):
        """Doubles ``x``."""

    def no_arguments():
        """Nothing to document."""

    class Config:
        """A config.

        Args:
            size: the side.
        """

        def __init__(self, size):
            self.size = size

    for obj, flagged in ((documented, False), (undocumented, True), (no_arguments, False)):
        assert (bool(_arguments(obj)) and "Args:" not in _docstrings(obj)) is flagged
    assert _arguments(Config) == ["size"] and "Args:" in _docstrings(Config)
