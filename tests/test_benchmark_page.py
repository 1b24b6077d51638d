"""docs/benchmarks.md is generated from docs/benchmarks/records/ (clflow.benchmark.render_page)."""

import json
import re
from pathlib import Path

import pytest

from clflow.benchmark import PAGE, PAGE_WIDTH, RECORD_FIELDS, RECORDS, SECTIONS, read_records, render_page

ROOT = Path(__file__).resolve().parents[1]
RECORD_FILES = sorted((ROOT / RECORDS).glob("*.json"))
MAY_BE_NULL = {"commit", "device", "load", "target"}


def test_the_committed_page_is_the_one_its_records_render():
    # run `python -m clflow.benchmark` from the repository's root after changing a record
    assert (ROOT / PAGE).read_text() == render_page(read_records(ROOT / RECORDS))


@pytest.mark.parametrize("path", RECORD_FILES, ids=lambda path: path.stem)
def test_each_record_has_the_fields_of_a_current_figure(path):
    record = json.loads(path.read_text())
    assert set(RECORD_FIELDS) <= set(record), f"missing: {set(RECORD_FIELDS) - set(record)}"
    assert set(record) <= set(RECORD_FIELDS) | {"notes", "docs"}, f"unknown: {set(record) - set(RECORD_FIELDS)}"
    assert record["benchmark"] == path.stem and record["section"] in SECTIONS
    assert re.match(r"\d{4}-\d{2}-\d{2}", record["date"]), record["date"]
    for name in RECORD_FIELDS:
        value = record[name]
        if name == "figures":  # name -> the figure as the docs wrote it, with its unit
            assert isinstance(value, dict) and value and all(isinstance(v, str) and v for v in value.values())
        elif name in MAY_BE_NULL:  # null: the docs did not say
            assert value is None or (isinstance(value, str) and value), name
        else:
            assert isinstance(value, str) and value, name


def test_every_section_has_records_and_the_page_stays_narrow():
    records = read_records(ROOT / RECORDS)
    assert len(records) == len(RECORD_FILES) and {record["section"] for record in records} == set(SECTIONS)
    page = render_page(records)
    assert all(len(line) <= PAGE_WIDTH for line in page.splitlines())
    # a wrapped line never starts a list item, a heading, a quote or a table of its own
    continuations = [line.strip() for line in page.splitlines() if line.startswith("    ")]
    assert not [line for line in continuations if re.match(r"([-*+>#|]|\d+[.)]) ", line)]


def test_the_page_links_to_its_history():
    page = (ROOT / PAGE).read_text()
    for link in re.findall(r"\]\((history/[^)]+)\)", page):
        assert (ROOT / "docs" / link).is_file(), link
