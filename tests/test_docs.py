"""The Python blocks of docs/extending.md run as written, in order, and do what the page
says: the new factor type is registered, its Jacobian matches central differences, and
in the graph the centre prior settles the landmark's badly observed distance."""

import re
from pathlib import Path

import numpy as np

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"


def test_extending_md_blocks_run_in_order(capsys):
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)
    assert len(blocks) >= 3, "docs/extending.md lost its examples"
    scope: dict = {"__name__": "docs_extending"}
    for i, code in enumerate(blocks):
        exec(compile(code, f"{DOC}:block{i + 1}", "exec"), scope)
    out = capsys.readouterr().out
    assert "boxes + centre prior" in out
    truth = scope["truth"]
    err = {name: np.linalg.norm(np.asarray(r.values[scope["L"](0)].center) - truth.center)
           for name, r in (("boxes", scope["boxes_only"]), ("prior", scope["with_prior"]))}
    assert err["prior"] < 0.05 and err["prior"] < err["boxes"], err
    # the factor type works like the built-in ones: the default noise, one group per type
    f = scope["CentrePriorFactor"](scope["L"](0), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(np.diag(f.sqrt_info), [20.0, 20.0, 20.0])


def test_formats_md_class_table_matches_the_code():
    """docs/formats.md's built-in class table lists every entry of the code's, with the same
    semi-axes, spread and source."""
    from spdslam.io import BUILTIN_CLASSES, CLASS_SOURCES

    text = (Path(__file__).resolve().parents[1] / "docs" / "formats.md").read_text(encoding="utf-8")
    for label, cp in BUILTIN_CLASSES.items():
        r = ", ".join(f"{x:.4g}" for x in cp.radii)
        assert f"| `{label}` | {r} | {cp.sigma:g} | {CLASS_SOURCES[label]} |" in text, label


def test_your_data_md_blocks_write_a_sequence_that_maps(tmp_path, monkeypatch, capsys):
    """docs/your-data.md's Python blocks run in order (in a scratch folder): the canonical
    folder they write reads back with every box, and the run maps the room's objects."""
    doc = Path(__file__).resolve().parents[1] / "docs" / "your-data.md"
    blocks = re.findall(r"```python\n(.*?)```", doc.read_text(encoding="utf-8"), re.S)
    assert len(blocks) == 2, "docs/your-data.md lost its examples"
    monkeypatch.chdir(tmp_path)
    scope: dict = {"__name__": "docs_your_data"}
    for i, code in enumerate(blocks):
        exec(compile(code, f"{doc}:block{i + 1}", "exec"), scope)
    rec, seq, result = scope["rec"], scope["seq"], scope["result"]
    assert len(seq.detections) == len(rec.detections) and len(seq) == len(rec)
    assert all(d.instance is None for d in seq.detections)
    assert len(result.objects) == len(rec.objects_gt) == 3
    assert f"3 objects mapped from {len(rec.detections)} boxes" in capsys.readouterr().out
