"""Numbers in the JSON files the viewer reads (issue 43): an integer literal of hundreds of
digits, or a float literal beyond a float's range (`1e400`, read as infinity), is refused with
one line naming the file and the field, never an OverflowError later."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from slamreloc.errors import InputError
from tests.fuzzing import fuzz_settings, run_cli
from tests.test_fuzz_inputs import _tiny_map


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory):
    return _tiny_map(tmp_path_factory.mktemp("json_numbers") / "map")


REPORTS = [  # a report of each kind the viewer reads, with NUMBER where a number goes
    '{"n_queries": 1, "per_query": [{"name": "a", "translation_error_m": NUMBER}]}',
    '{"n_pseudo_labels": NUMBER, "poses": {}}',
    '{"ate_rmse_m": 0.1, "n_kidnaps": NUMBER, "events": []}',
    '{"ate_rmse_m": 0.1, "events": [{"kind": "kidnap", "frame": NUMBER}]}',
    '{"other": {"deep": [1, 2, NUMBER]}}',
]


def test_view_refuses_a_report_holding_10_to_the_400(tiny_map, tmp_path):
    report = tmp_path / "r.json"
    report.write_text('{"ate_rmse_m": 0.1, "n_kidnaps": 1' + "0" * 400 + ', "events": []}')
    code, err = run_cli(["view", str(tiny_map), "--report", str(report), "--port", "1"])
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert str(report) in lines[0] and "401 digits" in lines[0]


@fuzz_settings(40)
@given(template=st.sampled_from(REPORTS),
       number=st.one_of(st.integers(2 ** 63, 10 ** 1000).map(str),
                        st.integers(-10 ** 1000, -2 ** 63).map(str),
                        st.integers(309, 5000).map(lambda e: f"1e{e}"),
                        st.integers(309, 5000).map(lambda e: f"-2.5E+{e}")))
def test_out_of_range_numbers_in_reports_are_refused(tmp_path_factory, template, number):
    from slamreloc.viewer.reports import read_json

    path = tmp_path_factory.mktemp("r") / "report.json"
    path.write_text(template.replace("NUMBER", number))
    with pytest.raises(InputError) as err:
        read_json(path)
    assert str(path) in str(err.value)


def test_numbers_in_range_are_read(tmp_path):
    from slamreloc.viewer.reports import read_json

    path = tmp_path / "report.json"
    doc = {"a": 2 ** 63 - 1, "b": -(2 ** 63 - 1), "c": 1.7e308, "d": [0, -0.0, 5e-324]}
    path.write_text(json.dumps(doc))
    assert read_json(path) == doc


@pytest.mark.parametrize("text, problem", [
    ('{"a": 1' + "0" * 400 + "}", "401 digits"),
    ('{"a": 9223372036854775808}', "beyond 64 bits"),
    ('{"a": 1e400}', "1e400 out of range"),
    ('{"a": [-1e309]}', "out of range"),
])
def test_every_json_reader_refuses_numbers_that_overflow(tmp_path, text, problem):
    """Every reader of a user's JSON (map metadata, reports, scene.json) parses through
    `parse_json`: a number that cannot be held is one error naming the file, not an
    OverflowError or a silent infinity later."""
    from slamreloc.errors import InputError
    from slamreloc.io.jsonio import read_json

    path = tmp_path / "x.json"
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as err:
        read_json(path)
    assert str(path) in str(err.value)
    path.write_text('{"a": -9223372036854775808, "b": 1.5e308}')
    assert read_json(path) == {"a": -(2 ** 63), "b": 1.5e308}
