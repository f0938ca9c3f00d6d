"""``python -m flowins.jobs.gnss_floor``: the GNSS floor of a recording read from disk."""
import pytest

from flowins.data.folder import read_folder, write_folder
from flowins.data.sequence import Sequence
from flowins.data.synthetic import synthetic_walk_recording
from flowins.evaluation.gnss_floor import gnss_floor
from flowins.jobs.gnss_floor import main


@pytest.fixture(scope="module")
def walk_folder(tmp_path_factory):
    rec = synthetic_walk_recording(duration_s=60.0, seed=1)
    folder = tmp_path_factory.mktemp("walk")
    return write_folder(Sequence(rec.imu, name="walk", gnss=rec.gnss, groundtruth=rec.truth), folder / "walk")


def _rows(text: str) -> list[list[str]]:
    """The table's rows, split into cells (τ first)."""
    return [line.replace(" (est.)", "").split() for line in text.splitlines()[2:]]


def test_the_table_is_the_floor_of_the_fixes_read_back(walk_folder, capsys):
    assert main([str(walk_folder), "--correlation-s", "0", "7.5"]) == 0
    out = capsys.readouterr().out
    rows = _rows(out)
    assert [row[0] for row in rows[1:]] == ["0.0", "7.5"]
    seq = read_folder(walk_folder)
    enu, cov, _ = seq.gnss.enu()
    sigma = cov.diagonal(dim1=-2, dim2=-1).sqrt()
    estimated = gnss_floor(seq.gnss.t_s, enu, sigma, seq.groundtruth.t_s, seq.groundtruth.pos_m)
    assert rows[0][0] == f"{estimated.correlation_s:.1f}"
    for i, (tau, *cells) in enumerate(rows):
        expected = gnss_floor(seq.gnss.t_s, enu, sigma, seq.groundtruth.t_s, seq.groundtruth.pos_m,
                              correlation_s=None if i == 0 else float(tau))
        assert cells[0] == f"{expected.rmse_m:.2f}" and cells[2] == f"{expected.horizontal_rmse_m:.2f}"
        assert cells[4:7] == [str(expected.fixes_used), "of", str(expected.fixes)]
    assert float(rows[1][1]) > 0.0


def test_a_recording_without_gnss_or_a_negative_tau_is_refused_by_name(walk_folder, tmp_path, capsys):
    rec = synthetic_walk_recording(duration_s=10.0, seed=1)
    no_gnss = write_folder(Sequence(rec.imu, name="walk", groundtruth=rec.truth), tmp_path / "no_gnss")
    assert main([str(no_gnss)]) == 2
    err = capsys.readouterr().err
    assert str(no_gnss) in err and "no GNSS fixes" in err
    assert main([str(walk_folder), "--correlation-s", "-1"]) == 2
    assert "--correlation-s must be >= 0" in capsys.readouterr().err
