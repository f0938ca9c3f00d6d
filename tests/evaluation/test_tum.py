"""TUM trajectory files: round trip, field order, and errors that name the line."""
import pytest
import torch

from flowins.evaluation import read_tum, write_tum
from flowins.geometry import quaternion

F64 = torch.float64


def random_poses(n, seed=0):
    gen = torch.Generator().manual_seed(seed)
    t = 1403636579.763555527 + torch.cumsum(0.05 * torch.rand(n, generator=gen, dtype=F64) + 0.001, 0)
    pos = 100 * torch.randn(n, 3, generator=gen, dtype=F64)
    q = quaternion.normalize(torch.randn(n, 4, generator=gen, dtype=F64))
    return t, pos, q


def test_round_trip(tmp_path):
    t, pos, q = random_poses(50)
    path = write_tum(tmp_path / "sub" / "est.txt", t, pos, q)
    t2, pos2, q2 = read_tum(path)
    assert t2.dtype == pos2.dtype == q2.dtype == F64
    assert (t2 - t).abs().max().item() <= 5e-10  # %.9f time stamps
    assert torch.equal(pos2, pos)  # repr round-trips float64 exactly
    assert torch.equal(q2, q)


def test_small_times_round_trip_to_a_nanosecond(tmp_path):
    t = torch.tensor([0.0, 0.123456789012, 1.5], dtype=F64)
    pos = torch.zeros(3, 3, dtype=F64)
    q = quaternion.identity(3, dtype=F64)
    t2, _, _ = read_tum(write_tum(tmp_path / "a.txt", t, pos, q))
    assert (t2 - t).abs().max().item() <= 5e-10


def test_written_line_has_qw_last(tmp_path):
    t = torch.tensor([1.5, 2.0], dtype=F64)
    pos = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], dtype=F64)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.6, 0.0, 0.8]], dtype=F64)  # w, x, y, z
    path = write_tum(tmp_path / "id.txt", t, pos, q)
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#")
    assert lines[1] == "1.500000000 1.0 2.0 3.0 0.0 0.0 0.0 1.0"
    assert lines[2] == "2.000000000 0.0 0.0 0.0 0.6 0.0 0.8 0.0"
    _, _, q2 = read_tum(path)
    assert torch.equal(q2, q)
    no_header = write_tum(tmp_path / "nh.txt", t, pos, q, header=None)
    assert no_header.read_text().splitlines()[0] == lines[1]


def test_reader_skips_comments_and_blank_lines(tmp_path):
    path = tmp_path / "c.txt"
    path.write_text("# a comment\n\n1.0 1 2 3 0 0 0 1\n   \n  # indented comment\n2.0 4 5 6 0 0 1 0\n")
    t, pos, q = read_tum(path)
    assert t.tolist() == [1.0, 2.0]
    assert pos.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert q.tolist() == [[1, 0, 0, 0], [0, 0, 0, 1]]


def test_line_with_seven_numbers_names_line_3(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"bad\.txt, line 3: expected 8 numbers .* got 7 fields"):
        read_tum(path)


def test_other_malformed_files(tmp_path):
    path = tmp_path / "word.txt"
    path.write_text("1.0 0 0 zero 0 0 0 1\n")
    with pytest.raises(ValueError, match="line 1: .*non-numeric"):
        read_tum(path)
    path.write_text("1.0 0 0 nan 0 0 0 1\n")
    with pytest.raises(ValueError, match="line 1: .*NaN"):
        read_tum(path)
    path.write_text("# only a comment\n")
    with pytest.raises(ValueError, match="no poses"):
        read_tum(path)


def test_writer_rejects_bad_input(tmp_path):
    t, pos, q = random_poses(4)
    with pytest.raises(ValueError, match="same number of rows"):
        write_tum(tmp_path / "x.txt", t, pos[:3], q)
    with pytest.raises(ValueError, match=r"quat_wxyz must have shape \(N, 4\)"):
        write_tum(tmp_path / "x.txt", t, pos, q[:, :3])
    pos[2, 1] = float("nan")
    with pytest.raises(ValueError, match="pos_m contains NaN or inf; first bad row is pos_m\\[2\\]"):
        write_tum(tmp_path / "x.txt", t, pos, q)
    assert not (tmp_path / "x.txt").exists()
