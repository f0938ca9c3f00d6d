"""The update helper against closed forms: the Kalman posterior in information form, the
hard gate, the innovation likelihood by hand, and the rows form against each row alone."""
import math

import pytest
import torch

from flowins.filter.chain import BatchChain, ChainBuilder
from flowins.filter.ekf import Gate
from flowins.filter.updater import update, update_rows
from flowins.state import STATE, STATE_DIM, normalize_quaternions

F64 = torch.float64


def random_spd(gen, n, *batch):
    A = torch.randn(*batch, n, n, generator=gen, dtype=F64)
    P = A @ A.transpose(-1, -2) / n + 0.1 * torch.eye(n, dtype=F64)
    return 0.5 * (P + P.transpose(-1, -2))


def chain_at(mean, cov, *, likelihood=False):
    chain = ChainBuilder(BatchChain(1, likelihood=likelihood))
    chain.add_node(0.0, torch.eye(STATE_DIM, dtype=F64), mean, cov)
    return chain


def toy(seed, M, d):
    """A prior ``(26,)``, ``(26, 26)`` and ``M`` linear blocks of dimension ``d``: H, z, R."""
    gen = torch.Generator().manual_seed(seed)
    mean = torch.randn(STATE_DIM, generator=gen, dtype=F64)
    cov = random_spd(gen, STATE_DIM)
    H = torch.randn(M, d, STATE_DIM, generator=gen, dtype=F64)
    z = torch.randn(M, d, generator=gen, dtype=F64)
    R = random_spd(gen, d, M)
    return mean, cov, H, z, R


def residual(H, z, mean):
    return z - (H @ mean)


@pytest.mark.parametrize("M,d", [(2, 3), (5, 1)])
@pytest.mark.parametrize("sequential", [False, True])
def test_the_posterior_is_the_closed_form_kalman_posterior(M, d, sequential):
    mean, cov, H, z, R = toy(0, M, d)
    chain = chain_at(mean, cov)
    result = update(chain, H=H, residual=residual(H, z, mean), noise_cov=R, sequential=sequential, kind="toy")
    # information form: P⁺ = (P⁻¹ + Σ Hᵢᵀ Rᵢ⁻¹ Hᵢ)⁻¹, m⁺ = P⁺ (P⁻¹ m + Σ Hᵢᵀ Rᵢ⁻¹ zᵢ)
    info = torch.linalg.inv(cov) + sum(H[i].T @ torch.linalg.inv(R[i]) @ H[i] for i in range(M))
    info_mean = torch.linalg.solve(cov, mean) + sum(H[i].T @ torch.linalg.solve(R[i], z[i]) for i in range(M))
    post_cov = torch.linalg.inv(info)
    post_mean = post_cov @ info_mean
    torch.testing.assert_close(chain.cov, post_cov, rtol=0, atol=1e-10)
    torch.testing.assert_close(chain.mean, normalize_quaternions(post_mean), rtol=0, atol=1e-10)
    assert torch.equal(result.mean, chain.mean)
    assert chain.log[-1]["kind"] == "toy" and chain.log[-1]["accepted"] == float(M)


def test_a_hard_gate_leaves_the_node_as_it_was_and_logs_the_rejection():
    mean, cov, H, z, R = toy(1, 1, 3)
    mean[STATE.q] = mean[STATE.q_prev] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64)  # unit: normalising is exact
    v = residual(H, z, mean) + 1e3
    chain = chain_at(mean, cov)
    update(chain, H=H, residual=v, noise_cov=R, gate=Gate(mode="hard"), kind="toy", name="far")
    assert torch.equal(chain.mean, mean) and torch.equal(chain.cov, cov)
    S = H[0] @ cov @ H[0].T + R[0]
    entry = chain.log[-1]
    assert entry["accepted"] == 0.0 and entry["name"] == "far"
    assert abs(entry["nis"] - float(v[0] @ torch.linalg.solve(S, v[0]))) <= 1e-10 * entry["nis"]


def test_the_likelihood_is_half_the_nis_plus_log_det_s_of_the_accepted_blocks():
    """``½ (vᵀ S⁻¹ v + log det S)`` per accepted block (the Gaussian's ``-log`` density less
    ``½ d log 2π``), over ``d`` scalars each; a gated block and a pseudo-measurement add none."""
    mean, cov, H, z, R = toy(2, 2, 3)
    v = residual(H, z, mean)
    v[1] += 1e3  # block 1 far off: the hard gate rejects it
    chain = chain_at(mean, cov, likelihood=True)
    update(chain, H=H, residual=v, noise_cov=R, gate=Gate(mode="hard"), kind="toy")
    S = H[0] @ cov @ H[0].T + R[0]
    by_hand = 0.5 * (float(v[0] @ torch.linalg.solve(S, v[0])) + float(torch.logdet(S)))
    density = torch.distributions.MultivariateNormal(torch.zeros(3, dtype=F64), covariance_matrix=S)
    assert abs(by_hand - (float(-density.log_prob(v[0])) - 1.5 * math.log(2 * math.pi))) <= 1e-12 * abs(by_hand)
    update(chain, H=H, residual=v, noise_cov=R, likelihood=False, kind="pseudo")
    track = chain.finish()
    assert abs(float(track.nll) - by_hand) <= 1e-12 * abs(by_hand)
    assert track.nll_count == 3.0


def test_rows_update_together_as_each_alone_and_a_row_without_valid_blocks_is_only_logged():
    priors = [toy(seed, 4, 2) for seed in (3, 4, 5)]
    H = torch.stack([p[2] for p in priors])
    v = torch.stack([residual(p[2], p[3], p[0]) for p in priors])
    R = torch.stack([p[4] for p in priors])
    valid = torch.tensor([[True, True, False, True], [True] * 4, [False] * 4])
    H, v = H * valid[..., None, None], v * valid[..., None]  # an invalid block carries nothing
    batch = BatchChain(3, likelihood=True)
    eye = torch.eye(STATE_DIM, dtype=F64).expand(3, 1, STATE_DIM, STATE_DIM)
    batch.add_nodes([[0.0]] * 3, eye, torch.stack([p[0] for p in priors]).unsqueeze(1),
                    torch.stack([p[1] for p in priors]).unsqueeze(1))
    update_rows(batch, [0, 1, 2], H=H, residual=v, noise_cov=R, gate=Gate(mode="hard", probability=0.9),
                valid=valid, infos=[{"kind": "toy"}] * 3)
    tracks = batch.finish()
    for b in range(2):
        alone = chain_at(*priors[b][:2], likelihood=True)
        update(alone, H=H[b], residual=v[b], noise_cov=R[b], gate=Gate(mode="hard", probability=0.9), valid=valid[b],
               kind="toy")
        track = alone.finish()
        torch.testing.assert_close(tracks[b].node_mean, track.node_mean, rtol=0, atol=1e-12)
        torch.testing.assert_close(tracks[b].node_cov, track.node_cov, rtol=0, atol=1e-12)
        assert tracks[b].log[0].keys() == track.log[0].keys()
        assert tracks[b].log[0]["accepted"] == track.log[0]["accepted"] <= valid[b].sum()
        torch.testing.assert_close(tracks[b].nll, track.nll, rtol=1e-12, atol=0)
    assert torch.equal(tracks[2].node_mean[0], priors[2][0]) and torch.equal(tracks[2].node_cov[0], priors[2][1])
    assert tracks[2].log == [{"t_s": 0.0, "kind": "toy", "nis": 0.0, "accepted": 0.0}]
    assert float(tracks[2].nll) == 0.0 and tracks[2].nll_count == 0.0


def test_a_valid_mask_of_the_wrong_shape_is_refused():
    mean, cov, H, z, R = toy(6, 2, 3)
    with pytest.raises(ValueError, match="valid must be"):
        update(chain_at(mean, cov), H=H, residual=residual(H, z, mean), noise_cov=R,
               valid=torch.ones(3, dtype=torch.bool))


def test_a_run_without_valid_blocks_keeps_its_node_and_is_logged():
    mean, cov, H, z, R = toy(7, 2, 3)
    chain = chain_at(mean, cov)
    update(chain, H=0 * H, residual=0 * z, noise_cov=R, valid=torch.zeros(2, dtype=torch.bool), kind="toy")
    assert torch.equal(chain.mean, mean) and torch.equal(chain.cov, cov)
    assert chain.log == [{"t_s": 0.0, "kind": "toy", "nis": 0.0, "accepted": 0.0}]


def test_residuals_of_the_wrong_rank_are_refused_naming_the_form_to_use():
    mean, cov, H, z, R = toy(8, 2, 3)
    with pytest.raises(ValueError, match="update_rows"):
        update(chain_at(mean, cov), H=H[None], residual=z[None], noise_cov=R[None])
    chain = chain_at(mean, cov)
    with pytest.raises(ValueError, match="r = 1 rows"):
        update_rows(chain.batch, [0], H=H, residual=z, noise_cov=R)


@pytest.mark.parametrize("waits", [False, True])
def test_a_failed_update_names_its_row_and_time_at_once_or_at_the_end_of_the_pass(monkeypatch, waits):
    """Row 1's innovation covariance is exactly zero (H = 0, R = 0: its solve is singular).
    Where reading the flag back is free (the CPU, eager) the update raises at once; where it
    costs (a GPU, ``torch.compile``) the flag stays on the device and ``finish`` raises the
    same error at the end of the pass. Either names row 1 and its time, never row 0."""
    import flowins.filter.chain as chain_module

    monkeypatch.setattr(chain_module, "waits_cost", lambda t: waits)
    priors = [toy(seed, 2, 3) for seed in (1, 2)]
    mean, cov = torch.stack([p[0] for p in priors]), torch.stack([p[1] for p in priors])
    H, z, R = (torch.stack([p[k] for p in priors]) for k in (2, 3, 4))
    H[1], R[1] = 0.0, 0.0
    batch = BatchChain(2)
    eye = torch.eye(STATE_DIM, dtype=F64).expand(2, 1, STATE_DIM, STATE_DIM)
    batch.add_nodes([[0.5], [1.25]], eye, mean.unsqueeze(1), cov.unsqueeze(1))
    message = r"update at t = 1\.250 s: a factorisation failed in batch row\(s\) \[1\]"
    with pytest.raises(ValueError, match=message):
        update_rows(batch, [0, 1], H=H, residual=z - (H @ mean[:, None, :, None]).squeeze(-1), noise_cov=R)
        assert waits, "the CPU's eager pass raises in the update"
        batch.finish()


@pytest.mark.parametrize("whitened", [False, True])
@pytest.mark.parametrize("sequential", [False, True])
def test_a_compiled_update_grows_its_rows_and_blocks_without_changing_the_result(whitened, sequential):
    """With every step compiled (``Compiler.all_steps``, what CUDA runs), two rows of a chain of
    four update with three blocks: the rows are grown to four and the blocks to four (zero
    Jacobian and residual, unit noise, invalid) for one fixed shape. Each row's posterior, NIS,
    gate weight and likelihood equal the plain update's (the gate hard, one block invalid, one
    rejected, blocks of their own degrees of freedom), through ``torch.compile`` with a backend
    that needs no compiler."""
    from flowins.filter.compiling import Compiler
    from flowins.filter.updater import gated_update, step_rows

    M, d = 3, 2
    gen = torch.Generator().manual_seed(5)
    means = torch.randn(4, STATE_DIM, generator=gen, dtype=F64)
    covs = random_spd(gen, STATE_DIM, 4)
    H = torch.randn(2, M, d, STATE_DIM, generator=gen, dtype=F64)
    res = torch.randn(2, M, d, generator=gen, dtype=F64)
    res[0, 2] *= 40.0  # rejected by the gate
    R = None if whitened else random_spd(gen, d, 2, M)
    logdet = 0.1 * torch.randn(2, M, generator=gen, dtype=F64) if whitened else None
    valid = torch.tensor([[True, True, True], [True, False, True]])
    dof = torch.tensor([[2, 1, 2], [2, 2, 1]])
    gate = Gate(probability=0.99)
    rows = [3, 1]
    torch._dynamo.reset()
    results = {}
    for compiler in (None, Compiler("eager", reason="test", all_steps=True)):
        chain = BatchChain(4, likelihood=True, compiler=compiler)
        chain.add_nodes([[0.0]] * 4, torch.eye(STATE_DIM, dtype=F64).expand(4, 1, -1, -1), means.unsqueeze(1),
                        covs.unsqueeze(1))
        results[compiler is None] = step_rows(chain, rows, H=H, residual=res, noise_cov=R, gate=gate,
                                              sequential=sequential, valid=valid, dof=dof, noise_logdet=logdet)
        assert compiler is None or compiler.calls == 1
    plain = gated_update(means[rows], covs[rows], H=H, residual=res, noise_cov=R, gate=gate, sequential=sequential,
                         valid=valid, likelihood=True, dof=dof, noise_logdet=logdet)
    for got in results.values():
        for a, b in zip(got, plain):
            assert (a is None) == (b is None)
            if a is not None:
                assert a.shape == b.shape
                scale = 1.0 if b.dtype == torch.bool else max(1.0, float(b.abs().max()))
                torch.testing.assert_close(a, b, rtol=0, atol=1e-10 * scale)
    assert plain.weight[0, 2] == 0.0 and plain.weight[1, 1] == 0.0 and plain.weight[0, 0] == 1.0
