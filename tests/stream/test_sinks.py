"""The TOA track's CSV file (``toa.csv``): what a spreadsheet or ``csv.reader`` reads back."""
import csv

import numpy as np
import pytest

from stream.sinks import ToaCsvSink


@pytest.mark.parametrize("tracks", [True, False])
def test_toa_csv_reads_back_what_was_written_to_its_precision(tmp_path, tracks):
    """Rows are written with one format string (not a csv writer's row); they read back through ``csv`` to the
    values written (time to 1 us, TOA to 1 ns, the speech probability to 0.001), NaN and infinity included, with
    the header's columns and the dialect's line ends."""
    path = tmp_path / "toa.csv"
    sink = ToaCsvSink(path, ["phone", "laptop", "pi"], tracks=tracks)
    rng = np.random.default_rng(3)
    rows = [(float(k) * 0.016 + 1e-7, rng.normal(0.0, 2e-3, 3), bool(k % 2), k % 4 - 1, rng.uniform())
            for k in range(300)]
    rows.append((5.0, np.array([np.nan, -0.0, np.inf]), False, -1, float("nan")))
    for time_s, toa_s, gated, track_id, p in rows:
        sink.write_row(time_s, toa_s, gated, track_id, p)
    sink.close()
    assert sink.n_rows == len(rows)
    raw = path.read_bytes()
    assert raw.count(b"\r\n") == len(rows) + 1 and raw.count(b"\n") == len(rows) + 1
    with open(path, newline="") as fh:
        read = list(csv.reader(fh))
    extra = ["steered_track", "speech_probability"] if tracks else []
    assert read[0] == ["time_s", "toa_s_0_phone", "toa_s_1_laptop", "toa_s_2_pi", "gated", *extra]
    assert len(read) == len(rows) + 1
    for (time_s, toa_s, gated, track_id, p), line in zip(rows, read[1:]):
        assert len(line) == len(read[0])
        assert float(line[0]) == pytest.approx(time_s, abs=5e-7)
        np.testing.assert_allclose([float(v) for v in line[1:4]], toa_s, rtol=0, atol=5e-10)
        assert int(line[4]) == int(gated)
        if tracks:
            assert int(line[5]) == track_id
            assert float(line[6]) == pytest.approx(p, abs=5e-4, nan_ok=True)
    assert read[-1][1:4] == ["nan", "-0.000000000", "inf"]


def test_a_row_that_does_not_match_the_header_is_one_sentence(tmp_path):
    """A row with another number of TOAs than the header has device columns would be read back into the wrong
    columns: it is refused in one sentence, and the rows before it stay in the file."""
    path = tmp_path / "toa.csv"
    sink = ToaCsvSink(path, ["phone", "laptop", "pi"], tracks=True)
    sink.write_row(0.0, np.zeros(3), False)
    with pytest.raises(ValueError, match=r"^toa.csv has 3 device columns; a row with 2 TOAs would not line up"):
        sink.write_row(0.016, np.zeros(2), False)
    sink.write_row(0.032, np.ones(3), False)
    sink.close()
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    assert len(rows) == 3 and rows[1][1:4] == ["0.000000000"] * 3 and rows[2][1:4] == ["1.000000000"] * 3
