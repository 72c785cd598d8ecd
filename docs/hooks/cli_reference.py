"""MkDocs hook: the command-line reference page, generated from adv3d's argparse parser at
every build (``reference/cli.md``), so that it cannot drift from the code."""
from __future__ import annotations

import argparse
import os

from mkdocs.structure.files import File

PAGE = "reference/cli.md"


def _commands(parser: argparse.ArgumentParser, words: tuple[str, ...] = ()):
    """(words, parser, help line) of every command under ``parser``, depth first."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            seen = set()
            for name, sub in action.choices.items():
                if id(sub) in seen:  # an alias of a command already listed
                    continue
                seen.add(id(sub))
                yield (*words, name), sub, helps.get(name) or ""
                yield from _commands(sub, (*words, name))


def _help_text(parser: argparse.ArgumentParser) -> str:
    """``parser.format_help()`` at a fixed width, whatever the terminal."""
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"
    try:
        return parser.format_help().rstrip()
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


def cli_markdown() -> str:
    """The reference page: an index of every command, then each command's ``--help``."""
    from adv3d_runner.cli import build_parser

    parser = build_parser()
    commands = list(_commands(parser))
    lines = [
        "# Command line",
        "",
        "Every `adv3d` command and option, generated from the argparse parser when the site is "
        "built (`docs/hooks/cli_reference.py`), so it is the `--help` of the installed version. "
        "Every command takes `-q/--quiet`; a usage error is one line and exit code 2, a bad file "
        "one line naming the file and field and exit code 1 ([reliability](../reliability.md)).",
        "",
        "| command | what it does |",
        "|---|---|",
    ]
    for words, _, help_line in commands:
        anchor = "adv3d-" + "-".join(words)
        cell = " ".join(help_line.split()).replace("|", "\\|")
        lines.append(f"| [`adv3d {' '.join(words)}`](#{anchor}) | {cell} |")
    lines += ["", "## adv3d", "", "```text", _help_text(parser), "```", ""]
    for words, sub, _ in commands:
        anchor = "adv3d-" + "-".join(words)
        level = "#" * min(2 + len(words) - 1, 4)
        lines += [f"{level} adv3d {' '.join(words)} {{ #{anchor} }}", "", "```text", _help_text(sub), "```", ""]
    return "\n".join(lines)


def on_files(files, config):
    """Add the generated page to the site's files."""
    files.append(File.generated(config, PAGE, content=cli_markdown()))
    return files
