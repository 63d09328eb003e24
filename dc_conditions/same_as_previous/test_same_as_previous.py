"""SameAsPrevious: sequences of samples, files compared by content."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from dc_conditions.same_as_previous import SameAsPrevious
from tests.condition_helpers import Inactive, check, configured


def write(path: Path, content: str) -> str:
    path.write_text(content)
    return str(path)


def test_same_as_previous_first_sample_is_never_the_same() -> None:
    condition = configured(SameAsPrevious, {})
    assert [condition.evaluate({"a": 1}) for _ in range(3)] == [False, True, True]


@pytest.mark.parametrize(
    ("params", "samples", "expected"),
    [
        pytest.param({}, [{"a": 1}, {"a": 2}, {"a": 2}, {"a": 1}], [False, False, True, False], id="value-changes"),
        pytest.param({}, [{"a": 1}, {"a": 1.0}], [False, True], id="int-and-float-are-the-same-number"),
        pytest.param({}, [{"a": 1}, {"a": True}], [False, False], id="bool-is-not-1"),
        pytest.param({}, [{"a": [1, 2]}, {"a": [2, 1]}], [False, False], id="array-order-matters"),
        pytest.param({}, [{"a": 1}, {"a": 1, "b": 2}], [False, False], id="new-key"),
        pytest.param({}, [{"a": 1, "tags": ["x"]}, {"a": 1, "tags": ["y"]}], [False, True], id="tags-ignored"),
        pytest.param(
            {"exclude": ["stamp"]},
            [{"a": 1, "stamp": 1}, {"a": 1, "stamp": 2}],
            [False, True],
            id="exclude-top-level",
        ),
        pytest.param(
            {"exclude": ["meta"]},
            [{"a": 1, "meta": {"t": 1}}, {"a": 1, "meta": {"t": 2, "u": 3}}],
            [False, True],
            id="exclude-object-and-its-children",
        ),
        pytest.param(
            {"exclude": ["cams/[0-9]+/stamp"]},
            [
                {"cams": [{"id": 1, "stamp": 1}]},
                {"cams": [{"id": 1, "stamp": 9}]},
                {"cams": [{"id": 2, "stamp": 9}]},
            ],
            [False, True, False],
            id="exclude-regex-through-array",
        ),
        pytest.param(
            {"exclude": ["stamp"]},
            [{"a": {"stamp": 1}}, {"a": {"stamp": 2}}],
            [False, False],
            id="exclude-is-a-full-match-of-the-path",
        ),
        pytest.param(
            {"exclude": [".*stamp"]},
            [{"a": {"stamp": 1}}, {"a": {"stamp": 2}}],
            [False, True],
            id="exclude-pattern-for-any-depth",
        ),
    ],
)
def test_same_as_previous_sequences(
    params: dict[str, Any], samples: list[dict[str, Any]], expected: list[bool]
) -> None:
    condition = configured(SameAsPrevious, params)
    assert [condition.evaluate(s) for s in samples] == expected


def test_same_as_previous_compares_file_contents_not_names(tmp_path: Path) -> None:
    condition = configured(SameAsPrevious, {"keys": ["local_paths/inspected"], "exclude": ["date"]})

    def sample(path: str) -> dict[str, Any]:
        return {"local_paths": {"inspected": path}, "date": path}

    first = write(tmp_path / "a.jpg", "line 1\nsame last line\n")
    assert condition.evaluate(sample(first)) is False
    renamed = write(tmp_path / "b.jpg", "line 1\nsame last line\n")
    assert condition.evaluate(sample(renamed)) is True, "same content under a new name is the same"
    write(tmp_path / "b.jpg", "line 1 changed\nsame last line\n")
    assert condition.evaluate(sample(renamed)) is False, "content changed in place (not on the last line)"
    assert condition.evaluate(sample(renamed)) is True


def test_same_as_previous_file_key_through_an_array_with_negative_index(tmp_path: Path) -> None:
    condition = configured(SameAsPrevious, {"keys": ["/frames/-1/path/"]})
    same = "image bytes"
    assert condition.evaluate({"frames": [{"path": write(tmp_path / "1.jpg", same)}]}) is False
    assert condition.evaluate({"frames": [{"path": write(tmp_path / "2.jpg", same)}]}) is True
    assert condition.evaluate({"frames": [{"path": write(tmp_path / "3.jpg", "other bytes")}]}) is False


def test_same_as_previous_large_file_is_hashed_whole(tmp_path: Path) -> None:
    condition = configured(SameAsPrevious, {"keys": ["file"]})
    big = os.urandom(3 * (1 << 20) + 7)
    path = tmp_path / "big.bin"
    path.write_bytes(big)
    assert condition.evaluate({"file": str(path)}) is False
    path.write_bytes(big[:100] + bytes([big[100] ^ 1]) + big[101:])
    assert condition.evaluate({"file": str(path)}) is False
    assert condition.evaluate({"file": str(path)}) is True


@pytest.mark.parametrize(
    ("sample", "reason"),
    [
        pytest.param({"other": 1}, "'file'", id="key-missing"),
        pytest.param({"file": 3}, "not a string", id="path-not-a-string"),
        pytest.param({"file": "/nonexistent/dc/file"}, "cannot read file", id="file-missing"),
        pytest.param(None, "no sample", id="no-sample"),
    ],
)
def test_same_as_previous_bad_data_is_inactive_and_keeps_the_previous_sample(
    tmp_path: Path, sample: Any, reason: str
) -> None:
    condition = configured(SameAsPrevious, {"keys": ["file"]})
    good = {"file": write(tmp_path / "f.txt", "x")}
    assert condition.evaluate(good) is False
    check(condition, sample, Inactive(reason))
    assert condition.evaluate(good) is True


def test_same_as_previous_starts_over_after_cleanup() -> None:
    condition = configured(SameAsPrevious, {})
    assert condition.evaluate({"a": 1}) is False
    condition.on_cleanup()
    condition.on_configure()
    assert condition.evaluate({"a": 1}) is False
