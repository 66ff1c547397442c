"""The package is what `rap generate` makes of the design, filled in: regenerating it from the
design changes nothing (every region of ours kept, every generated line as committed)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
KEPT = ("design", "src", "tests", "model.yaml", "pyproject.toml", "README.md", "deploy")
WHEELS = "deploy/wheels/"
"""Where the image's wheels go: git-ignored (.gitignore), so not in a fresh clone."""


def _rap(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(Path(sys.executable).parent / "rap"), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes()
        for name in KEPT
        for p in ([root / name] if (root / name).is_file() else (root / name).rglob("*"))
        if p.is_file()
        and "__pycache__" not in p.parts
        and not p.relative_to(root).as_posix().startswith(WHEELS)
    }


def test_importing_and_generating_again_changes_nothing(tmp_path: Path) -> None:
    copy = tmp_path / "ship_motion"
    copy.mkdir()
    for name in KEPT:
        src = HERE / name
        if src.is_dir():
            shutil.copytree(src, copy / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(src, copy / name)
    before = _files(copy)
    imported = _rap("import", "aadl", "design/", "-o", "model.yaml", cwd=copy)
    assert imported.returncode == 0, imported.stderr
    generated = _rap("generate", "model.yaml", "--package", "ship_motion", cwd=copy)
    assert generated.returncode == 0, generated.stderr
    assert "approves every well-formed plan" not in generated.stderr  # our check() is written
    after = _files(copy)
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert changed == [], f"regenerating changed {changed}"
