"""Griffe extension for the docs site: poseflow's docstrings made readable by mkdocstrings.

Three rewrites, applied to every docstring before mkdocstrings parses and renders it:

- poseflow's docstrings name other objects as ``:func:`procrustes``` or
  ``:class:`~poseflow.features.FPFHEncoder``` (as Sphinx reads them). Markdown has no such
  roles, so each is replaced by the name as inline code, shortened to its last component when
  it starts with ``~`` and to its title when it has one (``title <target>``), as in Sphinx.
- Their doctests sit under ``Example:``, which Google style (and ruff's pydocstyle) accepts but
  griffe reads only as ``Examples:``; the heading is renamed so that the doctests render as
  code, not as Markdown text.
- Constants are documented by ``#:`` comments on the lines above them (as Sphinx reads them);
  griffe reads only a string below an assignment, so the comment becomes the docstring.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

__all__ = ["DocstringsToMarkdown", "to_markdown"]

_ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|exc|obj|const):`(~?)([^`]+)`")
_EXAMPLE_HEADING = re.compile(r"^(\s*)Example:[ \t]*$", re.MULTILINE)
_DOC_COMMENT = re.compile(r"^\s*#:(?: |$)(.*)$")


def _code(match: re.Match[str]) -> str:
    tilde, target = match.groups()
    titled = re.fullmatch(r"(.+?)\s*<[^>]+>", target)  # :meth:`title <target>`
    if titled:
        return f"`{titled.group(1)}`"
    return f"`{target.rsplit('.', 1)[-1] if tilde else target}`"


def to_markdown(docstring: str) -> str:
    r"""Sphinx roles in ``docstring`` made inline code, ``Example:`` headings ``Examples:``.

    Example:
        >>> to_markdown("See :func:`~poseflow.geometry.compose` and :class:`ICP`.")
        'See `compose` and `ICP`.'
        >>> to_markdown(":meth:`FunFlow6D.save <poseflow.models.FunFlow6D.save>`")
        '`FunFlow6D.save`'
        >>> to_markdown("Example:\n    >>> 1 + 1\n    2")
        'Examples:\n    >>> 1 + 1\n    2'
    """
    return _EXAMPLE_HEADING.sub(r"\1Examples:", _ROLE.sub(_code, docstring))


def doc_comment(lines: list[str], lineno: int) -> str | None:
    r"""The ``#:`` comment block right above line ``lineno`` (1-based) of ``lines``, if any.

    Example:
        >>> doc_comment(["x = 1", "#: The answer,", "#: in full.", "ANSWER = 42"], 4)
        'The answer,\nin full.'
        >>> doc_comment(["x = 1", "ANSWER = 42"], 2) is None
        True
    """
    text: list[str] = []
    i = lineno - 2
    while i >= 0 and (match := _DOC_COMMENT.match(lines[i])):
        text.insert(0, match.group(1))
        i -= 1
    return "\n".join(text) if text else None


class DocstringsToMarkdown(griffe.Extension):
    """Rewrite the docstring of every loaded object with :func:`to_markdown`."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        """Rewrite ``obj``'s docstring in place, once it is loaded."""
        if obj.docstring is not None:
            obj.docstring.value = to_markdown(obj.docstring.value)

    def on_attribute_instance(self, *, attr: griffe.Attribute, **kwargs: Any) -> None:
        """Give an attribute without a docstring the ``#:`` comment above it, if it has one."""
        if attr.docstring is not None or attr.lineno is None or attr.filepath is None:
            return
        lines = attr.lines_collection
        text = doc_comment(lines[attr.filepath], attr.lineno) if attr.filepath in lines else None
        if text is not None:
            attr.docstring = griffe.Docstring(to_markdown(text), lineno=attr.lineno, parent=attr)
