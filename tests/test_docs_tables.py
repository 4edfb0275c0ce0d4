"""tools/docs_tables.py: a JSON record of `bmi eval --json F` / `bmi bench X --json F` fills its marked section."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "docs_tables.py"


def _tool():
    spec = importlib.util.spec_from_file_location("docs_tables", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


RECORD = {
    "command": "bmi eval --decoder classical --conditions standard --json out/eval.json",
    "commit": "1e227c8a0b1c2d3e4f5a6b7c8d9e0f1a2b3c4d5e",
    "date": "2026-11-27",
    "machine": {"platform": "x86_64", "cores": 2, "python": "3.11.7", "load_average": [2.5, 1.9, 1.8]},
    "tables": [{
        "title": "Benchmark, σ 0.005",
        "columns": ["condition", "region", "AbsRel", "δ1", "tiles"],
        "rows": [["standard", "centre", 0.47512, 0.516, 12.0], ["standard", "edge", 0.3901, None, 12]],
        "notes": "12 tiles per region, seed 20260.",
    }],
}

BEFORE = "# Results\n\nHand text above | kept.\n\n<!-- generated: eval -->\nold table\n<!-- end generated: eval -->\n\nBelow, kept too.\n"


def test_record_round_trips_into_its_section(tmp_path):
    doc, rec = tmp_path / "results.md", tmp_path / "eval.json"
    doc.write_text(BEFORE)
    rec.write_text(json.dumps(RECORD))
    out = subprocess.run([sys.executable, str(TOOL), str(doc), f"eval={rec}"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    text = doc.read_text()
    head, rest = text.split("<!-- generated: eval -->\n")
    body, tail = rest.split("<!-- end generated: eval -->")
    assert head == "# Results\n\nHand text above | kept.\n\n"
    assert tail == "\n\nBelow, kept too.\n"
    assert "old table" not in body
    assert body.splitlines()[0] == ("Command `bmi eval --decoder classical --conditions standard --json out/eval.json`"
                                    " · commit `1e227c8a0b1c` · 2026-11-27 · x86_64, 2 cores, Python 3.11.7,"
                                    " load 2.5 / 1.9 / 1.8.")
    assert "### Benchmark, σ 0.005" in body
    assert "| condition | region | AbsRel | δ1 | tiles |\n|---|---|---|---|---|\n" in body
    assert "| standard | centre | 0.4751 | 0.516 | 12 |" in body
    assert "| standard | edge | 0.3901 | – | 12 |" in body
    assert "12 tiles per region, seed 20260." in body
    # A second run replaces the section again and leaves the rest as it was: regeneration is idempotent.
    assert subprocess.run([sys.executable, str(TOOL), str(doc), f"eval={rec}"]).returncode == 0
    assert doc.read_text() == text


def test_null_commit_says_so():
    record = dict(RECORD, commit=None)
    assert "commit not recorded" in _tool().render_section(record).splitlines()[0]


@pytest.mark.parametrize("mutate, message", [
    (lambda r: r.pop("date"), "missing field 'date'"),
    (lambda r: r.update(commit=7), "field 'commit' must be a string or null"),
    (lambda r: r["tables"][0]["rows"].append([1, 2]), "tables[0].rows[2] has 2 cells; columns has 5"),
    (lambda r: r.update(tables=[]), "field 'tables' is empty"),
    (lambda r: r["tables"][0].pop("columns"), "tables[0]: missing field 'columns'"),
])
def test_malformed_record_is_refused_by_name_and_doc_untouched(tmp_path, mutate, message):
    record = json.loads(json.dumps(RECORD))
    mutate(record)
    doc, rec = tmp_path / "results.md", tmp_path / "bad.json"
    doc.write_text(BEFORE)
    rec.write_text(json.dumps(record))
    out = subprocess.run([sys.executable, str(TOOL), str(doc), f"eval={rec}"], capture_output=True, text=True)
    assert out.returncode == 1
    assert message in out.stderr and str(rec) in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    assert doc.read_text() == BEFORE


def test_missing_markers_and_bad_json_are_clear_errors(tmp_path):
    tool = _tool()
    doc, rec = tmp_path / "results.md", tmp_path / "eval.json"
    doc.write_text("# No markers here\n")
    rec.write_text(json.dumps(RECORD))
    with pytest.raises(tool.RecordError, match="no section 'eval'"):
        tool.update_document(doc, {"eval": rec})
    rec.write_text("{not json")
    with pytest.raises(tool.RecordError, match="not JSON"):
        tool.load_record(rec)
