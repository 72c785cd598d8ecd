"""Every tutorial of docs/tutorials/ run as written (tests/tutorial_pages.py), with checks that
what each page says came out did: so the tutorials cannot rot. docs/tutorials/test_your_stack.md
has its own test (tests/test_tutorial_stack.py)."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tutorial_pages import ROOT, TUTORIALS, blocks, commands, run_all


def _costs(run: Path) -> list[float]:
    return [json.loads(line)["cost"] for line in (run / "queries.jsonl").read_text().splitlines()]


def test_every_tutorial_in_the_site_has_a_test():
    tested = {"first_attack.md", "library_in_blender.md", "ray_cluster.md", "paper_tables.md",
              "test_your_stack.md"}
    assert {p.name for p in TUTORIALS.glob("*.md")} == tested
    nav = (ROOT / "mkdocs.yml").read_text()
    assert all(f"tutorials/{name}" in nav for name in tested)


def test_first_attack(tmp_path):
    run_all("first_attack.md", tmp_path)
    run = tmp_path / "runs" / "first"
    assert len(_costs(run)) == 3
    report = (run / "report.md").read_text()
    for section in ("Closed-loop evaluation (paper Table 1)", "Paired change against the original",
                    "Objective terms", "Per scene", "Criticality"):
        assert section in report, section
    assert (run / "convergence.png").is_file() and (run / "best_shapes.png").is_file()
    assert (tmp_path / "review.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    found = tmp_path / "found"
    for name in ("scenario.xml", "scenario.xosc", "road.xodr", "export.json"):
        assert (found / name).is_file(), name
    assert list((found / "shapes").glob("*.glb"))


def test_library_in_blender(tmp_path):
    pytest.importorskip("bpy")
    text = (TUTORIALS / "library_in_blender.md").read_text()
    python = [body for _, body in blocks(text, "python")]
    # the page's Python blocks, in order, in Blender's Python (the bpy module) with the add-on
    # registered as Blender registers an installed extension; the first shell command first
    first, *rest = commands("library_in_blender.md")
    from tutorial_pages import run

    res = run(first, tmp_path)
    assert res.returncode == 0, res.stderr
    script = tmp_path / "console.py"
    script.write_text(f"ADV3D = {str(ROOT)!r}\nimport blender_addon\nblender_addon.register()\n"
                      + "\n".join(textwrap.dedent(b) for b in python))
    res = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=600,
                         env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    assert res.returncode == 0, res.stderr[-3000:]
    assert "[('kenney.sedan', 'sedan'), ('quaternius.suv', 'suv'), ('kenney.hatchback', 'hatchback')]" in res.stdout
    assert (tmp_path / "mylib" / "space.npz").is_file() and (tmp_path / "mylib" / "shape.glb").is_file()
    for line in rest:
        res = run(line, tmp_path)
        assert res.returncode == 0, f"{line}\n{res.stderr[-3000:]}"
    assert (tmp_path / "car.obj").stat().st_size > 1000
    assert (tmp_path / "shapes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    library = json.loads((tmp_path / "mylib" / "library.json").read_text())
    assert sorted(a["id"] for a in library["assets"]) == ["kenney.hatchback", "kenney.sedan", "quaternius.suv"]


def test_ray_cluster(tmp_path):
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install -e '.[ray]')")
    try:
        run_all("ray_cluster.md", tmp_path)
    finally:  # the page's last command stops the cluster; make sure it does on a failure too
        from tutorial_pages import run

        run("ray stop", tmp_path)
    assert _costs(tmp_path / "runs" / "ray") == _costs(tmp_path / "runs" / "local")
    assert len(_costs(tmp_path / "runs" / "ray")) == 3


def test_paper_tables(tmp_path):
    run_all("paper_tables.md", tmp_path)
    rebuilt = json.loads((tmp_path / "kept" / "table1_A" / "table.json").read_text())
    kept = json.loads((ROOT / "docs" / "results" / "table1_A" / "table.json").read_text())

    def objective(table):
        return {(c["a"], c["b"]): (round(c["mean_diff"], 6), c["worse_for_stack"], c["n"], round(c["p_permutation"], 6))
                for c in table["comparisons"] if c["metric"] == "objective"}

    assert objective(rebuilt) == objective(kept)
    d = objective(rebuilt)[("Adv. closed-loop", "Original")]
    assert (round(d[0], 1), d[1], d[2], round(d[3], 3)) == (55.2, 7, 8, 0.016)   # the figure the page quotes
    mine = json.loads((tmp_path / "mine" / "table1_A_b2" / "table.json").read_text())
    assert list(mine["rows"]) == ["Original", "Adv. open-loop", "Adv. closed-loop"]
    assert (tmp_path / "mine" / "table1_A_b2" / "table.md").is_file()
