"""``rap import`` and ``rap model show``/``rap check`` on designs: the format found from
the names (or ``--format``), the model written, findings located in the design, and
the exit codes 0 / 1 / 2."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from rap_cli.app import app
from rap_cli.designs import DesignError, detect
from rap_cli.model_io import check_model_file
from typer.testing import CliRunner

FIXTURES = Path(__file__).resolve().parent / "fixtures"
runner = CliRunner()


@pytest.fixture
def aadl_design(tmp_path: Path) -> Path:
    folder = tmp_path / "design"
    folder.mkdir()
    for name in ("loop.aadl", "types.aadl"):
        shutil.copy(FIXTURES / "aadl_import" / name, folder / name)
    return folder


def test_the_format_is_found_from_the_names(tmp_path: Path, aadl_design: Path) -> None:
    assert detect([aadl_design])[0] == "aadl"
    rct = tmp_path / "rc"
    shutil.copytree(FIXTURES / "robochart_import", rct)
    assert detect([rct])[0] == "robochart"
    (tmp_path / "il").mkdir()
    (tmp_path / "il" / "design.json").write_text("{}")
    assert detect([tmp_path / "il"])[0] == "aadl-il"
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "model.yaml").write_text("system: x\ncompute_nodes: {}\n")
    assert detect([tmp_path / "m"]) == ("rap", [tmp_path / "m" / "model.yaml"])


def test_mixed_or_unknown_formats_are_refused_with_the_fix(
    tmp_path: Path, aadl_design: Path
) -> None:
    shutil.copy(FIXTURES / "robochart_import" / "loop.rct", aadl_design / "loop.rct")
    with pytest.raises(DesignError, match="mix formats"):
        detect([aadl_design])
    odd = tmp_path / "design.txt"
    odd.write_text("x")
    with pytest.raises(DesignError, match="--format"):
        detect([odd])
    res = runner.invoke(app, ["model", "show", str(aadl_design)])
    assert res.exit_code == 2
    assert "mix formats" in res.output
    res = runner.invoke(app, ["check", str(tmp_path / "nowhere")])
    assert res.exit_code == 2


def test_model_show_json_on_a_design_lists_what_the_import_yields(aadl_design: Path) -> None:
    res = runner.invoke(app, ["model", "show", str(aadl_design), "--json"])
    view = json.loads(res.output)
    assert {c["name"] for c in view["components"]} >= {"m", "l"}
    assert all(c["kind"] == "component" for c in view["components"])
    assert all(c["origin"].startswith("aadl ") for c in view["components"])
    assert {n["name"]: n["address"] for n in view["nodes"]} == {
        "edge": "10.0.0.2",
        "main": "10.0.0.1",
    }
    errors = [d for d in view["diagnostics"] if d["severity"] == "error"]
    # the design's own defects (an input nobody produces), located in the design
    assert errors
    assert all(d["file"].endswith(".aadl") and d["line"] > 0 for d in errors)
    assert res.exit_code == 1


def test_import_writes_a_model_that_checks_the_same(tmp_path: Path, aadl_design: Path) -> None:
    out = tmp_path / "model.yaml"
    res = runner.invoke(app, ["import", "aadl", str(aadl_design), "-o", str(out)])
    assert res.exit_code == 1, res.output  # the design has errors; the model is written
    assert "4 component(s)" in res.output
    text = out.read_text()
    assert text.startswith("# Imported by `rap import aadl`")
    checked = check_model_file(out)
    assert checked.plan is not None
    assert set(checked.plan.components) >= {"m", "l"}
    # the same cross-check findings, now located in the model file
    design = {d.message for d in check_model_file(out).diagnostics}
    shown = json.loads(runner.invoke(app, ["model", "show", str(aadl_design), "--json"]).output)
    from_design = {
        d["message"]
        for d in shown["diagnostics"]
        if d["severity"] != "note" and "package" not in d["message"]
    }
    assert from_design <= design


def test_import_to_standard_output(aadl_design: Path) -> None:
    res = runner.invoke(app, ["import", "aadl", str(aadl_design)])
    assert "system: robot" in res.stdout


def test_root_is_for_aadl_only(tmp_path: Path) -> None:
    rct = tmp_path / "rc"
    shutil.copytree(FIXTURES / "robochart_import", rct)
    res = runner.invoke(app, ["model", "show", str(rct / "loop.rct"), "--root", "X"])
    assert res.exit_code == 2
    assert "--root is for AADL" in res.output


def test_a_design_that_cannot_be_read_exits_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.aadl"
    bad.write_text("package P public system S end S; end")
    res = runner.invoke(app, ["import", "aadl", str(bad), "-o", str(tmp_path / "m.yaml")])
    assert res.exit_code == 2
    assert "bad.aadl:1:" in res.output
    assert not (tmp_path / "m.yaml").exists()


def test_robochart_import_makes_a_component_per_state_machine(tmp_path: Path) -> None:
    out = tmp_path / "m.yaml"
    res = runner.invoke(
        app,
        ["import", "robochart", str(FIXTURES / "robochart_import" / "loop.rct"), "-o", str(out)],
    )
    assert res.exit_code in (0, 1), res.output
    plan = check_model_file(out).plan
    assert plan is not None
    assert any((c.origin or "").startswith("robochart stm") for c in plan.components.values())
