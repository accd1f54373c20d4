"""The Python blocks of docs/extending.md run as written, in order, and do what the page
says: the new factor type is registered, its Jacobian matches central differences, and
in the graph the centre prior settles the landmark's badly observed distance."""

import re
from pathlib import Path

import numpy as np
import pytest

from spdslam.io import SequenceFormatError

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"


def test_extending_md_blocks_run_in_order(capsys, tmp_path, monkeypatch):
    from spdslam.io import FORMATS

    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)
    assert len(blocks) >= 5, "docs/extending.md lost its examples"
    monkeypatch.chdir(tmp_path)  # the format example writes a recording here
    scope: dict = {"__name__": "docs_extending"}
    try:
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
        # the input format: registered, found, read box for box, mapped; and the CLI reads it
        fmt = scope["JsonLinesRecording"]
        assert FORMATS["jsonl_recording"] is fmt
        assert "a JSON-lines recording (intrinsics.json and frames.jsonl)" in out
        assert f"{len(scope['room'].objects_gt)} objects mapped from a JSON-lines recording" in out
        from conftest import assert_cli_ok, cli_invoke
        from spdslam.io import read_map

        assert_cli_ok(cli_invoke("run", "recording", "--out", "out", "--max-iterations", "5",
                                 "--option", "min_score=0.5"))
        assert len(read_map(tmp_path / "out" / "map.json")[1]) >= 1
        bad = tmp_path / "recording" / "frames.jsonl"
        lines = bad.read_text(encoding="utf-8").splitlines()
        lines[3] = lines[3].replace('"t"', '"time"')
        bad.write_text("\n".join(lines) + "\n", encoding="utf-8")
        with pytest.raises(SequenceFormatError, match=r"frames.jsonl:4: .*KeyError"):
            scope["read_sequence"](tmp_path / "recording")
    finally:
        FORMATS.pop("jsonl_recording", None)


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
