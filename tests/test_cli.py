import json

import pytest

from adv3d_runner.cli import main
from adv3d_runner.errors import FileFormatError
from adv3d_runner.fileio import read_json, write_json


def test_help_lists_commands(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "adv3d" in out


def test_read_json_names_file_on_bad_json(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(FileFormatError) as exc:
        read_json(bad)
    assert "bad.json" in str(exc.value)


def test_write_json_is_atomic_and_round_trips(tmp_path):
    target = tmp_path / "x.json.gz"
    write_json(target, {"a": [1, 2.5]})
    assert read_json(target) == {"a": [1, 2.5]}
    # a failing write (NaN is not JSON) leaves the old file intact and no temporary behind
    with pytest.raises(ValueError):
        write_json(target, {"a": float("nan")})
    assert read_json(target) == {"a": [1, 2.5]}
    assert [p.name for p in tmp_path.iterdir()] == ["x.json.gz"]


def test_atomic_write_gives_a_normal_file_mode(tmp_path):
    import os
    target = tmp_path / "y.json"
    write_json(target, {"a": 1})
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask
    os.chmod(target, 0o640)  # a user's own mode is kept on rewrite
    write_json(target, {"a": 2})
    assert target.stat().st_mode & 0o777 == 0o640


def test_demo_decodes_vehicles_and_attacks(tmp_path):
    import trimesh

    out = tmp_path / "demo"
    assert main(["-q", "demo", "--out", str(out), "--budget", "2", "--seconds", "0.5"]) == 0
    mesh = trimesh.load(out / "mean_vehicle.glb", force="mesh")
    assert mesh.is_watertight and len(mesh.faces) > 1000
    lines = (out / "attack" / "queries.jsonl").read_text().splitlines()
    assert len(lines) == 2 and all(json.loads(line)["status"] == "ok" for line in lines)
    report = (out / "attack" / "report.md").read_text()
    assert "Original" in report and "### Avoidability: stack-induced or scenario-induced" in report
    # the demo searched the realistic region and ends on its finding (or says there is none)
    from adv3d_runner.attack.avoidability import read_avoidability
    from adv3d_runner.demo import report_finding

    run = json.loads((out / "attack" / "run.json").read_text())
    assert run["region"] == "realistic"
    summary = json.loads((out / "attack" / "summary.json").read_text())
    ((sid, entry),) = summary["scenes"].items()
    assert all(r["realistic"] for r in entry["modes"]["closed"]["closed_loop_eval"]["realism"])
    doc = read_avoidability(out / "attack")
    finding = doc["scenes"][sid]["modes"]["closed"]["finding"]
    lines = report_finding(out / "attack", out / "finding")
    assert lines[0].startswith(f"best shape of {sid} [closed]: passes the realism report; avoidability: {finding}")
    if finding == "stack-induced":
        assert lines[-2].startswith("criticality: ") and lines[-1].startswith("export: ")
    else:
        assert lines[-1].startswith("no realistic, stack-induced finding on this scene")
    _finding_with_export(out, sid)


def _finding_with_export(out, sid):
    """report_finding on the demo's run with its avoidability file saying stack-induced (as a scene
    with such a finding has it): the finding, its criticality line and the export."""
    from adv3d_runner.attack.avoidability import FAILURE_KINDS
    from adv3d_runner.demo import criticality_line, report_finding

    path = out / "attack" / "avoidability.json"
    doc = json.loads(path.read_text())
    m = doc["scenes"][sid]["modes"]["closed"]
    assert set(FAILURE_KINDS) == set(m["kinds"])
    m["finding"] = "stack-induced"
    m["kinds"]["hard_braking"]["verdict"] = "stack-induced"
    path.write_text(json.dumps(doc))
    lines = report_finding(out / "attack", out / "finding")
    assert lines[1] == f"finding: {sid} [closed]: hard braking with the stack, not with ground-truth perception"
    crit = json.loads((out / "attack" / "summary.json").read_text())["scenes"][sid]["modes"]["closed"][
        "closed_loop_eval"].get("criticality")
    assert lines[2] == "criticality: " + criticality_line(crit)
    try:
        import scenariogeneration  # noqa: F401
    except ImportError:
        assert lines[3].startswith("export: not written (OpenSCENARIO export needs scenariogeneration"), lines
        return
    assert lines[3].startswith("export: ") and (out / "finding" / "export.json").is_file(), lines
