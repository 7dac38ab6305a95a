"""The architecture is enforced: import-linter's contracts in pyproject.toml (imports only downward,
dmrt core <- baselines/reference <- bench <- dmrt.app; no plotting in library code) hold for the
tree, and an upward import makes them fail."""

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dmrt", "baselines", "reference", "bench", "shaders")


def lint_imports(root: Path) -> subprocess.CompletedProcess:
    """Run import-linter's command on the packages under ``root`` (those shadow the installed ones)."""
    exe = Path(sys.executable).with_name("lint-imports")
    return subprocess.run([str(exe), "--config", str(root / "pyproject.toml"), "--no-cache"], cwd=root,
                          env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"}, capture_output=True, text=True)


def test_contracts_hold():
    r = lint_imports(ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


def test_upward_import_breaks_the_contract(tmp_path):
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    scene = tmp_path / "dmrt" / "io" / "scene.py"
    scene.write_text(scene.read_text() + "\n\ndef _upward():\n    from dmrt.runtime.renderer import Renderer  # noqa\n")
    r = lint_imports(tmp_path)
    assert r.returncode != 0 and "BROKEN" in r.stdout
    assert "dmrt.io.scene -> dmrt.runtime.renderer" in r.stdout
