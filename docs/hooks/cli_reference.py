"""MkDocs hook: the command-line reference, generated from ``poseflow.cli.build_parser()``.

``docs/cli.md`` holds the page's introduction and the marker ``<!-- cli-reference -->``; at
build time the marker is replaced by one section per subcommand (nested ones such as
``poseflow demo registration`` included): its description, its usage line and a table of its
arguments per group with their defaults, all read from the same argparse parsers that
``poseflow COMMAND --help`` prints, so a new subcommand or option appears without an edit here.
"""

from __future__ import annotations

import argparse
import html
import os
import re
import textwrap
from typing import Any

__all__ = ["MARKER", "on_page_markdown", "render_parser", "render_reference"]

#: The line of ``docs/cli.md`` that the generated reference replaces.
MARKER = "<!-- cli-reference -->"

#: Width of the usage lines, as ``--help`` prints them in a terminal of this many columns.
USAGE_WIDTH = 100

_CODE_SPAN = re.compile(r"(`[^`]*`)")


def _text(text: str) -> str:
    """Escape argparse text for Markdown, leaving its backtick code spans as they are."""
    parts = _CODE_SPAN.split(text)
    for i in range(0, len(parts), 2):  # even parts lie outside code spans
        parts[i] = html.escape(parts[i], quote=False).replace("*", r"\*").replace("_", r"\_")
    return "".join(parts)


def _cell(text: str) -> str:
    """One table cell: a single line, pipes escaped."""
    return _text(" ".join(text.split())).replace("|", r"\|")


def _subcommands(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action
    return None


def _default(action: argparse.Action) -> str:
    value = action.default
    if value is None or value is argparse.SUPPRESS or value is False or value == []:
        return ""
    if isinstance(action, argparse.BooleanOptionalAction):
        return "on" if value else "off"
    if isinstance(value, (list, tuple)):
        value = " ".join(map(str, value))
    return f"`{value}`"


def _help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    text = action.help or ""
    if "%" in text:  # argparse's own substitutions, e.g. %(default)s
        params = {k: v for k, v in vars(action).items() if v is not argparse.SUPPRESS}
        text = text % {**params, "prog": parser.prog}
    return text


def _arguments_table(parser: argparse.ArgumentParser, actions: list[argparse.Action]) -> str:
    formatter = parser._get_formatter()
    rows = ["| argument | description | default |", "|---|---|---|"]
    for action in actions:
        if action.help is argparse.SUPPRESS or isinstance(
            action, (argparse._HelpAction, argparse._SubParsersAction)
        ):
            continue
        invocation = formatter._format_action_invocation(action)  # as --help writes it
        invocation = invocation.replace("|", r"\|")
        rows.append(f"| `{invocation}` | {_cell(_help(parser, action))} | {_default(action)} |")
    return "\n".join(rows) if len(rows) > 2 else ""


def render_parser(parser: argparse.ArgumentParser, level: int = 2) -> str:
    """The Markdown section of one (sub)command: description, usage, arguments, epilog."""
    out = [f"{'#' * level} `{parser.prog}`", ""]
    if parser.description:
        out += [_text(textwrap.dedent(parser.description).strip()), ""]
    out += ["```text", parser.format_usage().rstrip(), "```", ""]
    for group in parser._action_groups:
        table = _arguments_table(parser, group._group_actions)
        if not table:
            continue
        out += [f"**{_text(group.title or 'arguments')}**", ""]
        if group.description:
            out += [_text(textwrap.dedent(group.description).strip()), ""]
        out += [table, ""]
    if parser.epilog:
        out += [_text(textwrap.dedent(parser.epilog).strip()), ""]
    sub = _subcommands(parser)
    if sub is not None:
        for child in sub.choices.values():
            out.append(render_parser(child, level + 1))
    return "\n".join(out)


def render_reference() -> str:
    """The whole reference: a table of the subcommands, then one section for each."""
    from poseflow.cli import build_parser

    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(USAGE_WIDTH)  # argparse wraps usage lines to the terminal
    try:
        parser = build_parser()
        sub = _subcommands(parser)
        if sub is None:
            raise RuntimeError("poseflow.cli.build_parser() registered no subcommands")
        helps = {a.dest: a.help or "" for a in sub._choices_actions}
        out = ["| command | what it does |", "|---|---|"]
        for name in sub.choices:
            out.append(f"| [`poseflow {name}`](#poseflow-{name}) | {_cell(helps.get(name, ''))} |")
        out.append("")
        for child in sub.choices.values():
            out.append(render_parser(child))
        return "\n".join(out)
    finally:
        if columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = columns


def on_page_markdown(markdown: str, *, page: Any, **kwargs: Any) -> str:
    """Replace the marker of ``cli.md`` by the generated reference (MkDocs event)."""
    if page.file.src_uri != "cli.md":
        return markdown
    if MARKER not in markdown:
        raise RuntimeError(f"docs/cli.md lost its {MARKER} line")
    return markdown.replace(MARKER, render_reference())
