"""Versioned, checked, untrusted-safe map format.

- every map records its format version and the slamreloc version that wrote it;
- a map from a newer format is refused naming both versions; format 1 is still read;
- small maps of every format (tests/data/maps/format-N, made by `python -m tests.test_map_format`)
  are committed and must keep loading, with the same predictions, in every future version;
- loading never runs code from the map: pickle payloads (which would create a file) are
  refused in regressor.pt, regressor.npz and database.npz.
"""

from __future__ import annotations

import json
import pickle
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import slamreloc
from slamreloc.errors import InputError
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.map.format import (DATABASE, FORMAT_VERSION, LABELLED, LEGACY_WEIGHTS, META, NEW,
                                  PROVENANCE, PSEUDO, WEIGHTS, sha256_file)
from slamreloc.map.meta import CameraMeta, FeatureMeta, MapMeta, RegressorMeta
from slamreloc.map.write import migrate_map, save_map
from slamreloc.map.scene_map import MapDatabase, SceneMap

FIXTURES = Path(__file__).parent / "data" / "maps"
PROBE = np.linspace(-1, 1, 5 * 8, dtype=np.float32).reshape(5, 8)  # descriptors to predict


class Payload:
    """Unpickling this runs code: it creates the file `target`."""

    def __init__(self, target: Path) -> None:
        self.target = Path(target)

    def __reduce__(self):
        return (Path.touch, (self.target,))


def _fixture_parts():
    """A tiny deterministic map: regressor, database, metadata."""
    torch.manual_seed(1)
    rng = np.random.default_rng(1)
    cfg = RegressorConfig(in_dim=8, hidden=(16,), head="clusters", n_clusters=4)
    model = SceneCoordinateRegressor(cfg)
    with torch.no_grad():
        model.centres.copy_(torch.from_numpy(rng.normal(size=(4, 3)).astype(np.float32)))
        model.out_mean.copy_(torch.tensor([1.0, 2.0, 3.0]))
    n = 20
    db = MapDatabase(rng.normal(size=(n, 8)).astype(np.float32), rng.normal(size=(n, 3)),
                     rng.random((n, 2)) * 30, np.arange(n) % 2, ["seq-01/frame-000000",
                                                                  "seq-01/frame-000001"],
                     np.stack([np.eye(4), np.eye(4)]))
    meta = MapMeta(features=FeatureMeta("sift", {"max_keypoints": 256}),
                   regressor=RegressorMeta("tiny", cfg.to_dict(), model.num_parameters()),
                   labels={"n_labelled": n}, train={"epochs": 0},
                   camera=CameraMeta(64, 48, 60.0, 60.0, 32.0, 24.0))
    return model, db, meta


def make_map(out: Path, tag: str = "") -> Path:
    model, db, meta = _fixture_parts()
    return save_map(out, replace(meta, extra={"tag": tag}), model, db)


def make_format1_map(out: Path) -> Path:
    """What slamreloc's format-1 writer produced: regressor.pt (torch.save), "version": 1."""
    model, db, meta = _fixture_parts()
    out.mkdir(parents=True)
    state = {k: (v.half() if v.is_floating_point() and v.dim() > 0 and k.startswith("mlp")
                 else v) for k, v in model.state_dict().items()}
    torch.save(state, out / LEGACY_WEIGHTS)
    np.savez(out / DATABASE, descriptors=db.descriptors.astype(np.float16),
             points=db.points.astype(np.float32), keypoints=db.keypoints.astype(np.float32),
             frame_index=db.frame_index.astype(np.int32), world_from_cam=db.world_from_cam)
    body = {k: v for k, v in meta.to_json().items() if k not in ("format", "format_version")}
    (out / META).write_text(json.dumps({"format": "slamreloc-map", "version": 1, **body,
                                        "frame_names": db.frame_names}, indent=1))
    return out


def _predict(root: Path) -> list:
    m = SceneMap.load(root)
    with torch.no_grad():
        return m.regressor(torch.from_numpy(PROBE)).tolist()


def write_fixtures() -> None:
    """Create the committed fixture of today's format (and format 1) if missing."""
    makers = {1: make_format1_map, FORMAT_VERSION: make_map}
    for version, maker in makers.items():
        out = FIXTURES / f"format-{version}"
        if out.exists():
            continue
        maker(out)
        (FIXTURES / f"format-{version}.expected.json").write_text(json.dumps(
            {"slamreloc_version": slamreloc.__version__, "predictions": _predict(out)}))
        (out.parent / f".{out.name}.lock").unlink(missing_ok=True)
        print(f"wrote {out}")


def test_todays_format_has_a_committed_fixture():
    assert (FIXTURES / f"format-{FORMAT_VERSION}" / META).is_file(), (
        f"no committed map of format {FORMAT_VERSION}: run `python -m tests.test_map_format` "
        "and commit tests/data/maps")


@pytest.mark.parametrize("fixture", sorted(p.name for p in FIXTURES.glob("format-*")
                                           if p.is_dir()))
def test_committed_maps_of_every_format_still_load(fixture, tmp_path):
    """A map written by an earlier (or this) version loads, with the same predictions."""
    root = tmp_path / fixture
    shutil.copytree(FIXTURES / fixture, root)
    expected = json.loads((FIXTURES / f"{fixture}.expected.json").read_text())
    np.testing.assert_allclose(_predict(root), expected["predictions"], rtol=1e-3, atol=1e-3)
    m = SceneMap.load(root)
    assert m.format_version == int(fixture.split("-")[1])
    assert len(m.database.points) == 20 and m.camera.width == 64
    # an older format is migrated (rewritten in today's format) without changing predictions
    migrate_map(root)
    assert SceneMap.load(root).format_version == FORMAT_VERSION
    np.testing.assert_allclose(_predict(root), expected["predictions"], rtol=1e-3, atol=1e-3)
    assert not (root / LEGACY_WEIGHTS).exists()


def test_a_map_records_its_format_and_writer(tmp_path):
    meta = json.loads((make_map(tmp_path / "m") / META).read_text())
    assert meta["format"] == "slamreloc-map" and meta["format_version"] == FORMAT_VERSION
    assert meta["slamreloc_version"] == slamreloc.__version__
    assert set(meta["files"]) == {WEIGHTS, DATABASE}
    assert not (tmp_path / "m" / LEGACY_WEIGHTS).exists()


def test_provenance_is_checksummed_and_read_through_the_map(tmp_path):
    """An updated map's provenance.npz is listed with its checksum and read by the map's own
    reader, also when the regressor is not built (the viewer's open)."""
    model, db, meta = _fixture_parts()
    source = np.array([LABELLED] * 15 + [PSEUDO] * 3 + [NEW] * 2, np.int8)
    quality = np.linspace(0.1, 1.0, len(source)).astype(np.float32)
    root = save_map(tmp_path / "m", meta, model, db,
                    extra={PROVENANCE: {"source": source, "quality": quality}})
    assert set(json.loads((root / META).read_text())["files"]) == {WEIGHTS, DATABASE, PROVENANCE}
    m = SceneMap.load(root, regressor=False)
    assert m.regressor is None and len(m.database.points) == len(source)
    np.testing.assert_array_equal(m.provenance.source, source)
    np.testing.assert_array_equal(m.provenance.quality, quality)
    assert SceneMap.load(make_map(tmp_path / "plain")).provenance is None
    np.savez(root / PROVENANCE, source=source[::-1], quality=quality)
    with pytest.raises(InputError, match=f"{PROVENANCE}: contents do not match the checksum"):
        SceneMap.load(root, regressor=False).provenance  # noqa: B018
    for arrays, message in (({"source": source[:-1], "quality": quality[:-1]}, "expected the 20"),
                            ({"source": source + 3, "quality": quality}, "codes other than"),
                            ({"source": source}, "missing array 'quality'")):
        root = save_map(tmp_path / "m", meta, model, db, extra={PROVENANCE: arrays})
        with pytest.raises(InputError, match=message):
            SceneMap.load(root, regressor=False).provenance  # noqa: B018


def test_opening_without_the_regressor_still_checks_the_weights(tmp_path):
    root = make_map(tmp_path / "m")
    (root / WEIGHTS).write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(InputError, match=f"{WEIGHTS}: contents do not match"):
        SceneMap.load(root, regressor=False)


def test_a_newer_format_is_refused_naming_both_versions(tmp_path):
    root = make_map(tmp_path / "m")
    meta = json.loads((root / META).read_text())
    (root / META).write_text(json.dumps({**meta, "format_version": 999,
                                         "slamreloc_version": "7.3.1"}))
    with pytest.raises(InputError) as err:
        SceneMap.load(root)
    msg = str(err.value)
    assert "999" in msg and "7.3.1" in msg and slamreloc.__version__ in msg
    assert f"1 to {FORMAT_VERSION}" in msg and str(root / META) in msg


@pytest.mark.parametrize("content, message", [
    ("[]", "expected a JSON object, got list"),
    ('{"format": "slamreloc-map"}', "format_version must be an integer"),
    ('{"format": "slamreloc-map", "format_version": "2"}', "must be an integer"),
    ('{"format": "slamreloc-map", "format_version": 0}', "unknown map format version 0"),
    ("{", "not valid JSON"),
    ("\xff\xfe", "not valid JSON"),
])
def test_malformed_metadata_is_one_line_naming_the_file(tmp_path, content, message):
    root = make_map(tmp_path / "m")
    (root / META).write_text(content, errors="surrogateescape")
    with pytest.raises(InputError, match=message) as err:
        SceneMap.load(root)
    assert str(root / META) in str(err.value) and "\n" not in str(err.value)


def test_missing_keys_and_wrong_types_are_named(tmp_path):
    root = make_map(tmp_path / "m")
    meta = json.loads((root / META).read_text())
    cases = [({**meta, "camera": {**meta["camera"], "fx": "525"}}, "'camera.fx' must be a number"),
             ({k: v for k, v in meta.items() if k != "labels"}, "missing key 'labels'"),
             ({**meta, "regressor": {**meta["regressor"], "config": {
                 **meta["regressor"]["config"], "hidden": [10 ** 9]}}}, "layer widths"),
             ({**meta, "features": {"name": "sift", "bogus": 1}}, "unknown feature option")]
    for doc, message in cases:
        (root / META).write_text(json.dumps(doc))
        with pytest.raises(InputError, match=message):
            SceneMap.load(root)


def test_weights_of_another_map_or_corrupted_are_refused(tmp_path):
    """The checksum in the metadata binds the three files: no mixed or damaged map loads."""
    a = make_map(tmp_path / "a", tag="a")
    b = tmp_path / "b"
    model, db, meta = _fixture_parts()
    torch.manual_seed(5)
    save_map(b, meta, SceneCoordinateRegressor(model.config), db)
    shutil.copy(b / WEIGHTS, a / WEIGHTS)
    with pytest.raises(InputError, match="do not match the checksum"):
        SceneMap.load(a)
    (a / WEIGHTS).write_bytes(np.random.default_rng(0).bytes(4096))  # the random bytes
    with pytest.raises(InputError, match=f"{WEIGHTS}: contents do not match"):
        SceneMap.load(a)


def test_pickle_payload_in_legacy_weights_is_refused_and_never_run(tmp_path):
    root = make_format1_map(tmp_path / "m")
    target = tmp_path / "payload-ran"
    state = torch.load(root / LEGACY_WEIGHTS, weights_only=True)
    torch.save({**state, "mlp.0.weight": Payload(target)}, root / LEGACY_WEIGHTS)
    # the payload is real: an unsafe load runs it
    torch.load(root / LEGACY_WEIGHTS, weights_only=False)
    assert target.exists()
    target.unlink()
    with pytest.raises(InputError, match="refused") as err:
        SceneMap.load(root)
    assert not target.exists()
    assert "\n" not in str(err.value) and str(root / LEGACY_WEIGHTS) in str(err.value)


@pytest.mark.parametrize("name, key", [(WEIGHTS, "mlp.0.weight"), (DATABASE, "points")])
def test_pickle_payload_in_npz_is_refused_and_never_run(tmp_path, name, key):
    root = make_map(tmp_path / "m")
    target = tmp_path / "payload-ran"
    with np.load(root / name) as z:
        arrays = {k: z[k] for k in z.files}
    arrays[key] = np.array([Payload(target)], dtype=object)
    np.savez(root / name, **arrays)
    with np.load(root / name, allow_pickle=True) as z:  # the payload is real
        z[key]
    assert target.exists()
    target.unlink()
    meta = json.loads((root / META).read_text())
    meta["files"][name] = sha256_file(root / name)  # even with a matching checksum
    (root / META).write_text(json.dumps(meta))
    with pytest.raises(InputError, match="refused: .*pickled Python objects"):
        SceneMap.load(root).database  # noqa: B018
    assert not target.exists()


def test_plain_pickle_named_regressor_pt_in_a_format2_map_is_ignored(tmp_path):
    """A format-2 map reads regressor.npz only; a stray regressor.pt is never opened."""
    root = make_map(tmp_path / "m")
    target = tmp_path / "payload-ran"
    (root / LEGACY_WEIGHTS).write_bytes(pickle.dumps(Payload(target)))
    SceneMap.load(root).database  # noqa: B018
    assert not target.exists()


if __name__ == "__main__":
    sys.exit(write_fixtures())
