"""``benchmarks.map_option_ab``: the side-by-side table of one hex-stage option on and off."""
from __future__ import annotations

import pytest

from benchmarks.map_option_ab import main, table


def test_table_counts_and_marks_each_run():
    rows = [{"model": "s01c_a", "value": True, "good": True, "valid": True, "first_failed": None, "inverted": 0,
             "seconds": 2.0, "option_s": 0.5},
            {"model": "s01c_a", "value": False, "good": False, "valid": True, "first_failed": "extraction",
             "inverted": 0, "seconds": 1.0, "option_s": None},
            {"model": "s02c_b", "value": True, "error": "FileNotFoundError: no field"}]
    md = table(rows, "fixed_holonomy").splitlines()
    assert md[2] == "| s01c_a | good, 0 inverted, 2 s, step 0.5 s | valid map, 0 inverted, 1 s |"
    assert md[3] == "| s02c_b | error: FileNotFoundError: no field | – |"
    assert md[-1] == "Good hex meshes: 1/2 with fixed_holonomy=True, 0/2 with False."


def test_unknown_option_is_refused(capsys):
    with pytest.raises(SystemExit):
        main(["no_such_option"])
    assert "unknown option 'no_such_option'" in capsys.readouterr().err
