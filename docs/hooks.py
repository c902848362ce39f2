"""MkDocs hooks: the command-line reference is generated from ``twinrl.cli.build_parser()``,
and the table of checkpoint kinds from ``twinrl.loop.checkpoints``.

A page whose source holds the marker ``<!-- cli-reference -->`` gets, in its place, one section
per ``twinrl`` subcommand: its description and a table of its arguments, walked from the argparse
parser's actions, so the page cannot drift from the CLI (no hand-kept copy).
"""

from __future__ import annotations

import argparse

MARKER = "<!-- cli-reference -->"
KINDS_MARKER = "<!-- checkpoint-kinds -->"


def _escape(text: str) -> str:
    return (text or "").replace("|", "\\|").replace("\n", " ").replace("<", "&lt;")


def _names(action: argparse.Action) -> str:
    if action.option_strings:
        names = ", ".join(f"`{o}`" for o in action.option_strings)
        if action.nargs != 0:
            metavar = action.metavar or action.dest.upper()
            if isinstance(metavar, tuple):
                metavar = " ".join(metavar)
            names += f" `{metavar}`"
        return names
    return f"`{action.metavar or action.dest}`"


def _default(action: argparse.Action) -> str:
    if action.nargs == 0 or action.default in (None, argparse.SUPPRESS) or action.required:
        return ""
    return f"`{action.default}`"


def _help(action: argparse.Action) -> str:
    text = action.help or ""
    if text == argparse.SUPPRESS:
        return ""
    if action.choices and not isinstance(action, argparse._SubParsersAction):
        text += f" (choices: {', '.join(str(c) for c in action.choices)})"
    try:
        text = text % {"default": action.default, "prog": ""}
    except (KeyError, TypeError, ValueError):
        pass
    return _escape(text)


def parser_markdown(parser: argparse.ArgumentParser) -> str:
    """Markdown for every subcommand of ``parser``: a section with the description and an
    argument table (name, default, help)."""
    out: list[str] = []
    for action in parser._actions:  # argparse keeps its actions there; no public accessor
        if not isinstance(action, argparse._SubParsersAction):
            continue
        for name, sub in action.choices.items():
            out += [f"## `twinrl {name}`", "", _escape_block(sub.description or ""), "",
                    "```text", sub.format_usage().strip(), "```", "",
                    "| argument | default | meaning |", "|---|---|---|"]
            for a in sub._actions:
                if isinstance(a, argparse._HelpAction):
                    continue
                out.append(f"| {_names(a)} | {_default(a)} | {_help(a)} |")
            out.append("")
    return "\n".join(out)


def _escape_block(text: str) -> str:
    return text.replace("<", "&lt;")


def kinds_markdown() -> str:
    """The table of what twinrl's directories hold (``twinrl.loop.checkpoints``): kind, what it
    is, the file that says so, and the commands that take it."""
    from twinrl.learn.checkpoint import KINDS
    from twinrl.loop.checkpoints import DIRECTORY_KINDS, RECORDED_IN, TAKES

    rows = ["| kind | what it is | said by | taken by |", "|---|---|---|---|"]
    for kind, what in {**KINDS, **DIRECTORY_KINDS}.items():
        takers = ", ".join(f"`twinrl {c}`" for c, kinds in TAKES.items() if kind in kinds)
        rows.append(f"| `{kind}` | {_escape(what)} | `{RECORDED_IN[kind]}` | {takers or '—'} |")
    return "\n".join(rows)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if KINDS_MARKER in markdown:
        markdown = markdown.replace(KINDS_MARKER, kinds_markdown())
    if MARKER not in markdown:
        return markdown
    from twinrl.cli import build_parser

    return markdown.replace(MARKER, parser_markdown(build_parser()))
