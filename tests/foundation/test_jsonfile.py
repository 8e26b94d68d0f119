"""skyfix.jsonfile.read_json: content, and errors that name the file."""

import pytest

from skyfix.errors import DataError, InputError
from skyfix.jsonfile import read_json


def test_reads_content(tmp_path):
    (tmp_path / "a.json").write_text('{"fx": 500.0}')
    assert read_json(tmp_path / "a.json", "camera file") == {"fx": 500.0}


def test_missing_file_raises_the_requested_error(tmp_path):
    with pytest.raises(DataError, match="camera file .*does not exist"):
        read_json(tmp_path / "none.json", "camera file")
    with pytest.raises(InputError, match="plan file .*does not exist"):
        read_json(tmp_path / "none.json", "plan file", missing=InputError)


def test_malformed_file_raises_data_error(tmp_path):
    (tmp_path / "bad.json").write_text("{fx: ")
    with pytest.raises(DataError, match="bad.json is not readable JSON"):
        read_json(tmp_path / "bad.json", "camera file")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(DataError, match="not readable JSON"):
        read_json(tmp_path / "bin.json", "camera file")
