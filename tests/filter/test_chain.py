"""The node chain: a batch's rows grow, update and predict apart, and each row's track
holds its own nodes, log and innovation likelihood."""
import torch

from flowins.filter.augmentation import PoseAugmentation, copy_matrices
from flowins.filter.chain import BatchChain, ChainBuilder
from flowins.state import STATE_DIM

F64 = torch.float64


def test_a_prediction_on_some_rows_moves_the_others_newest_node():
    """An event's linear prediction on row 0 only: row 1's node stays the same node (its
    prediction, transition and filtered Gaussian), and row 1's next update lands on it."""
    gen = torch.Generator().manual_seed(0)
    chain = BatchChain(2)
    mean = torch.randn(2, 1, STATE_DIM, generator=gen, dtype=F64)
    cov = torch.eye(STATE_DIM, dtype=F64).expand(2, 1, STATE_DIM, STATE_DIM) * 2.0
    chain.add_nodes([[0.0], [0.0]], torch.eye(STATE_DIM, dtype=F64).expand(2, 1, STATE_DIM, STATE_DIM), mean, cov)
    A = 0.5 * torch.eye(STATE_DIM, dtype=F64)
    chain.linear_predict_rows([0], A.unsqueeze(0), torch.eye(STATE_DIM, dtype=F64).unsqueeze(0))
    new_mean = torch.zeros(1, STATE_DIM, dtype=F64)
    chain.update_rows([1], new_mean, torch.eye(STATE_DIM, dtype=F64).unsqueeze(0))
    first, second = chain.finish()
    assert first.t_s.tolist() == [0.0, 0.0] and second.t_s.tolist() == [0.0]
    torch.testing.assert_close(first.node_mean[1], 0.5 * mean[0, 0], rtol=0, atol=0)
    torch.testing.assert_close(first.node_cov[1], 0.5 * torch.eye(STATE_DIM, dtype=F64) + torch.eye(STATE_DIM, dtype=F64))
    assert torch.equal(first.transition[1], A)
    assert torch.equal(second.node_mean[0], new_mean[0]) and torch.equal(second.pred_mean[0], mean[1, 0])


def test_the_pose_copy_by_index_is_the_matrix_step_exactly():
    """The limit augmentation on a chain (entries copied by index) equals T m, T P Tᵀ + Q."""
    gen = torch.Generator().manual_seed(3)
    mean = torch.randn(STATE_DIM, generator=gen, dtype=F64)
    A = torch.randn(STATE_DIM, STATE_DIM, generator=gen, dtype=F64)
    cov = A @ A.T
    chain = ChainBuilder()
    chain.add_node(0.0, torch.eye(STATE_DIM, dtype=F64), mean, cov)
    PoseAugmentation(0.0, nugget_var=1e-6, mode="limit").apply(chain)
    T, Q = copy_matrices(1e-6, dtype=F64)
    assert torch.equal(chain.mean, T @ mean)
    assert torch.equal(chain.cov, T @ cov @ T.T + Q)
    assert torch.equal(chain.finish().transition[1], T)


def test_each_row_sums_its_own_likelihood_and_a_chain_without_one_keeps_none():
    gen = torch.Generator().manual_seed(2)
    eye = torch.eye(STATE_DIM, dtype=F64).expand(3, 1, STATE_DIM, STATE_DIM)
    tracks = {}
    for likelihood in (True, False):
        chain = BatchChain(3, likelihood=likelihood)
        chain.add_nodes([[0.0]] * 3, eye, torch.randn(3, 1, STATE_DIM, generator=gen, dtype=F64), eye)
        chain.add_likelihood([0, 2], torch.tensor([1.5, -0.25], dtype=F64), torch.tensor([3.0, 1.0], dtype=F64))
        chain.add_likelihood([2], torch.tensor([2.0], dtype=F64), torch.tensor([0.5], dtype=F64))
        tracks[likelihood] = chain.finish()
    assert [float(t.nll) for t in tracks[True]] == [1.5, 0.0, 1.75]
    assert [t.nll_count for t in tracks[True]] == [3.0, 0.0, 1.5]
    assert all(t.nll is None and t.nll_count == 0.0 for t in tracks[False])


def test_a_log_entry_goes_to_its_row_with_the_node_time_and_an_empty_one_is_left_out():
    chain = BatchChain(2)
    eye = torch.eye(STATE_DIM, dtype=F64).expand(2, 1, STATE_DIM, STATE_DIM)
    chain.add_nodes([[0.5], [0.75]], eye, torch.zeros(2, 1, STATE_DIM, dtype=F64), eye)
    chain.log_rows([1, 0], [{"kind": "toy"}, {}])
    assert chain.logs == [[], [{"t_s": 0.75, "kind": "toy"}]]


def test_the_final_frame_of_the_first_entries_is_the_whole_states_block():
    """``in_final_frame(marginal=26)`` of a state with 3 cloned poses and a heading alignment:
    the first 26 entries of the whole state's final frame (the map keeps each pose's block
    apart), and a map that mixes later entries in is refused."""
    import pytest

    from flowins.measurements.gnss_heading import HeadingFit, heading_transform
    from flowins.state import normalize_quaternions, state_dim

    gen = torch.Generator().manual_seed(4)
    D = state_dim(3)
    chain = ChainBuilder()
    mean = normalize_quaternions(torch.randn(D, generator=gen, dtype=F64))
    L = torch.randn(D, D, generator=gen, dtype=F64)
    chain.add_node(0.0, torch.eye(D, dtype=F64), mean, L @ L.T / D + torch.eye(D, dtype=F64))
    chain.add_node(1.0, torch.eye(D, dtype=F64), mean, 2.0 * (L @ L.T / D + torch.eye(D, dtype=F64)))
    fit = HeadingFit(torch.tensor(0.7, dtype=F64), torch.tensor(0.01, dtype=F64), torch.tensor([1.0, 2.0], dtype=F64),
                     torch.tensor([-3.0, 5.0], dtype=F64), torch.tensor(0.1, dtype=F64), torch.ones(3, dtype=torch.bool))
    A, b = heading_transform(fit, dim=D)
    Q = torch.diag(torch.rand(D, generator=gen, dtype=F64))
    chain.change_frame(A, Q, b)
    track = chain.finish()
    whole, part = track.in_final_frame(), track.in_final_frame(marginal=STATE_DIM)
    assert part.node_mean.shape == (3, STATE_DIM)
    torch.testing.assert_close(part.node_mean, whole.node_mean[:, :STATE_DIM], rtol=0, atol=1e-14)
    torch.testing.assert_close(part.node_cov, whole.node_cov[:, :STATE_DIM, :STATE_DIM], rtol=0, atol=1e-13)
    # node 0 moved: R(0.7) about the vertical
    assert not torch.allclose(part.node_mean[0], mean[:STATE_DIM])
    mixed = A.clone()
    mixed[0, STATE_DIM] = 0.1
    track.frame_changes = [(track.frame_changes[0][0], mixed, b, Q)]
    with pytest.raises(ValueError, match="in_final_frame.*mixes state entries"):
        track.in_final_frame(marginal=STATE_DIM)


def test_deferred_log_values_arrive_when_the_log_is_read_and_entries_not_kept_leave_it():
    """``log_rows(values=, keep=)``: the entries are in the log at once with their host facts; the
    device values join them (as bool, int or float by dtype) when the log is read, and an entry
    whose ``keep`` is False is gone from it. A state kept per row is set for some rows only."""
    chain = BatchChain(3)
    chain.add_nodes([[0.5], [0.5], [0.5]], torch.eye(STATE_DIM, dtype=F64).expand(3, 1, STATE_DIM, STATE_DIM),
                    torch.zeros(3, 1, STATE_DIM, dtype=F64), torch.eye(STATE_DIM, dtype=F64).expand(3, 1, STATE_DIM, STATE_DIM))
    chain.log_rows([2, 0], [{"kind": "a"}, {"kind": "a"}],
                   values={"n": torch.tensor([7, 3]), "x": torch.tensor([0.25, 1.5], dtype=F64),
                           "hit": torch.tensor([True, False])})
    chain.log_rows([0, 1, 2], [{"kind": "b"}] * 3, values={"n": torch.tensor([1, 2, 3])},
                   keep=torch.tensor([False, True, True]))
    assert chain._logs[2][0] == {"t_s": 0.5, "kind": "a"}  # written, the values still on the device
    logs = chain.logs
    assert logs[0] == [{"t_s": 0.5, "kind": "a", "n": 3, "x": 1.5, "hit": False}]
    assert logs[1] == [{"t_s": 0.5, "kind": "b", "n": 2}]
    assert logs[2] == [{"t_s": 0.5, "kind": "a", "n": 7, "x": 0.25, "hit": True}, {"t_s": 0.5, "kind": "b", "n": 3}]
    assert [type(v) for v in logs[2][0].values()] == [float, str, int, float, bool]
    chain.set_row_state("count", [2, 0], torch.tensor([4, 5]))
    assert chain.row_state("count", [0, 1, 2]).tolist() == [5, 0, 4]
    assert chain.row_index([2, 0]) is chain.row_index([2, 0]) and chain.row_index([2, 0]).tolist() == [2, 0]
