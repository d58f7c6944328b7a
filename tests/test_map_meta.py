"""The one schema of slamreloc_map.json (slamreloc.map.meta.MapMeta).

- `from_json` then `to_json` gives back every metadata it accepts, key order and values
  included (a rewrite changes no byte it need not), also keys and values it does not type;
- `from_json` refuses a bad field with one line naming the file and the field;
- `stamped` lays the metadata out as `save_map` writes it.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from hypothesis import assume, given
from hypothesis import strategies as st

from slamreloc import __version__
from slamreloc.errors import InputError
from slamreloc.io.jsonio import parse_json
from slamreloc.io.values import check_values
from slamreloc.map.format import DATABASE, FORMAT_VERSION, MAP_FORMAT, WEIGHTS
from slamreloc.registry import DATASET_KINDS, PRESETS
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.map.meta import (TRAIN_RULES, CameraMeta, DatasetMeta, FeatureMeta, MapMeta,
                                RegressorMeta, SurfaceMeta, UpdateMeta)
from slamreloc.types import Camera, frame_name_problem, lens_camera_problem
from tests.fuzzing import damaged_json, fuzz_settings, json_values

PATH = Path("/maps/m/slamreloc_map.json")
SHA = "0123456789abcdef" * 4
finite_json = st.recursive(
    st.none() | st.booleans() | st.integers(-(2 ** 40), 2 ** 40)
    | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                 max_size=3),
    max_leaves=5)  # what a JSON file can hold (parse_json refuses NaN and infinities)
numbers = st.integers(1, 5000) | st.floats(1.0, 5000.0)


@st.composite
def shuffled(draw, doc: dict) -> dict:
    return {k: doc[k] for k in draw(st.permutations(list(doc)))}


ROOTS = st.none() | st.sampled_from(["/data/scene", "/tmp/d", "/"])  # recorded: absolute


@st.composite
def some_keys(draw, typed: dict, strict: tuple[str, ...] = ()) -> dict:
    """A JSON object with some of the keys `typed` names (key -> strategy of the right type),
    each of the right type or, sometimes, any JSON value (never for `strict` keys, which the
    schema checks: counts, sizes, kinds); and sometimes an unknown key."""
    doc = {}
    for key, strategy in typed.items():
        if draw(st.booleans()):
            doc[key] = draw(strategy if key in strict else strategy | finite_json)
    if draw(st.booleans()):
        doc["x_" + draw(st.text("abc", max_size=3))] = draw(finite_json)
    return draw(shuffled(doc))


def _size(config: dict) -> int:
    """The number of parameters of a regressor config (built on the meta device)."""
    with torch.device("meta"):
        return SceneCoordinateRegressor(RegressorConfig.from_dict(config)).num_parameters()


def _arch_for(config: dict, draw) -> str:
    """The preset name a map records with `config`: the preset's own where the config is one,
    any preset's otherwise (a config made in code)."""
    head = config.get("head", "regression")
    fixed = (tuple(config["hidden"]), head, config.get("n_clusters", 1) if head == "clusters"
             else 1)
    for name, preset in PRESETS.items():
        p_head = preset.get("head", "regression")
        if fixed == (tuple(preset["hidden"]), p_head, preset.get("n_clusters", 1)
                     if p_head == "clusters" else 1):
            return name
    return draw(st.sampled_from(sorted(PRESETS)))


def _counts_where_named(record: dict) -> dict:
    """`record` with each key named as a count (`n_*`) holding one (a whole number >= 0)."""
    return {k: (abs(v) if isinstance(v, int) and not isinstance(v, bool) else 3)
            if k.startswith("n_") else v for k, v in record.items()}


@st.composite
def metadata(draw) -> dict:
    """Metadata that `from_json` accepts, in any key order, as parsed from a file."""
    version = draw(st.sampled_from([1, FORMAT_VERSION]))
    features = {"name": "sift"}
    for key, strategy in (("max_keypoints", st.integers(1, 1 << 20)),
                          ("contrast_threshold", st.floats(1e-6, 1.0)),
                          ("n_octave_layers", st.integers(1, 16)), ("root", st.booleans()),
                          ("upsample", st.booleans())):
        if draw(st.booleans()):
            features[key] = draw(strategy)
    config = {"in_dim": draw(st.integers(1, 4096)),
              "hidden": draw(st.lists(st.integers(1, 1 << 16), min_size=1, max_size=4))}
    for key, strategy in (("prototype_init", st.booleans()),
                          ("prototype_threshold", st.floats(-1.0, 1.0) | st.integers(-1, 1)),
                          ("head", st.sampled_from(["regression", "clusters"])),
                          ("n_clusters", st.integers(1, 1 << 16))):
        if draw(st.booleans()):
            config[key] = draw(strategy)
    width, height = draw(st.integers(1, 4096)), draw(st.integers(1, 4096))
    camera = {"width": width, "height": height, "fx": draw(numbers), "fy": draw(numbers),
              "cx": draw(st.floats(-width, 2 * width) | st.integers(-width, 2 * width)),
              "cy": draw(st.floats(-height, 2 * height) | st.integers(-height, 2 * height))}
    lens = draw(st.sampled_from([None, ("PINHOLE", 0), ("OPENCV", 4), ("OPENCV_FISHEYE", 4),
                                 ("SIMPLE_RADIAL", 1)]))
    if lens:
        camera["model"] = lens[0]
        camera["distortion"] = draw(st.lists(st.floats(-0.5, 0.5) | st.integers(-1, 1),
                                             min_size=lens[1], max_size=lens[1]))
    assume(lens_camera_problem(camera.get("model", "PINHOLE"), width, height, camera["fx"],
                               camera["fy"], camera["cx"], camera["cy"],
                               tuple(camera.get("distortion", ()))) is None)
    doc = {"format": MAP_FORMAT,
           "features": draw(shuffled(features)),
           "regressor": draw(shuffled({"arch": _arch_for(config, draw),
                                       "config": draw(shuffled(config)),
                                       "parameters": _size(config),
                                       **draw(some_keys({}))})),
           "labels": draw(shuffled({"n_labelled": draw(st.integers(0, 10 ** 7)),
                                    **draw(st.dictionaries(st.text("nm_", max_size=5),
                                                           finite_json, max_size=3).map(
                                        _counts_where_named))})),
           "camera": draw(shuffled(camera))}
    doc["format_version" if version > 1 or draw(st.booleans()) else "version"] = version
    if version > 1:
        doc["files"] = {WEIGHTS: SHA, DATABASE: SHA,
                        **draw(st.dictionaries(st.sampled_from(["surface.npz", "provenance.npz"]),
                                               st.just(SHA)))}
    # required: every writer lists the training frames (a map without them is refused)
    doc["frame_names"] = draw(st.lists(st.text(max_size=8).filter(
        lambda n: frame_name_problem(n) is None), max_size=4))
    optional = {
        "slamreloc_version": st.text(max_size=8) | finite_json,
        "train": st.dictionaries(st.text("abc_", max_size=5), finite_json, max_size=4)
        | finite_json.filter(lambda v: not isinstance(v, dict) or not {"precision", *TRAIN_RULES}
                             & set(v)),  # typed fields: checked (test_schema_types...)
        "timings_s": st.dictionaries(st.text("abc_", max_size=5), st.floats(0, 100), max_size=3),
        "dataset": some_keys({"root": ROOTS,
                              "kind": st.sampled_from(DATASET_KINDS) | st.none(),
                              "split": st.text(max_size=5), "metric": st.booleans(),
                              "poses": st.sampled_from(["dataset", "slam", "/p/poses.txt"])},
                             strict=("root", "split", "kind", "poses", "metric")) | st.none(),
        "surface": some_keys({"n_points": st.integers(0, 10 ** 6) | st.none(),
                              "voxel_m": st.floats(0.001, 1.0) | st.integers(1, 2)},
                             strict=("n_points", "voxel_m")),
        "pseudo_label": some_keys({"source_map": st.text(max_size=8),
                                   "n_frames_registered": st.integers(0, 1000),
                                   "dataset": st.fixed_dictionaries(
                                       {}, optional={"root": ROOTS,
                                                     "split": st.none() | st.text(max_size=4)}),
                                   "history": st.lists(st.text(max_size=5), max_size=3)},
                                  strict=("n_frames_registered", "dataset")),
        "tag": finite_json,
    }
    for key, strategy in optional.items():
        if draw(st.booleans()):
            doc[key] = draw(strategy)
    try:  # every value by its name's kind (`slamreloc.io.values`): a generated `x_m` of -1
        check_values(doc, PATH)  # or `n_a` of 2.5 is no metadata a writer makes
    except InputError:
        assume(False)
    return json.loads(json.dumps(draw(shuffled(doc))))


@fuzz_settings(300)
@given(doc=metadata())
def test_from_json_then_to_json_gives_back_every_accepted_metadata(doc):
    meta = MapMeta.from_json(doc, PATH)
    out = meta.to_json()
    if "format_version" not in doc:  # format 1 recorded `version`; the reader adds the other
        assert out.pop("format_version") == doc["version"]
    assert json.dumps(out, indent=1) == json.dumps(doc, indent=1)  # key order included
    again = MapMeta.from_json(meta.to_json(), PATH)
    assert again == meta and again.to_json() == meta.to_json()


@fuzz_settings(300)
@given(doc=metadata())
def test_typed_views_read_what_the_metadata_records(doc):
    try:  # the schema keeps every rule of a camera (`Camera`), naming the file and the key
        expected = Camera.from_dict(doc["camera"])
    except InputError as err:
        with pytest.raises(InputError) as refused:
            MapMeta.from_json(doc, PATH)
        assert str(refused.value).startswith(f"{PATH}: 'camera'"), refused.value
        assert str(err).split(": ")[-1][:40] in str(refused.value)
        return
    meta = MapMeta.from_json(doc, PATH)
    assert meta.feature_name == doc["features"]["name"]
    assert meta.feature_options == {k: v for k, v in doc["features"].items() if k != "name"}
    assert meta.n_labelled == doc["labels"]["n_labelled"]
    assert meta.camera.to_camera() == expected
    assert meta.regressor.to_config().hidden == tuple(doc["regressor"]["config"]["hidden"])
    assert meta.format_version == doc.get("format_version", doc.get("version"))
    dataset = doc.get("dataset")
    root = dataset.get("root") if isinstance(dataset, dict) else None
    assert meta.dataset_root == (Path(root) if isinstance(root, str)
                                 and Path(root).is_absolute() else None)
    metric = dataset.get("metric", True) if isinstance(dataset, dict) else True
    if metric is None or isinstance(metric, bool):
        assert meta.metric is bool(metric)
    else:  # kept verbatim, refused where it is read as a yes or no
        with pytest.raises(InputError, match="'dataset.metric' must be true or false"):
            meta.metric  # noqa: B018
    assert meta.frame_names == (tuple(doc["frame_names"]) if "frame_names" in doc else None)
    meta.train_config  # noqa: B018 - malformed training settings take the defaults


@pytest.mark.parametrize("change, message", [
    (lambda d: 3, "expected a JSON object, got int"),
    (lambda d: {**d, "format": "x"}, "not a slamreloc map (format='x')"),
    (lambda d: {**d, "format_version": True}, "format_version must be an integer, got True"),
    (lambda d: {**d, "format_version": 3, "slamreloc_version": "9.0"},
     f"map format version 3 (written by slamreloc 9.0) is newer than this slamreloc "
     f"{__version__} reads (format versions 1 to {FORMAT_VERSION}); upgrade slamreloc"),
    (lambda d: {**d, "format_version": 0}, "unknown map format version 0"),
    (lambda d: {k: v for k, v in d.items() if k != "features"}, "missing key 'features'"),
    (lambda d: {**d, "features": {"name": "orb"}},
     "'features.name' must be sift or superpoint, got 'orb'"),
    (lambda d: {**d, "features": {"name": "sift", "root": 1}},
     "'features.root' has the wrong type (1)"),
    (lambda d: {**d, "features": {"name": "sift", "max_keypoints": -1}},
     "'features.max_keypoints' out of range"),
    (lambda d: {**d, "regressor": {**d["regressor"], "arch": 1}},
     "'regressor.arch' must be a string, got 1"),
    (lambda d: {**d, "regressor": {**d["regressor"], "parameters": 1.5}},
     "'regressor.parameters' must be an integer, got 1.5"),
    (lambda d: {**d, "regressor": {**d["regressor"], "config": {"in_dim": 8}}},
     "missing key 'regressor.config.hidden'"),
    (lambda d: {**d, "regressor": {**d["regressor"], "config": {"in_dim": 8, "hidden": [4],
                                                                 "depth": 3}}},
     "unknown key 'regressor.config.depth'"),
    (lambda d: {**d, "labels": {"n_labelled": -1}},
     "'labels.n_labelled' is a count, a whole number >= 0; got -1"),
    # round 10: counts, sizes and names that must mean what they say
    (lambda d: {**d, "labels": {"n_labelled": 3, "n_keyframes": -3}},
     "'labels.n_keyframes' is a count, a whole number >= 0; got -3"),
    (lambda d: {**d, "labels": {"n_labelled": 3, "labelled_fraction": 2}},
     "'labels.labelled_fraction' must be a fraction in [0, 1], got 2"),
    (lambda d: {**d, "surface": {"n_points": -1}},
     "'surface.n_points' is a count, a whole number >= 0; got -1"),
    (lambda d: {**d, "surface": {"n_points": 5, "voxel_m": 0}},
     "'surface.voxel_m' must be a voxel size in (0, 10] metres, got 0"),
    (lambda d: {**d, "pseudo_label": {"n_frames_registered": "3"}},
     "'pseudo_label.n_frames_registered' is a count, a whole number >= 0; got '3'"),
    (lambda d: {**d, "dataset": {**d["dataset"], "poses": "colmap"}},
     "'dataset.poses' must be \"dataset\", \"slam\" or the absolute path of the pose file"),
    (lambda d: {**d, "surface": {"n_points": 5, "voxel_m": 1e9}},
     "'surface.voxel_m' must be a voxel size in (0, 10] metres, got 1000000000.0"),
    (lambda d: {**d, "dataset": {**d["dataset"], "kind": "bogus"}},
     "'dataset.kind' must be one of 7scenes, synthetic, tum, colmap, rosbag, session, got 'bogus'"),
    (lambda d: {**d, "files": {**d["files"], "unknown.npz": SHA}},
     "'files' lists 'unknown.npz', which is not a file a map of format 2 holds"),
    (lambda d: {**d, "files": {**d["files"], "slamreloc_map.json": SHA}},
     "'files' lists 'slamreloc_map.json', which is not a file a map of format 2 holds"),
    (lambda d: {**d, "regressor": {"arch": "paper", "config": {
        "in_dim": 8, "hidden": [512, 512, 512, 128]}, "parameters": _size(
            {"in_dim": 8, "hidden": [512, 512, 512, 128]})}},
     "'regressor.arch' is 'paper', but 'regressor.config' is the 'tiny' architecture"),
    (lambda d: {**d, "regressor": {**d["regressor"], "parameters": 7}},
     "'regressor.parameters' is 7, but the recorded config has 195 parameters"),
    (lambda d: {**d, "frame_names": ["seq-01/./frame-000000"]},
     "'frame_names'[0] 'seq-01/./frame-000000' is not a plain relative path"),
    (lambda d: {**d, "frame_names": ["seq-01//frame-000000"]},
     "'frame_names'[0] 'seq-01//frame-000000' is not a plain relative path"),
    (lambda d: {**d, "labels": []}, "'labels' must be an object, got []"),
    (lambda d: {**d, "camera": {**d["camera"], "width": 0}},
     "'camera.width' must be in 1..65536, got 0"),
    (lambda d: {**d, "camera": {**d["camera"], "fx": "60"}},
     "'camera.fx' must be a number, got '60'"),
    (lambda d: {**d, "camera": {**d["camera"], "fx": 0.5}}, "'camera': focal lengths must be"),
    (lambda d: {**d, "camera": {**d["camera"], "k1": 0.1}}, "unknown camera key 'k1'"),
    (lambda d: {**d, "camera": {**d["camera"], "model": "OPENCV"}},
     "missing key 'camera.distortion'"),
    (lambda d: {**d, "camera": {**d["camera"], "model": "OPENCV", "distortion": [0.1]}},
     "'camera': OPENCV has 4 distortion parameters, got 1"),
    (lambda d: {**d, "frame_names": ["a", 1]}, "'frame_names' must be a list of strings"),
    # round 8: typed fields that other commands act on
    (lambda d: {**d, "train": {"epochs": -1}}, "'train.epochs' must be a whole number"),
    (lambda d: {**d, "train": {"lr": -1}}, "'train.lr' must be a learning rate in (0, 10], "
                                           "got -1"),
    (lambda d: {**d, "train": {"batch_size": 0}}, "'train.batch_size' must be a whole number "
                                                  "of rows in 1..1048576, got 0"),
    (lambda d: {**d, "train": {"betas": [0.9]}}, "'train.betas' must be two numbers in [0, 1)"),
    (lambda d: {**d, "timings_s": "x"}, "'timings_s' must be an object of seconds"),
    (lambda d: {k: v for k, v in d.items() if k != "files"}, "missing key 'files'"),
    (lambda d: {**d, "files": {WEIGHTS: "00", DATABASE: SHA}},
     f"'files.{WEIGHTS}' '00' is not a SHA-256 digest (64 lower-case hex digits)"),
    # round 38, W4: digits of the right count in the wrong case are said to be so
    (lambda d: {**d, "files": {WEIGHTS: SHA.upper(), DATABASE: SHA}},
     f"'files.{WEIGHTS}' {repr(SHA.upper())[:57]}... is a SHA-256 in upper-case hex digits; a "
     "map records lower-case ones"),
    (lambda d: {**d, "frame_pictures": [SHA.upper()] * len(d["frame_names"])},
     f"'frame_pictures'[0] {repr(SHA.upper())[:57]}... is a SHA-256 in upper-case hex "
     "digits; a map records lower-case ones (or \"\", not known)"),
])
def test_from_json_refuses_a_bad_field_in_one_line_naming_the_file(change, message):
    with pytest.raises(InputError) as err:
        MapMeta.from_json(change(_valid_doc()), PATH)
    assert str(err.value) == f"{PATH}: {message}" or (
        str(err.value).startswith(f"{PATH}: {message}") and "\n" not in str(err.value))


@fuzz_settings(300)
@given(data=st.data())
def test_damaged_metadata_is_refused_in_one_line_or_read_back_whole(data):
    text = data.draw(damaged_json(_valid_doc()) | json_values.map(
        lambda v: json.dumps(v).encode()))
    try:
        doc = parse_json(text, PATH)  # as MapMeta.read parses the file
        meta = MapMeta.from_json(doc, PATH)
    except InputError as err:
        assert str(err).startswith(f"{PATH}: ") and "\n" not in str(err)
        return
    out = meta.to_json()
    if "format_version" not in doc:
        out.pop("format_version")
    assert out == doc


def test_stamped_lays_out_the_metadata_as_save_map_writes_it():
    meta = replace(_built(), extra={"tag": "t", "version": 1, "slamreloc_version": 5})
    doc = meta.stamped({WEIGHTS: SHA, DATABASE: SHA}, ["f0", "f1"]).to_json()
    assert list(doc) == ["format", "format_version", "slamreloc_version", "features",
                         "regressor", "train", "labels", "camera", "dataset", "timings_s",
                         "surface", "tag", "files", "frame_names"]
    assert doc["format_version"] == FORMAT_VERSION and doc["slamreloc_version"] == __version__
    assert doc["frame_names"] == ["f0", "f1"] and doc["files"][WEIGHTS] == SHA
    # a rewrite keeps the order it read (the surface before the update it gained)
    read = MapMeta.from_json(doc, PATH)
    updated = replace(read, pseudo_label=UpdateMeta(n_frames=3, history=("a",)))
    layout = list(updated.stamped(doc["files"], ["f0"]).to_json())
    assert layout[-4:] == ["tag", "pseudo_label", "files", "frame_names"]
    assert updated.stamped(doc["files"], []).to_json()["pseudo_label"] == {"n_frames": 3,
                                                                           "history": ["a"]}


def test_values_the_schema_does_not_type_are_kept_verbatim():
    doc = {**_valid_doc(), "dataset": {"note": 7, "metric": None, "poses": "/p.txt"},
           "slamreloc_version": ["x"]}
    meta = MapMeta.from_json(doc, PATH)
    assert meta.dataset == DatasetMeta(poses="/p.txt", extra={"note": 7, "metric": None})
    # read as before the schema: a recorded null is not metric, no root recorded
    assert meta.dataset_root is None and meta.metric is False and meta.poses_source == "/p.txt"
    assert meta.pseudo_label is None and meta.n_frames_updated == 0
    assert meta.slamreloc_version is None and meta.extra["slamreloc_version"] == ["x"]
    assert meta.to_json() == doc and list(meta.to_json()["dataset"]) == ["note", "metric", "poses"]


@pytest.mark.parametrize("edit, message", [
    ({"dataset": {"root": 7}}, "'dataset.root' must be a string (the dataset's path), got 7"),
    ({"dataset": {"root": "scene"}}, "'dataset.root' must be an absolute path"),
    ({"dataset": 5}, "'dataset' must be an object, got 5"),
    ({"dataset": {"split": 5}}, "'dataset.split' must be a string"),
    ({"pseudo_label": "odd"}, "'pseudo_label' must be an object (the update's record)"),
    ({"pseudo_label": {"dataset": {"root": "rel"}}}, "'pseudo_label.dataset.root' must be an "
                                                     "absolute path"),
])
def test_a_recorded_dataset_follows_one_rule_for_every_command(edit, message):
    """Attack round 13, J4 and J5: a root or split of another type, or a pseudo_label record
    that is no object, was taken by `localize` and refused by the commands that use the
    dataset; the schema refuses it for all."""
    with pytest.raises(InputError) as err:
        MapMeta.from_json({**_valid_doc(), **edit}, PATH)
    assert message in str(err.value), err.value


def test_a_camera_is_recorded_as_the_camera_writes_itself():
    for cam in (Camera(64, 48, 60.0, 60.0, 31.5, 23.5),
                Camera(64, 48, 60.0, 61.0, 32.0, 24.0, "OPENCV", (0.1, -0.01, 0.0, 0.0))):
        record = CameraMeta.from_camera(cam)
        assert record.to_json() == cam.to_dict() and record.to_camera() == cam


def _built() -> MapMeta:
    return MapMeta(features=FeatureMeta("sift", {"max_keypoints": 256, "upsample": True}),
                   regressor=RegressorMeta("tiny", {"in_dim": 8, "hidden": [16]},
                                           _size({"in_dim": 8, "hidden": [16]})),
                   train={"epochs": 2, "precision": "fp32"},
                   labels={"n_labelled": 20, "median_reproj_error_px": None},
                   camera=CameraMeta(64, 48, 60.0, 60.0, 32.0, 24.0),
                   dataset=DatasetMeta(root="/d", kind="synthetic", split="train", metric=True,
                                       poses="dataset"),
                   timings_s={"train_s": 1.5}, surface=SurfaceMeta(n_points=10, voxel_m=0.01))


def _valid_doc() -> dict:
    return _built().stamped({WEIGHTS: SHA, DATABASE: SHA}, ["f0"]).to_json()
