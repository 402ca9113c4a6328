"""A griffe extension for the API reference: docstring examples render as code.

The project's docstrings carry doctests (they run in the tests) either free-standing or under an
``Example:`` heading. Google-style parsing treats both as Markdown text, where an expression such
as ``td["next", "bump"][:, :2]`` reads as a reference link (a broken cross-reference, an error
under ``mkdocs build --strict``) and the session loses its layout. This extension, loaded by
mkdocstrings (mkdocs.yml), renames ``Example:`` to the ``Examples:`` section griffe renders as
code, and fences every other free-standing ``>>>`` session as a ``pycon`` block. The docstrings
themselves stay as they are.
"""

from __future__ import annotations

from typing import Any

from griffe import Extension, Object


def fence_sessions(text: str) -> str:
    r"""``text`` with ``Example:`` headings renamed and free-standing sessions fenced.

    >>> fence_sessions("Text.\n\n>>> 1 + 1\n2\n\nMore.").splitlines()
    ['Text.', '', '```pycon', '>>> 1 + 1', '2', '```', '', 'More.']
    >>> fence_sessions("Example:\n    >>> 1 + 1\n    2").splitlines()[0]
    'Examples:'
    """
    lines, out, session = text.splitlines(), [], False
    for line in lines:
        if line.rstrip() == "Example:":
            line = line.replace("Example:", "Examples:")
        if line.startswith(">>> ") and not session:
            out.append("```pycon")
            session = True
        elif session and not line.strip():
            out.append("```")
            session = False
        out.append(line)
    if session:
        out.append("```")
    return "\n".join(out)


class DoctestsAsCode(Extension):
    """Rewrites each docstring once the object tree is built, before it is parsed."""

    def on_object(self, *, obj: Object, **kwargs: Any) -> None:
        if obj.docstring is not None and ">>>" in obj.docstring.value:
            obj.docstring.value = fence_sessions(obj.docstring.value)
