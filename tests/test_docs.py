"""The documentation's own rules: the README is short and its test command is .ci/run's, the
command-line reference lists every command, and docstrings and comments cite docs pages or the
paper, not issue numbers or rounds of work (history belongs in CHANGELOG.md and
docs/archive.md)."""
from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HISTORY = re.compile(r"\bissues? \d+|\bissue\d+\b|(?<![\w&])#\d{2,}\b|\bround \d+|\b\d+(?:st|nd|rd|th) round\b|"
                     r"\b(?:first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth) round\b",
                     re.IGNORECASE)
SOURCES = ("adv3d_runner", "blender_addon", "bench", "tests", "examples")


def _python_files():
    for top in SOURCES:
        for path in sorted((ROOT / top).rglob("*.py")):
            if not any(part.startswith(".") or part in ("site-packages", "__pycache__") for part in path.parts):
                yield path


def _comments_and_docstrings(path: Path):
    """(line, text) of every comment and docstring of a Python file."""
    source = path.read_text(encoding="utf-8")
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], tok.string
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                yield body[0].lineno, body[0].value.value


def test_comments_and_docstrings_cite_pages_not_issues_or_rounds():
    found = []
    for path in _python_files():
        for line, text in _comments_and_docstrings(path):
            for m in HISTORY.finditer(text):
                found.append(f"{path.relative_to(ROOT)}:{line}: ...{text[max(0, m.start() - 30):m.end() + 20]!r}")
    assert not found, "cite a docs page or the paper instead:\n" + "\n".join(found)


def test_readme_is_short_and_its_test_command_is_ci_run():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) < 150
    assert not HISTORY.search(readme)
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line.startswith("python3 -m venv")]
    assert len(ci) == 1 and f"    {ci[0]}\n" in readme
    assert "mkdocs build --strict" in ci[0] and ".[blender,test,docs]" in ci[0]


def test_the_command_line_reference_lists_every_command():
    import argparse
    import importlib.util

    spec = importlib.util.spec_from_file_location("cli_reference", ROOT / "docs" / "hooks" / "cli_reference.py")
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    page = hook.cli_markdown()
    from adv3d_runner.cli import build_parser

    def leaves(parser, words=()):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield (*words, name), sub
                    yield from leaves(sub, (*words, name))

    commands = list(leaves(build_parser()))
    assert len(commands) > 20
    for words, sub in commands:
        assert f"## adv3d {' '.join(words)} {{" in page or f"# adv3d {' '.join(words)} {{" in page, words
        for option in sub._option_string_actions:
            assert option in page, (words, option)


def test_every_command_of_the_how_to_page_parses(monkeypatch):
    """docs/howto.md's recipes are not run (they are full size), but each ``adv3d`` line must parse
    with the installed command line: no option that does not exist, no bad value."""
    import glob
    import shlex

    from adv3d_runner.cli import _join_axis_values, build_parser

    text = (ROOT / "docs" / "howto.md").read_text()
    lines = [line.strip() for block in re.findall(r"^```sh[^\n]*\n(.*?)^```", text, flags=re.S | re.M)
             for line in block.splitlines() if line.strip()]
    assert len(lines) >= 12
    monkeypatch.chdir(ROOT)
    parser = build_parser()
    for line in lines:
        words = [w for word in shlex.split(line) for w in (sorted(glob.glob(word)) if "*" in word else [word])]
        assert words[0] == "adv3d", line
        if "--" in words:  # adv3d numerics --emulate NAME -- CMD: the command after -- parses too
            inner = words[words.index("--") + 1:]
            parser.parse_args(_join_axis_values(parser, inner[1:]))
            words = words[:words.index("--")]
        try:
            parser.parse_args(_join_axis_values(parser, words[1:]))
        except SystemExit as exc:
            raise AssertionError(f"docs/howto.md: {line}") from exc
