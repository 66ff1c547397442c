"""rap new / rap generate: the generated package runs as generated, passes its own tests,
and keeps the user's code across regeneration."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from rap_cli.app import app
from rap_cli.generate.regions import RegionError, merge, regions
from typer.testing import CliRunner

FIXTURES = Path(__file__).parent / "fixtures"
runner = CliRunner()


def _rap(*args: str, cwd: Path) -> tuple[int, str]:
    old = Path.cwd()
    os.chdir(cwd)
    try:
        result = runner.invoke(app, list(args))
    finally:
        os.chdir(old)
    return result.exit_code, result.output


def _pytest(package: Path) -> subprocess.CompletedProcess[str]:
    """``python -m pytest`` in the package, with the Python environment RAP runs in."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly"],
        cwd=package,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        check=False,
    )


@pytest.fixture(scope="module")
def starter(tmp_path_factory: pytest.TempPathFactory) -> Path:
    where = tmp_path_factory.mktemp("new")
    code, out = _rap("new", "plant", cwd=where)
    assert code == 0, out
    return where / "plant"


def test_rap_new_scaffolds_a_package_that_passes_its_own_tests(starter: Path) -> None:
    for rel in (
        "model.yaml",
        "README.md",
        "pyproject.toml",
        "plant/messages.py",
        "plant/nodes/monitor.py",
        "plant/nodes/execute.py",
        "tests/test_loop.py",
        "tests/test_execute.py",
        "plant/schemas/Setpoint.schema.json",
    ):
        assert (starter / rel).is_file(), rel
    readme = (starter / "README.md").read_text()
    assert "python -m pytest" in readme
    assert "rap up model.yaml --all" in readme
    code, out = _rap("check", "model.yaml", cwd=starter)
    assert code == 0, out
    run = _pytest(starter)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "6 passed" in run.stdout


def test_the_execute_stage_acts_only_through_the_gate(starter: Path) -> None:
    text = (starter / "plant/nodes/execute.py").read_text()
    assert 'gate = ApprovalGate(\n    legitimators=["legitimate"],' in text
    assert "@gate.on_approved(node, plan=messages.Setpoint)" in text
    assert 'on_event("approved-setpoint")' not in text
    legit = (starter / "plant/nodes/legitimate.py").read_text()
    assert "@legitimate(node, plan=messages.Setpoint)" in legit


def test_messages_keep_constraints_docs_and_are_registered(starter: Path) -> None:
    schema = json.loads((starter / "plant/schemas/Setpoint.schema.json").read_text())
    assert schema["$id"] == "plant.Setpoint/1"
    target = schema["$defs"]["Setpoint"]["properties"]["target"]
    assert target["minimum"] == -10
    assert target["maximum"] == 10
    assert target["description"] == "The new set point."
    probe = (
        "import msgspec, rap_schemas.catalog as c\n"
        "from plant import messages\n"
        "cls = c.by_type('plant.Setpoint/1')\n"
        "assert cls is messages.Setpoint\n"
        "try:\n"
        "    msgspec.json.decode(b'{\"target\": 11}', type=cls)\n"
        "except msgspec.ValidationError as e:\n"
        "    print('refused', e)\n"
    )
    probe_file = starter / "probe_messages.py"
    probe_file.write_text(probe)
    try:
        run = subprocess.run(
            [sys.executable, "probe_messages.py"],
            cwd=starter,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
    finally:
        probe_file.unlink()
    assert run.returncode == 0, run.stderr
    assert "refused Expected `float` <= 10" in run.stdout


def test_user_code_survives_regeneration(tmp_path: Path) -> None:
    code, out = _rap("new", "edited", cwd=tmp_path)
    assert code == 0, out
    pkg = tmp_path / "edited"
    node = pkg / "edited/nodes/analyse.py"
    text = node.read_text()
    mine = "    # my analysis starts here\n    log.info('observed %s', msg.value)\n"
    marker = "    # region user: on_observed\n"
    assert marker in text
    node.write_text(text.replace(marker, marker + mine))
    config_marker = "    # region user: config\n"
    node.write_text(
        node.read_text().replace(config_marker, config_marker + "    threshold: float = 0.5\n")
    )
    readme = pkg / "README.md"
    readme.write_text("my own readme\n")
    # the model changes: analyse gets a second output; regenerate in place
    model = pkg / "model.yaml"
    model.write_text(
        model.read_text().replace(
            "      deviation: {direction: out, type: Reading, topic: deviation}",
            "      deviation: {direction: out, type: Reading, topic: deviation}\n"
            "      alarm: {direction: out, kind: event, topic: alarm}",
        )
    )
    code, out = _rap("generate", "model.yaml", cwd=pkg)
    assert code == 0, out
    again = node.read_text()
    assert mine in again
    assert "    threshold: float = 0.5\n" in again
    assert "async def send_alarm(ctx: Context) -> None:" in again
    assert readme.read_text() == "my own readme\n"
    # the edited, regenerated package passes its tests (the new output is expected too)
    assert (
        'await h.expect_event("alarm", after=mark)' in (pkg / "tests/test_analyse.py").read_text()
    )
    run = _pytest(pkg)
    assert run.returncode == 0, run.stdout + run.stderr


def test_a_region_whose_port_is_gone_is_kept_commented_out() -> None:
    old = "x\n    # region user: on_a\n    do_a()\n    # endregion user: on_a\n"
    new = "x\n    # region user: on_b\n    pass\n    # endregion user: on_b\n"
    merged = merge(new, old)
    assert "#     do_a()" in merged
    assert "regions of an earlier generation" in merged


def test_broken_region_markers_refuse_the_generation(tmp_path: Path) -> None:
    code, out = _rap("new", "broken", cwd=tmp_path)
    assert code == 0, out
    pkg = tmp_path / "broken"
    node = pkg / "broken/nodes/plan.py"
    node.write_text(node.read_text().replace("    # endregion user: on_deviation\n", "", 1))
    before = (pkg / "broken/messages.py").stat().st_mtime_ns
    code, out = _rap("generate", "model.yaml", cwd=pkg)
    assert code == 2
    assert "plan.py:98: region" in out
    assert "close that one first" in out
    assert "nothing was written" in out
    assert (pkg / "broken/messages.py").stat().st_mtime_ns == before
    with pytest.raises(RegionError):
        regions("# region user: a\n# region user: b\n")


def test_rap_new_from_a_design_generates_a_package_that_passes_its_tests(tmp_path: Path) -> None:
    design = FIXTURES / "aadl_import"
    if not design.is_dir():
        pytest.fail(f"fixture {design} is missing")
    code, out = _rap("new", "fromdesign", "--from", str(design), cwd=tmp_path)
    assert code == 0, out
    pkg = tmp_path / "fromdesign"
    assert (pkg / "model.yaml").is_file()
    # the header names the design relative to the model, not by this machine's path
    header = (pkg / "model.yaml").read_text().splitlines()[0]
    named = header.split("imported from ", 1)[1].split(" by rap new", 1)[0]
    assert not Path(named).is_absolute(), header
    assert (pkg / named).resolve() == design.resolve()
    run = _pytest(pkg)
    assert run.returncode == 0, run.stdout + run.stderr


def test_rap_new_refuses_a_folder_that_is_not_empty(tmp_path: Path) -> None:
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "x").write_text("")
    code, out = _rap("new", "taken", cwd=tmp_path)
    assert code == 2
    assert "exists and is not empty" in out


CONSTRAINED = """\
system: shapes
compute_nodes: {here: {}}
messages:
  Mode: {enum: [IDLE, RUN]}
  Shape:
    fields:
      count: {type: uint8, gt: 3}
      ratio: {type: float, gt: 0.5, lt: 0.75}
      name: {type: str, min_length: 3, max_length: 5}
      code: {type: str, pattern: "^[0-9]+$"}
      corners: {type: "list[float, 4]"}
      tags: {type: "list[str]", min_length: 2}
      mode: {type: Mode}
      note: {type: "optional[str]"}
      blob: {type: bytes, min_length: 2}
components:
  m:
    stage: monitor
    node: here
    ports:
      shape: {direction: in, kind: data, type: Shape, topic: shape}
"""


def test_generated_samples_satisfy_the_constraints(tmp_path: Path) -> None:
    """Every example message decodes under its own constraints (the generated tests
    send them; a receiver would reject one that broke them)."""
    (tmp_path / "model.yaml").write_text(CONSTRAINED)
    code, out = _rap("generate", "model.yaml", "--package", "shapes", cwd=tmp_path)
    assert code == 0, out
    probe = (
        "import msgspec\n"
        "from shapes import messages\n"
        "from shapes.samples import sample\n"
        "for cls in messages.MESSAGES:\n"
        "    x = sample(cls)\n"
        "    msgspec.convert(msgspec.to_builtins(x), cls)\n"
        "    print(cls.__name__, 'ok')\n"
        "bad = msgspec.to_builtins(sample(messages.Shape)) | {'ratio': 0.9}\n"
        "try:\n"
        "    msgspec.convert(bad, messages.Shape)\n"
        "except msgspec.ValidationError:\n"
        "    print('constraints enforced')\n"
    )
    (tmp_path / "probe_samples.py").write_text(probe)
    run = subprocess.run(
        [sys.executable, "probe_samples.py"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["Shape", "ok", "constraints", "enforced"]


LIMITS_TEST = """
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_schemas import Verdict
from rap_sdk import Context, Node
from rap_sdk.gate import propose
from rap_sdk.testing import Harness

from {pkg} import messages
from {pkg}.nodes import execute, legitimate

pytestmark = pytest.mark.anyio


async def test_a_plan_beyond_the_model_limits_never_reaches_the_robot() -> None:
    rogue = Node("rogue-plan", stage="plan")

    @rogue.on_event("go")
    async def go(ctx: Context) -> None:
        await propose(ctx, messages.Setpoint(target=300.0))  # the model says le: 10

    async with Harness(system="t") as h:
        await h.hold(open_service(KnowledgeConfig(system="t"), fabric=h.fabric))
        await h.start(legitimate.node, execute.node, rogue)
        await h.emit("go")
        verdict = (await h.expect_event("verdict")).decode(Verdict)
        assert not verdict.approved
        assert "constraints" in verdict.reason
        assert not h.of(h.records[0].kind.DATA, "robot/setpoint")
"""


def test_the_legitimate_stage_refuses_a_plan_beyond_the_model_limits(tmp_path: Path) -> None:
    code, out = _rap("new", "limits", cwd=tmp_path)
    assert code == 0, out
    pkg = tmp_path / "limits"
    # a test file of the user's own: the generator never touches it
    (pkg / "tests/test_mine_limits.py").write_text(LIMITS_TEST.format(pkg="limits"))
    code, out = _rap("generate", "model.yaml", cwd=pkg)
    assert code == 0, out
    assert (pkg / "tests/test_mine_limits.py").read_text() == LIMITS_TEST.format(pkg="limits")
    run = _pytest(pkg)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "7 passed" in run.stdout


def test_the_placeholder_check_warning_goes_once_the_check_is_written(tmp_path: Path) -> None:
    code, out = _rap("new", "judged", cwd=tmp_path)
    assert code == 0, out
    assert "approves every well-formed plan until you write its check" in out
    pkg = tmp_path / "judged"
    module = pkg / "judged" / "nodes" / "legitimate.py"
    text = module.read_text()
    start = text.index("# placeholder: approves every plan")
    end = text.index("# endregion user: check")
    mine = "if proposal.plan is None:\n        return 'no plan'\n    return None\n    "
    module.write_text(text[:start] + mine + text[end:])
    code, out = _rap("generate", "model.yaml", cwd=pkg)
    assert code == 0, out
    assert "approves every well-formed plan" not in out
    assert "return 'no plan'" in module.read_text()


def test_a_copied_package_regenerates_its_own_package_not_one_named_after_the_folder(
    tmp_path: Path,
) -> None:
    code, out = _rap("new", "orig", cwd=tmp_path)
    assert code == 0, out
    import shutil

    shutil.copytree(tmp_path / "orig", tmp_path / "copy-2")
    code, out = _rap("generate", "model.yaml", cwd=tmp_path / "copy-2")
    assert code == 0, out
    assert not (tmp_path / "copy-2/copy_2").exists()
    assert "COPY orig/ orig/" in (tmp_path / "copy-2/deploy/Dockerfile").read_text()


def test_rap_new_refuses_a_name_that_import_would_resolve_elsewhere(tmp_path: Path) -> None:
    code, out = _rap("new", "json", cwd=tmp_path)
    assert code == 2
    assert "that name is taken by" in out
    assert not (tmp_path / "json").exists()


def test_a_port_of_an_unknown_type_refuses_the_generation(tmp_path: Path) -> None:
    code, out = _rap("new", "typo", cwd=tmp_path)
    assert code == 0, out
    pkg = tmp_path / "typo"
    model = pkg / "model.yaml"
    model.write_text(
        model.read_text().replace(
            "reading: {direction: in, kind: data, type: Reading,",
            "reading: {direction: in, kind: data, type: Reeding,",
        )
    )
    code, out = _rap("generate", "model.yaml", cwd=pkg)
    assert code == 2
    assert "component 'monitor', port 'reading': type 'Reeding'" in out
    assert "nothing was written" in out


def test_a_region_whose_port_left_the_model_is_reported_and_the_old_file_kept(
    tmp_path: Path,
) -> None:
    code, out = _rap("new", "moved", cwd=tmp_path)
    assert code == 0, out
    pkg = tmp_path / "moved"
    node = pkg / "moved/nodes/analyse.py"
    marker = "    # region user: on_observed\n"
    node.write_text(node.read_text().replace(marker, marker + "    log.info('mine')\n"))
    before = node.read_text()
    model = pkg / "model.yaml"
    model.write_text(model.read_text().replace("observed: {direction: in", "seen: {direction: in"))
    code, out = _rap("generate", "model.yaml", cwd=pkg)
    assert code == 0, out
    assert "on_observed no longer exist" in out
    assert "#     log.info('mine')" in node.read_text()
    assert (pkg / ".rap/previous/moved/nodes/analyse.py").read_text() == before


def test_a_file_rap_rewrites_is_kept_when_it_is_not_as_rap_wrote_it(tmp_path: Path) -> None:
    """rap generate rewrites some files whole (messages, samples, deploy/): one edited by
    hand since, or a file of the user's at that place, is kept in .rap/previous first and
    named in a warning; one as rap wrote it is rewritten quietly. tests/conftest.py has
    regions: the user's fixtures stay in it."""
    code, out = _rap("new", "kept", cwd=tmp_path)
    assert code == 0, out
    pkg = tmp_path / "kept"
    samples = pkg / "kept" / "samples.py"
    generated = samples.read_text()
    code, out = _rap("generate", "model.yaml", cwd=pkg)
    assert code == 0, out
    assert "not as rap last wrote them" not in out  # untouched: nothing to keep
    mine = generated + "\n\nEXTRA = 'mine'\n"
    samples.write_text(mine)
    conftest = pkg / "tests" / "conftest.py"
    fixture = "@pytest.fixture\ndef ship() -> str:\n    return 'mine'\n"
    conftest.write_text(
        conftest.read_text().replace(
            "# region user: fixtures\n", f"# region user: fixtures\n{fixture}"
        )
    )
    code, out = _rap("generate", "model.yaml", cwd=pkg)
    assert code == 0, out
    assert "1 file(s) rap rewrites were not as rap last wrote them: kept/samples.py" in out
    assert (pkg / ".rap/previous/kept/samples.py").read_text() == mine
    assert samples.read_text() == generated
    assert fixture in conftest.read_text()
    # a package generated into a folder that already had its own file there
    other = tmp_path / "other"
    (other / "kept").mkdir(parents=True)
    (other / "kept" / "samples.py").write_text("# the user's own samples\n")
    (other / "model.yaml").write_text((pkg / "model.yaml").read_text())
    code, out = _rap("generate", "model.yaml", "--package", "kept", cwd=other)
    assert code == 0, out
    assert "kept/samples.py" in out
    assert (other / ".rap/previous/kept/samples.py").read_text() == "# the user's own samples\n"


REPO = Path(__file__).resolve().parents[3]
SHIP_DESIGN = REPO / "examples" / "ship_motion" / "design"


def _ruff(package: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``ruff`` with the repository's settings, run in the package as its own project."""
    return subprocess.run(
        [sys.executable, "-m", "ruff", *args, "--config", str(REPO / "pyproject.toml"), "."],
        cwd=package,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_generated_packages_pass_ruff_and_regenerate_without_churn(tmp_path: Path) -> None:
    pytest.importorskip("ruff")  # a dev dependency of the repository
    code, out = _rap("new", "plant", cwd=tmp_path)
    assert code == 0, out
    code, out = _rap("new", "ship", "--from", str(SHIP_DESIGN), cwd=tmp_path)
    assert code == 0, out
    for pkg in (tmp_path / "plant", tmp_path / "ship"):
        lint = _ruff(pkg, "check", "--no-cache")
        assert lint.returncode == 0, lint.stdout + lint.stderr
        fmt = _ruff(pkg, "format", "--check", "--no-cache")
        assert fmt.returncode == 0, fmt.stdout + fmt.stderr
    ship = tmp_path / "ship"
    messages = (ship / "ship" / "messages.py").read_text()
    # constraint literals keep their type: ints stay ints, floats stay floats
    assert "samples: Annotated[int, msgspec.Meta(ge=0, le=9223372036854775807)]" in messages
    assert "training_error: Annotated[float, msgspec.Meta(ge=0.0)]" in messages
    plant = (tmp_path / "plant" / "plant" / "messages.py").read_text()
    assert "msgspec.Meta(ge=-10, le=10," in plant
    # the design's Measurement_Unit ends the docs of its Time fields
    assert 'trained_from: Annotated[float, msgspec.Meta(description="unit: s")]' in messages
    # regenerating from the written model changes nothing
    before = {p: p.read_text() for p in ship.rglob("*") if p.is_file() and ".rap" not in p.parts}
    code, out = _rap("generate", "model.yaml", cwd=ship)
    assert code == 0, out
    after = {p: p.read_text() for p in before}
    assert [p.name for p in before if before[p] != after[p]] == []


GATE_PROBE = """
import time
from rap_schemas import PlanProposal, Verdict
from {pkg} import messages
from {pkg}.nodes import execute

now = time.time_ns()
plan = messages.Setpoint(target=1.0)
old = PlanProposal(
    plan_uid=b"u" * 16, plan_type=plan.TYPE, plan=plan, proposer="plan", created=now - 30 * 10**9
)
verdict = Verdict(
    plan_uid=old.plan_uid, approved=True, legitimator="legitimate", ts=now, proposal=old
)
print(execute.Config().plan_max_age, execute.gate.check(verdict, "legitimate", now))
"""


@pytest.mark.parametrize(("config", "says"), [("", "1.0 plan"), ("60", "60.0 None")])
def test_the_models_plan_max_age_reaches_the_gate(tmp_path: Path, config: str, says: str) -> None:
    """A model whose execute stage says ``config: {plan_max_age: 60}``: its generated gate
    takes a 30 s old approval (the default 1 s would refuse it as stale)."""
    from rap_cli.generate_cli import STARTER

    model = STARTER.format(name="gated")
    if config:
        model = model.replace(
            "    doc: Acts only on set points the legitimate stage approved (the gate).\n",
            "    doc: Acts only on set points the legitimate stage approved (the gate).\n"
            f"    config: {{plan_max_age: {config}}}\n",
        )
        assert f"plan_max_age: {config}" in model
    (tmp_path / "model.yaml").write_text(model)
    code, out = _rap("generate", "model.yaml", "--package", "gated", cwd=tmp_path)
    assert code == 0, out
    (tmp_path / "probe_gate.py").write_text(GATE_PROBE.format(pkg="gated"))
    run = subprocess.run(
        [sys.executable, "probe_gate.py"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith(says), run.stdout
    if not config:
        assert "is stale" in run.stdout


def test_a_src_layout_project_gets_its_package_in_src(tmp_path: Path) -> None:
    proj = tmp_path / "proj"
    (proj / "src" / "proj").mkdir(parents=True)
    mine = '"""The project\'s own package: rap generate writes next to its modules."""\n'
    (proj / "src" / "proj" / "__init__.py").write_text(mine)
    (proj / "src" / "proj" / "physics.py").write_text("G = 9.81\n")
    (tmp_path / "model.yaml").write_text(_starter_model("proj"))
    code, out = _rap("generate", "model.yaml", "-o", "proj", "--package", "proj", cwd=tmp_path)
    assert code == 0, out
    assert not (proj / "proj").exists()
    for rel in ("messages.py", "samples.py", "nodes/execute.py", "schemas/Setpoint.schema.json"):
        assert (proj / "src" / "proj" / rel).is_file(), rel
    assert (proj / "src" / "proj" / "__init__.py").read_text() == mine  # the user's, kept
    assert (proj / "tests" / "test_loop.py").is_file()
    assert (proj / "deploy" / "Dockerfile").is_file()
    assert "COPY src/proj/ proj/" in (proj / "deploy" / "Dockerfile").read_text()
    assert "kept as you have them: src/proj/__init__.py" in out
    # the generated tests find the package in src/ without an install
    run = _pytest(proj)
    assert run.returncode == 0, run.stdout + run.stderr
    # regenerating from the package's own model finds the package in src/ again
    code, out = _rap("generate", "model.yaml", cwd=proj)
    assert code == 0, out
    assert not (proj / "proj").exists()


def _starter_model(name: str) -> str:
    from rap_cli.generate_cli import STARTER

    return STARTER.format(name=name)


def test_the_package_of_the_target_folder_itself_is_not_taken(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from rap_cli.generate_cli import _taken

    (tmp_path / "src" / "ownpkg").mkdir(parents=True)
    (tmp_path / "src" / "ownpkg" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path / "src"))  # installed, say as editable
    assert _taken("ownpkg", tmp_path) is None
    assert _taken("ownpkg", tmp_path / "elsewhere") is not None
    assert _taken("json", tmp_path) is not None


def test_string_literals_and_unused_imports_as_ruff_wants_them() -> None:
    import ast

    from rap_cli.generate.pyfmt import prune_imports, q

    for text, literal in [
        ("plain", '"plain"'),
        ("it's", '"it\'s"'),
        ('say "hi"', "'say \"hi\"'"),
        ("both ' and \"", '"both \' and \\""'),
        ("line\nbreak\\", '"line\\nbreak\\\\"'),
    ]:
        assert q(text) == literal
        assert ast.literal_eval(q(text)) == text
    module = (
        "from __future__ import annotations\n\n"
        "import enum\nimport logging\n\n"
        "from rap_schemas import Empty, PlanProposal, Verdict\n\n"
        "from .. import messages\nfrom ..samples import sample\n\n"
        "# region user: imports\nfrom os import path\n\n# endregion user: imports\n\n"
        "log = logging.getLogger(__name__)\n\n\n"
        "def f(p: PlanProposal) -> None:\n"
        "    # region user: f\n    print(sample, path)\n    # endregion user: f\n"
    )
    pruned = prune_imports(module)
    assert "import enum" not in pruned
    assert "from rap_schemas import PlanProposal\n" in pruned  # Empty, Verdict: unused
    assert "from .. import messages" not in pruned
    assert "from ..samples import sample\n" in pruned  # the user's region uses it
    assert "from os import path\n" in pruned  # a region's own imports are the user's
    assert "\n\n\n\n" not in pruned.split("log =")[0]
    assert prune_imports(pruned) == pruned
