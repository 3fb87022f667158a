"""The README's FEM example runs as printed and gives the closed-form answers it compares with."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_fem_example(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    example = next(b for b in blocks if "QuasiStaticSolver" in b)
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(example, "README.md", "exec"), scope)
    eq, L, E, force = scope["eq"], scope["L"], scope["E"], scope["force"]
    assert eq.travel["press"][0] == pytest.approx(force * L / (E * L * L), rel=0.01)
    assert eq.von_mises[0].mean() == pytest.approx(force / L**2, rel=0.01)
    assert (tmp_path / "box.vtu").stat().st_size > 0
