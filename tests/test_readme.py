"""The README's example runs and recovers the object."""

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_example_recovers_the_object(capsys):
    code = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert code, "README has no python example"
    scope: dict = {}
    exec(compile(code[0], str(README), "exec"), scope)
    result, truth = scope["result"], scope["truth"]
    assert result.converged
    est = result.values[scope["L"](0)]
    np.testing.assert_allclose(est.radii, [0.6, 0.4, 0.3], atol=1e-6)
    np.testing.assert_allclose(est.center, truth.center, atol=1e-6)
    assert capsys.readouterr().out.strip()
