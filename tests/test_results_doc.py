"""docs/results.md against its kept files: the generated parts (verdicts, the shipped stack's
tables, compute) are what ``adv3d experiments --docs`` makes of the kept tables, and every
number in the prose outside them carries a reference to the kept value it quotes,
``NUMBER<!--= FOLDER/FILE.json#PATH -->``, resolved here (docs/results.md, "Protocol": the
protocol's constants are exempt, in a section marked ``<!-- prose-numbers: definitions -->``)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PAGE = REPO / "docs" / "results.md"
ROOT = REPO / "docs" / "results"

NUMBER = r"[+-]?\d+(?:\.\d+)?"
REF = re.compile(rf"(?<![\w.])({NUMBER})<!--= (?P<file>[^#\s]+)#(?P<path>.+?) -->")
# names that contain digits but quote no result: Table 1, Tables 2-6, Eq. 3-5, 95 % CI is a method
NAME = re.compile(r"\b(?:Tables?|Eq\.|Section)\s+\d+(?:-\d+)?|\b95 % (?:bootstrap )?interval|\b80 % power")
BARE = re.compile(rf"(?<![\w.`/-]){NUMBER}(?![\w`])")


def resolve(doc, path: str):
    """``a.b[k=v;k2=v2].c.0.{d. e}``: keys, list items selected by their fields, list items by
    index, and a key with dots in braces (a row name such as ``{Adv. closed-loop}``)."""
    for part in re.findall(r"\{[^}]*\}|[^.\[\]{}]+(?:\[[^\]]*\])?", path):
        if part.startswith("{"):
            doc = doc[part[1:-1]]
            continue
        key, _, sel = part.partition("[")
        if key:
            doc = doc[int(key)] if isinstance(doc, list) else doc[key]   # a list item by its index
        if sel:
            want = dict(kv.split("=", 1) for kv in sel.rstrip("]").split(";"))
            (doc,) = [x for x in doc if all(str(x.get(k)) == v for k, v in want.items())]
    return doc


def prose_sections(text: str):
    """(heading, prose) of each section: without code blocks, tables, generated blocks,
    headings, inline code, link targets and images."""
    text = re.sub(r"<!-- BEGIN generated: (\S+) -->.*?<!-- END generated: \1 -->", "", text, flags=re.S)
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    sections = re.split(r"^(#{1,6} .*)$", text, flags=re.M)
    heading = ""
    for chunk in sections:
        if re.match(r"^#{1,6} ", chunk):
            heading = chunk
            continue
        lines = [ln for ln in chunk.splitlines() if not ln.lstrip().startswith("|")]
        prose = "\n".join(lines)
        prose = re.sub(r"`[^`]*`", "", prose)
        prose = re.sub(r"\]\([^)]*\)", "]", prose)
        yield heading, prose


def test_generated_parts_are_the_kept_tables():
    from adv3d_runner.experiments.summary import BLOCK, blocks

    if not (ROOT / "table1_A_b20" / "table.json").exists():
        pytest.skip("the kept tables are not in this checkout")
    made = blocks(ROOT)
    found = {m["name"]: m["body"] for m in BLOCK.finditer(PAGE.read_text())}
    assert set(found) == set(made)
    for name, body in made.items():
        assert found[name] == body, f"docs/results.md's {name} block is stale: run adv3d experiments --docs"


def test_every_number_in_the_prose_is_a_checked_reference():
    text = PAGE.read_text()
    checked = 0
    for heading, prose in prose_sections(text):
        if "<!-- prose-numbers: definitions" in prose:
            continue
        for m in REF.finditer(prose):
            doc = json.loads((ROOT / m["file"]).read_text())
            value = float(resolve(doc, m["path"]))
            shown = m.group(1)
            decimals = len(shown.split(".")[1]) if "." in shown else 0
            assert abs(float(shown) - value) <= 0.5 * 10**-decimals + 1e-12, (heading, shown, m["path"], value)
            checked += 1
        bare = NAME.sub("", re.sub(r"<!--.*?-->", "", REF.sub("", prose), flags=re.S))
        loose = BARE.findall(bare)
        assert not loose, f"{heading}: numbers without a reference to a kept file: {loose}"
    assert checked >= 10


def test_a_wrong_number_or_a_bare_one_is_caught(tmp_path):
    """The check can fail: a quoted value off by one in its last digit, or a number without
    its reference."""
    doc = json.loads((ROOT / "table1_A_b20" / "table.json").read_text())
    path = "comparisons[a=Adv. closed-loop;b=Adv. open-loop;metric=objective].mean_diff"
    value = resolve(doc, path)
    assert f"{value:.1f}" == "7.6"
    wrong = "7.7"
    assert abs(float(wrong) - value) > 0.05
    assert BARE.findall(NAME.sub("", "closed minus open is +7.6 on Table 1's 13 scenes")) == ["+7.6", "13"]
