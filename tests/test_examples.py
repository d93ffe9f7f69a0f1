"""Every script in ``examples/`` runs to completion (in a subprocess, warnings as errors)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = sorted((Path(__file__).parent.parent / "examples").glob("*.py"))


def test_examples_exist() -> None:
    assert len(EXAMPLES) >= 3


@pytest.mark.parametrize("script", EXAMPLES, ids=lambda p: p.name)
def test_example_runs(script: Path, tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONWARNINGS": "error", "MPLBACKEND": "Agg"}
    done = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True,
                          text=True, env=env, cwd=tmp_path, timeout=600, check=False)
    assert done.returncode == 0, f"{script.name} failed:\n{done.stdout}\n{done.stderr}"
    assert "wrote" in done.stdout
    assert any(tmp_path.iterdir()), "the example wrote nothing into its output directory"


ROOT = Path(__file__).parent.parent


def test_readme_python_example_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The README's API example (read_graph -> optimize -> write_graph) works as printed."""
    import re

    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert blocks, "README.md has no python example"
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    assert (tmp_path / "m3500_opt.g2o").exists()


def test_ci_runs_the_readme_test_command() -> None:
    """.ci/run proves the README: it runs the same test command the quick start shows."""
    readme = (ROOT / "README.md").read_text()
    quick = readme.split("## Quick start", 1)[1].split("```bash\n", 1)[1].split("```", 1)[0]
    commands = [line for line in quick.splitlines() if line.strip()]
    assert commands == ['pip install -e . && hybridpgo demo',
                        'pip install -e ".[dev]" && python -m pytest']
    ci = (ROOT / ".ci" / "run").read_text()
    assert "\npython -m pytest " in ci and 'pip install --quiet -e ".[dev]"' in ci
