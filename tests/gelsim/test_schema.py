"""gelsim.schema: the dataset format in one place, and docs/dataset.md's layout section agreeing with it."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from gelsim import schema

README = Path(__file__).resolve().parents[2] / "docs" / "dataset.md"   # the layout moved here from the README


def _layout_section() -> str:
    text = README.read_text()
    start = text.index("## Layout (what `stam` reads)")
    return text[start:text.index("\n## ", start + 1)]


def test_constants_are_defined_once():
    import gelsim.dataset
    import gelsim.motion
    import gelsim.stats
    import stam.data

    assert gelsim.motion.ACTIONS is schema.ACTIONS and gelsim.stats.ACTIONS is schema.ACTIONS
    assert gelsim.dataset.ACTIONS is schema.ACTIONS and gelsim.dataset.SPLITS is schema.SPLITS
    assert stam.data.SPLITS is schema.SPLITS


def test_readme_layout_names_the_schema_paths():
    sec = _layout_section()
    assert f"DIR/{schema.MANIFEST} " in sec
    assert f"DIR/{schema.video_stem(7, '<id>').replace('f007', 'fNNN')}.mp4" in sec
    assert f"DIR/{schema.labels_path(7, '<id>').replace('f007', 'fNNN')} " in sec
    assert f"DIR/{schema.record_path('<id>')} " in sec
    assert f"DIR/{schema.PREVIEWS_DIR}/" in sec
    assert schema.video_stem(1, schema.sequence_id(1, 0)) == "videos/f001/f001-s0000"
    assert schema.labels_path(12, "f012-s0003") == "labels/f012/f012-s0003.npz"


def test_readme_manifest_example_has_the_schema_fields_in_order():
    sec = _layout_section()
    block = sec[sec.index("```json") + len("```json"):]
    doc = json.loads(block[:block.index("```")])
    assert tuple(k for k in doc if k not in schema.OPTIONAL_MANIFEST_FIELDS) == schema.MANIFEST_FIELDS
    assert doc["format"] == schema.FORMAT and doc["format_version"] == schema.FORMAT_VERSION
    assert tuple(doc["profile"]) == schema.PROFILE_FIELDS
    assert tuple(doc["fabrics"][0]) == schema.FABRIC_FIELDS
    entry = tuple(doc["sequences"][0])
    assert entry[:len(schema.SEQUENCE_FIELDS)] == schema.SEQUENCE_FIELDS
    assert set(entry[len(schema.SEQUENCE_FIELDS):]) <= set(schema.OPTIONAL_SEQUENCE_FIELDS)
    assert tuple(doc["splits"]) == schema.SPLITS


def test_readme_label_table_is_the_schema():
    """Every key of docs/dataset.md's label table is a schema key with the same shape, and back."""
    rows = re.findall(r"^\| (`[^|]+`) \| ([^|]+) \|", _layout_section(), re.M)
    shapes = {}
    for keys, shape_cell in rows:
        names = re.findall(r"`(\w+)`", keys)
        cell = re.findall(r"\(([^)]*)\)", shape_cell)
        if len(cell) == 1:      # one shape for all the row's keys
            cell = cell * len(names)
        assert len(cell) == len(names), keys
        for name, shp in zip(names, cell):
            shapes[name] = tuple(int(d) if d.strip().isdigit() else d.strip() for d in shp.split(",") if d.strip())
    assert set(shapes) == set(schema.LABEL_KEYS)
    for key in schema.LABELS:
        assert shapes[key.name] == key.shape, key.name


def _labels(T=5, N=4) -> dict:
    out = {}
    for key in schema.LABELS:
        shape = tuple(T if d == "T" else N if d == "N" else d for d in key.shape)
        out[key.name] = np.zeros(shape, bool if key.kind == "b" else np.float32)
    return out


def test_label_problems():
    assert schema.label_problems(_labels(), 5) == []
    lab = _labels()
    del lab["contact_bbox_px"], lab["contact_centroid_px"]          # optional: older version-1 datasets
    assert schema.label_problems(lab, 5) == []
    del lab["shear_mm"]
    assert schema.label_problems(lab, 5) == ["labels lack 'shear_mm'"]
    probs = schema.label_problems(_labels(T=6), 5)
    assert len(probs) == len([k for k in schema.LABELS if "T" in k.shape])
    assert "labels 'time_s' have shape (6,), expected (T=5)" in probs
    lab = _labels()
    lab["markers_rest_px"] = np.zeros((3, 2), np.float32)            # N differs from markers_xy_px's
    assert schema.label_problems(lab, 5) == ["labels 'markers_rest_px' have shape (3, 2), expected (N=4, 2)"]
    lab = _labels()
    lab["in_contact"] = np.zeros(5, np.float32)
    assert schema.label_problems(lab, 5) == ["labels 'in_contact' have dtype float32, expected kind 'b'"]
    lab = _labels(N=0)                                                # a sensor without markers
    assert schema.label_problems(lab, 5) == []


def test_manifest_helpers():
    seqs = [{"id": "a", "split": "train"}, {"id": "b", "split": "test"}, {"id": "c", "split": "train"}]
    m = schema.make_manifest(complete=True, generator_version="x", seed=1, options={}, catalog_version="v",
                             profile={"name": "p", "width_px": 2, "height_px": 1, "mm_per_px": 0.1, "fps_hz": 30.0,
                                      "extra": 1},
                             fabrics=[{"id": 1, "name": "n", "family": "f", "material": "m", "extra": 2}],
                             libraries={k: "1.0" for k in schema.LIBRARIES}, sequences=seqs, units=[])
    assert tuple(m)[:-2] == schema.MANIFEST_FIELDS[:-1] and tuple(m)[-2:] == ("units", "sequences")
    assert m["splits"] == {"train": 2, "val": 0, "test": 1}
    assert "extra" not in m["profile"] and "extra" not in m["fabrics"][0]
    assert schema.manifest_problem(m) is None
    assert "not a gelsim dataset" in schema.manifest_problem({"format": "coco"})
    assert "not a gelsim dataset" in schema.manifest_problem([1, 2])
    assert "format_version 2" in schema.manifest_problem(dict(m, format_version=2))
    rec = {k: k for k in schema.SEQUENCE_FIELDS} | {"timings_s": {}, "seconds": 1.0}
    assert tuple(schema.sequence_entry(rec)) == schema.SEQUENCE_FIELDS
    assert schema.sequence_entry(rec | {"unit": 3})["unit"] == 3
    with pytest.raises(KeyError):
        schema.sequence_entry({"id": "x"})


def test_sha256_of_file_and_png_directory(tmp_path):
    import hashlib

    (tmp_path / "f.bin").write_bytes(b"abc")
    assert schema.sha256_of(tmp_path / "f.bin") == hashlib.sha256(b"abc").hexdigest()
    d = tmp_path / "frames"
    d.mkdir()
    (d / "000001.png").write_bytes(b"2")
    (d / "000000.png").write_bytes(b"1")
    (d / "notes.txt").write_bytes(b"ignored")
    assert schema.sha256_of(d) == hashlib.sha256(b"12").hexdigest()


def test_dataset_doc_nuisance_record_table_is_the_record():
    """docs/dataset.md's table of the per-frame nuisance record names every key of
    gelsim.nuisance.record.RECORD, with its dtype, and no other."""
    from gelsim.nuisance.record import RECORD

    text = README.read_text()
    start = text.index("## The per-frame nuisance record")
    sec = text[start:text.index("\n## ", start + 1)]
    rows = dict(re.findall(r"^\| `(\w+)` \| \([^)]*\) (\w+) \|", sec, re.M))
    assert rows == {k.name: k.dtype for k in RECORD}
