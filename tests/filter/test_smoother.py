"""RTS smoother over a node chain against the dense batch Gaussian posterior.

The truth: stack all node states ``x_0..x_{J-1}`` of a linear-Gaussian chain
``x_j = A_j x_{j-1} + w_j`` into one Gaussian (mean and full joint covariance,
cross-covariances included), condition on every measurement with one dense
solve and read off the marginals.
"""
import pytest
import torch

from flowins.filter.augmentation import (
    augmentation_matrix,
    copy_pose,
    forgetting_matrices,
)
from flowins.filter.ekf import ekf_update, linear_predict
from flowins.filter.augmentation import PoseAugmentation
from flowins.filter.chain import ChainBuilder
from flowins.filter.smoother import rts_smooth
from flowins.geometry import quaternion as quat
from flowins.state import CORE_DIM, STATE, STATE_DIM, make_state

F64 = torch.float64


def random_spd(gen, n, scale=1.0, floor=0.1):
    A = torch.randn(n, n, generator=gen, dtype=F64)
    P = scale * (A @ A.T / n + floor * torch.eye(n, dtype=F64))
    return 0.5 * (P + P.T)


class LinearChain:
    """Records a linear-Gaussian chain twice: into a ChainBuilder and as the batch model."""

    def __init__(self, m0, P0):
        self.chain = ChainBuilder()
        self.chain.add_node(0.0, torch.eye(m0.shape[0], dtype=F64), m0, P0)
        self.m0, self.P0 = m0, P0
        self.A, self.Q = [], []  # per node j >= 1
        self.meas = []  # (node index, H (n, D), z (n,), R (n, n))

    @property
    def J(self):
        return len(self.chain.t_s)

    def predict(self, A, Q, dt=1.0):
        """An ordinary prediction to a new time."""
        mean, cov = linear_predict(self.chain.mean, self.chain.cov, A, Q)
        self.chain.add_node(self.chain.time_s + dt, A, mean, cov)
        self.A.append(A)
        self.Q.append(Q)

    def predict_same_time(self, A, Q):
        """A forgetting-like step (ChainBuilder.linear_predict: a node at the same time)."""
        self.chain.linear_predict(A, Q)
        self.A.append(A)
        self.Q.append(Q)

    def measure(self, H, z, R):
        """A linear update of the newest node, through ekf_update (one block)."""
        innovation = z - H @ self.chain.mean
        n = z.shape[0]
        result = ekf_update(
            self.chain.mean,
            self.chain.cov,
            innovation=innovation.reshape(1, n),
            H=H.reshape(1, n, -1),
            noise_cov=R.reshape(1, n, n),
        )
        self.chain.update(result)
        self.meas.append((self.J - 1, H, z, R))

    def batch_posterior(self):
        """Dense truth: marginal means ``(J, D)`` and covariances ``(J, D, D)``."""
        J, D = self.J, self.m0.shape[0]
        # x = mu + L w, w = (x_0 - m0, w_1, ..., w_{J-1}) ~ N(0, blkdiag(P0, Q_1, ...))
        L = torch.zeros(J * D, J * D, dtype=F64)
        mu = torch.zeros(J, D, dtype=F64)
        mu[0] = self.m0
        for j in range(J):
            L[j * D : (j + 1) * D, j * D : (j + 1) * D] = torch.eye(D, dtype=F64)
            if j > 0:
                A = self.A[j - 1]
                mu[j] = A @ mu[j - 1]
                L[j * D : (j + 1) * D, : j * D] = A @ L[(j - 1) * D : j * D, : j * D]
        W = torch.block_diag(self.P0, *self.Q)
        Sigma = L @ W @ L.T
        mu = mu.reshape(-1)
        rows, zs, Rs = [], [], []
        for j, H, z, R in self.meas:
            Hj = torch.zeros(H.shape[0], J * D, dtype=F64)
            Hj[:, j * D : (j + 1) * D] = H
            rows.append(Hj)
            zs.append(z)
            Rs.append(R)
        Hb, zb, Rb = torch.cat(rows), torch.cat(zs), torch.block_diag(*Rs)
        S = Hb @ Sigma @ Hb.T + Rb
        K = torch.linalg.solve(S, Hb @ Sigma).T
        mu_post = mu + K @ (zb - Hb @ mu)
        Sigma_post = Sigma - K @ S @ K.T
        Sigma_post = 0.5 * (Sigma_post + Sigma_post.T)
        marg = torch.stack([Sigma_post[j * D : (j + 1) * D, j * D : (j + 1) * D] for j in range(J)])
        return mu_post.reshape(J, D), marg, mu.reshape(J, D), Sigma


def assert_close_scaled(got, expected, tol):
    scale = max(1.0, float(expected.abs().max()))
    err = float((got - expected).abs().max())
    assert err <= tol * scale, f"max error {err:.3e} > {tol:.1e} * {scale:.3g}"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rts_equals_batch_posterior_on_generic_chain(seed):
    gen = torch.Generator().manual_seed(seed)
    D = 5
    lc = LinearChain(torch.randn(D, generator=gen, dtype=F64), random_spd(gen, D, scale=2.0))

    def rand_A():
        return torch.eye(D, dtype=F64) + 0.2 * torch.randn(D, D, generator=gen, dtype=F64)

    def measure(n=2, scale=0.3):
        H = torch.randn(n, D, generator=gen, dtype=F64)
        lc.measure(H, torch.randn(n, generator=gen, dtype=F64), random_spd(gen, n, scale=scale))

    measure()  # an update at the first node
    for k in range(6):
        lc.predict(rand_A(), random_spd(gen, D, scale=0.05))
        if k % 3 != 2:  # some nodes without a measurement
            measure()
    measure(n=3)  # two updates at the same node
    # forgetting-like step: rows 3, 4 forgotten, then re-inflated by Q
    A_forget = torch.diag(torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0], dtype=F64))
    Q_forget = torch.diag(torch.tensor([0.0, 0.0, 0.0, 4.0, 9.0], dtype=F64))
    lc.predict_same_time(A_forget, Q_forget)
    # augmentation-like update "x3 = x0, x4 = x1" with a small nugget
    H_aug = torch.tensor([[1.0, 0, 0, -1, 0], [0, 1.0, 0, 0, -1]], dtype=F64)
    lc.measure(H_aug, torch.zeros(2, dtype=F64), 1e-4 * torch.eye(2, dtype=F64))
    for k in range(5):
        lc.predict(rand_A(), random_spd(gen, D, scale=0.05))
        if k != 1:
            measure()

    track = lc.chain.finish()
    assert track.t_s.shape[0] == lc.J
    # the same-time node: two nodes share a time, the output keeps the last one
    assert int(track.output_index.shape[0]) == lc.J - 1
    smoothed = rts_smooth(track, normalize=False)
    mean_true, cov_true, _, _ = lc.batch_posterior()
    assert_close_scaled(smoothed.node_mean, mean_true, 1e-8)
    assert_close_scaled(smoothed.node_cov, cov_true, 1e-8)
    # the filter's last node is already the full posterior
    assert_close_scaled(track.node_mean[-1], mean_true[-1], 1e-8)
    # and the smoother does something: earlier nodes differ from the filter
    assert float((smoothed.node_mean[0] - track.node_mean[0]).abs().max()) > 1e-3


def test_batch_prior_matches_forward_filter_without_measurements():
    """Sanity of the truth itself: with no measurement, marginals are the forward predictions."""
    gen = torch.Generator().manual_seed(4)
    D = 4
    lc = LinearChain(torch.randn(D, generator=gen, dtype=F64), random_spd(gen, D))
    for _ in range(4):
        lc.predict(torch.randn(D, D, generator=gen, dtype=F64), random_spd(gen, D, scale=0.1))
    lc.measure(torch.zeros(1, D, dtype=F64), torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))  # no information
    track = lc.chain.finish()
    mean_true, cov_true, _, _ = lc.batch_posterior()
    assert_close_scaled(track.pred_mean, mean_true, 1e-10)
    assert_close_scaled(track.pred_cov, cov_true, 1e-10)
    smoothed = rts_smooth(track, normalize=False)
    assert_close_scaled(smoothed.node_cov, cov_true, 1e-9)


@pytest.mark.parametrize("seed", [0, 1])
def test_rts_equals_batch_posterior_through_paper_forgetting_and_augmentation(seed):
    """A⋆, Q⋆ and H⋆ of the paper as the linear model of a 26-dim Gaussian chain."""
    gen = torch.Generator().manual_seed(seed)
    D = STATE_DIM
    A_star, Q_star = forgetting_matrices(10.0, 10.0, dtype=F64)
    H_star = augmentation_matrix(dtype=F64)
    nugget = 1e-4
    m0 = torch.randn(D, generator=gen, dtype=F64)
    lc = LinearChain(m0, random_spd(gen, D, scale=1.0))

    def rand_A():
        A = torch.eye(D, dtype=F64)
        A[:CORE_DIM, :CORE_DIM] += 0.05 * torch.randn(CORE_DIM, CORE_DIM, generator=gen, dtype=F64)
        return A  # the old pose is constant between frames, like the INS

    def measure():
        H = torch.randn(3, D, generator=gen, dtype=F64)
        lc.measure(H, torch.randn(3, generator=gen, dtype=F64), random_spd(gen, 3, scale=0.5))

    def Q_core():
        Q = torch.zeros(D, D, dtype=F64)
        Q[:CORE_DIM, :CORE_DIM] = random_spd(gen, CORE_DIM, scale=0.01)
        return Q

    def frame():
        lc.predict_same_time(A_star, Q_star)
        lc.measure(H_star, torch.zeros(7, dtype=F64), nugget * torch.eye(7, dtype=F64))

    frame()
    for k in range(4):
        lc.predict(rand_A(), Q_core())
        measure()
        if k % 2 == 1:
            frame()
    lc.predict(rand_A(), Q_core())  # a node without measurement at the end

    track = lc.chain.finish()
    smoothed = rts_smooth(track, normalize=False)
    mean_true, cov_true, _, _ = lc.batch_posterior()
    assert_close_scaled(smoothed.node_mean, mean_true, 1e-8)
    assert_close_scaled(smoothed.node_cov, cov_true, 1e-8)
    # the augmented pose of a frame node equals its current pose up to the nugget
    j = 1  # the first frame's forgetting node
    p_gap = smoothed.node_mean[j, STATE.p] - smoothed.node_mean[j, STATE.p_prev]
    assert float(p_gap.abs().max()) < 1e-2


def _pose_state(seed):
    """A plausible 26-dim Gaussian: unit quaternions, a random SPD core and the augmented copy."""
    gen = torch.Generator().manual_seed(seed)
    q = quat.normalize(torch.randn(4, generator=gen, dtype=F64))
    q_prev = quat.normalize(torch.randn(4, generator=gen, dtype=F64))
    mean = make_state(
        p=torch.tensor([12.0, -5.0, 1.5], dtype=F64),
        v=torch.randn(3, generator=gen, dtype=F64),
        q=q,
        b_a=0.05 * torch.randn(3, generator=gen, dtype=F64),
        b_w=1e-3 * torch.randn(3, generator=gen, dtype=F64),
        p_prev=torch.tensor([11.0, -4.5, 1.4], dtype=F64),
        q_prev=q_prev,
    )
    scales = torch.ones(STATE_DIM, dtype=F64)
    scales[STATE.q] = 0.05
    scales[STATE.q_prev] = 0.05
    scales[STATE.b_w] = 0.01
    cov = random_spd(gen, STATE_DIM) * torch.outer(scales, scales)
    return mean, 0.5 * (cov + cov.T)


@pytest.mark.parametrize("seed", [0, 1])
def test_paper_augmentation_with_large_sigma_converges_to_limit(seed):
    mean, cov = _pose_state(seed)
    results = {}
    for mode in ("paper", "limit"):
        chain = ChainBuilder()
        chain.add_node(0.0, torch.eye(STATE_DIM, dtype=F64), mean, cov)
        PoseAugmentation(0.0, sigma_p0=1e4, sigma_q0=1e3, nugget_var=1e-6, mode=mode).apply(chain)
        assert len(chain.t_s) == 2 and chain.t_s[1] == 0.0  # a forgetting node at the same time
        results[mode] = (chain.mean, chain.cov)
    (m_paper, P_paper), (m_limit, P_limit) = results["paper"], results["limit"]
    assert float((m_paper - m_limit).abs().max()) <= 1e-5 * float(m_limit.abs().max())
    assert float((P_paper - P_limit).abs().max()) <= 1e-5 * float(P_limit.abs().max())
    # the limit itself, by hand: the old pose is the current one (copied rows and columns)
    idx_new = STATE.indices("p", "q")
    idx_old = STATE.indices("p_prev", "q_prev")
    torch.testing.assert_close(m_limit[idx_old], mean[idx_new], rtol=0, atol=1e-12)
    torch.testing.assert_close(P_limit[idx_old][:, :CORE_DIM], cov[idx_new][:, :CORE_DIM], rtol=0, atol=1e-15)
    expected_block = cov[idx_new][:, idx_new] + 1e-6 * torch.eye(7, dtype=F64)
    torch.testing.assert_close(P_limit[idx_old][:, idx_old], expected_block, rtol=0, atol=1e-15)
    torch.testing.assert_close(P_limit[:CORE_DIM, :CORE_DIM], cov[:CORE_DIM, :CORE_DIM], rtol=0, atol=0)
    # copy_pose is the same step as the limit event (up to its quaternion re-normalisation)
    m_copy, P_copy = copy_pose(mean, cov, nugget_var=1e-6)
    torch.testing.assert_close(m_copy, m_limit, rtol=0, atol=1e-14)
    torch.testing.assert_close(P_copy, P_limit, rtol=0, atol=0)


def test_paper_augmentation_with_small_sigma_is_the_linear_step():
    """Finite σ: the event is the textbook linear prediction + update, and it shrinks the pose."""
    mean, cov = _pose_state(0)
    chain = ChainBuilder()
    chain.add_node(0.0, torch.eye(STATE_DIM, dtype=F64), mean, cov)
    sigma_p0, sigma_q0, nugget = 3.0, 1e3, 1e-9
    PoseAugmentation(0.0, sigma_p0=sigma_p0, sigma_q0=sigma_q0, nugget_var=nugget, mode="paper").apply(chain)
    # textbook: forget (A⋆ m, A⋆ P A⋆ᵀ + Q⋆), then observe H⋆ x = 0 with R = nugget I
    A, Q = forgetting_matrices(sigma_p0, sigma_q0, dtype=F64)
    m_f, P_f = A @ mean, A @ cov @ A.T + Q
    track = chain.finish()
    torch.testing.assert_close(track.pred_mean[1], m_f, rtol=0, atol=1e-15)
    torch.testing.assert_close(track.pred_cov[1], P_f, rtol=0, atol=1e-9)
    assert torch.equal(track.transition[1], A)
    H = augmentation_matrix(dtype=F64)
    S = H @ P_f @ H.T + nugget * torch.eye(7, dtype=F64)
    K = P_f @ H.T @ torch.linalg.inv(S)
    m_lin = m_f - K @ H @ m_f
    P_lin = P_f - K @ S @ K.T
    core = torch.arange(STATE.q.start)  # p, v: untouched by the quaternion re-normalisation
    torch.testing.assert_close(chain.mean[core], m_lin[core], rtol=0, atol=1e-8)
    torch.testing.assert_close(chain.cov, 0.5 * (P_lin + P_lin.T), rtol=0, atol=1e-6)
    # σ_p0 = 3 m against a position spread of about 1 m: the pose is pulled towards the origin
    shrink = float(chain.mean[STATE.p].norm() - mean[STATE.p].norm())
    assert shrink < -0.05


@pytest.mark.parametrize("run_length", [1, 2, 5, 13])
def test_rts_through_long_prediction_runs_equals_batch_posterior(run_length):
    """Runs of prediction-only nodes of several lengths between updates (the
    key-node smoother composes gains across each run)."""
    gen = torch.Generator().manual_seed(run_length)
    D = 4
    lc = LinearChain(torch.randn(D, generator=gen, dtype=F64), random_spd(gen, D))
    for block in range(3):
        for _ in range(run_length):
            lc.predict(torch.eye(D, dtype=F64) + 0.1 * torch.randn(D, D, generator=gen, dtype=F64), random_spd(gen, D, scale=0.02))
        H = torch.randn(2, D, generator=gen, dtype=F64)
        lc.measure(H, torch.randn(2, generator=gen, dtype=F64), random_spd(gen, 2, scale=0.2))
    for _ in range(run_length):  # and a trailing run without updates
        lc.predict(torch.eye(D, dtype=F64), random_spd(gen, D, scale=0.02))
    smoothed = rts_smooth(lc.chain.finish(), normalize=False)
    mean_true, cov_true, _, _ = lc.batch_posterior()
    assert_close_scaled(smoothed.node_mean, mean_true, 1e-8)
    assert_close_scaled(smoothed.node_cov, cov_true, 1e-8)


@pytest.mark.parametrize("blocks", ["one", "many"])
@pytest.mark.parametrize("marginal", [1, 2, 4])
def test_marginal_smoother_equals_batch_posterior_marginal(marginal, blocks, monkeypatch):
    """``rts_smooth(marginal=m)``: the batch posterior's marginal of the first ``m`` entries, through
    short runs of prediction-only nodes, forgetting-like steps and a long run, and the same
    figures as the whole-state smoother's first ``m`` entries; the same with the nodes taken in
    blocks of a few nodes (a run longer than a block is one block)."""
    from flowins.filter import smoother

    if blocks == "many":
        monkeypatch.setattr(smoother, "_BLOCK_BYTES", 3 * 8 * 4 * 4)
        assert smoother._node_blocks(torch.tensor([0, 2, 3, 9, 40, 41]), 42, 4) == [(0, 3), (3, 9), (9, 40), (40, 41)]
    gen = torch.Generator().manual_seed(11 + marginal)
    D = 4
    lc = LinearChain(torch.randn(D, generator=gen, dtype=F64), random_spd(gen, D))
    for run_length in (0, 1, 2, 7, 30, 1):
        for _ in range(run_length):
            lc.predict(torch.eye(D, dtype=F64) + 0.1 * torch.randn(D, D, generator=gen, dtype=F64), random_spd(gen, D, scale=0.02))
        lc.predict_same_time(torch.eye(D, dtype=F64) + 0.1 * torch.randn(D, D, generator=gen, dtype=F64), random_spd(gen, D, scale=0.01))
        H = torch.randn(2, D, generator=gen, dtype=F64)
        lc.measure(H, torch.randn(2, generator=gen, dtype=F64), random_spd(gen, 2, scale=0.2))
    lc.predict(torch.eye(D, dtype=F64), random_spd(gen, D, scale=0.02))
    track = lc.chain.finish()
    part = rts_smooth(track, normalize=False, marginal=marginal)
    mean_true, cov_true, _, _ = lc.batch_posterior()
    assert part.node_mean.shape == (lc.J, marginal) and part.node_cov.shape == (lc.J, marginal, marginal)
    assert_close_scaled(part.node_mean, mean_true[:, :marginal], 1e-8)
    assert_close_scaled(part.node_cov, cov_true[:, :marginal, :marginal], 1e-8)
    whole = rts_smooth(track, normalize=False)
    assert_close_scaled(part.node_cov, whole.node_cov[:, :marginal, :marginal], 1e-12)


def test_marginal_smoother_refuses_a_frame_change_that_mixes_in_later_entries():
    gen = torch.Generator().manual_seed(5)
    D = 3
    lc = LinearChain(torch.randn(D, generator=gen, dtype=F64), random_spd(gen, D))
    lc.predict(torch.eye(D, dtype=F64), random_spd(gen, D, scale=0.1))
    track = lc.chain.finish()
    A = torch.eye(D, dtype=F64)
    track.frame_changes = [(1, A, torch.zeros(D, dtype=F64), torch.zeros(D, D, dtype=F64))]
    assert rts_smooth(track, normalize=False, marginal=2).node_mean.shape == (2, 2)  # block-diagonal: fine
    A = A.clone()
    A[0, 2] = 0.5
    track.frame_changes = [(1, A, torch.zeros(D, dtype=F64), torch.zeros(D, D, dtype=F64))]
    with pytest.raises(ValueError, match="marginal=2"):
        rts_smooth(track, marginal=2)
    with pytest.raises(ValueError, match="expected 1 .. 3"):
        rts_smooth(track, marginal=4)


def test_key_node_smoother_equals_node_by_node_recursion_on_ins_gnss():
    from flowins.data.synthetic import synthetic_walk_recording
    from flowins.filter.smoother import rts_smooth_sequential
    from flowins.navigation import NavigationConfig, NavigationRun, navigate

    rec = synthetic_walk_recording(duration_s=20.0, seed=3)
    result = navigate(NavigationRun(rec.imu, rec.gnss), config=NavigationConfig())
    fast = rts_smooth(result.filter)
    slow = rts_smooth_sequential(result.filter)
    assert_close_scaled(fast.node_mean, slow.node_mean, 1e-9)
    assert_close_scaled(fast.node_cov, slow.node_cov, 1e-9)


def test_rts_through_an_exactly_singular_predicted_covariance_equals_batch_posterior():
    """A state entry known exactly (zero variance, no process noise: a constant, or the
    float32 fate of the pose copy's nugget) makes the predicted covariances exactly singular;
    the smoother's gain is still defined on their range and must equal the batch posterior
    (the factorisation falls back to a rounding-level jitter for those nodes)."""
    gen = torch.Generator().manual_seed(3)
    D = 3
    P0 = torch.zeros(D, D, dtype=F64)
    P0[:2, :2] = random_spd(gen, 2)
    chain = LinearChain(torch.tensor([0.0, 0.0, 1.5], dtype=F64), P0)
    A = torch.tensor([[1.0, 0.1, 0.0], [0.0, 1.0, 0.2], [0.0, 0.0, 1.0]], dtype=F64)
    Q = torch.diag(torch.tensor([0.01, 0.05, 0.0], dtype=F64))
    for k in range(3):
        chain.predict(A, Q)
        chain.measure(torch.tensor([[1.0, 0.0, 1.0]], dtype=F64), torch.tensor([0.3 * k + 1.0], dtype=F64),
                      0.1 * torch.eye(1, dtype=F64))
    track = chain.chain.finish()
    with pytest.raises(RuntimeError):  # what a plain factorisation does with it
        torch.linalg.lu_factor(track.pred_cov[1])
    smoothed = rts_smooth(track, normalize=False)
    mean, cov, _, _ = chain.batch_posterior()
    assert_close_scaled(smoothed.mean, mean, 1e-9)
    assert_close_scaled(smoothed.cov, cov, 1e-9)


def test_matrices_whose_batched_pivots_come_out_invalid_are_factorised_alone(monkeypatch):
    """torch 2.13's MKL can return invalid pivots for some matrices of a batch (after
    ``torch.set_num_threads``): those are factorised again one by one, and the result is each
    matrix's own LU, the valid ones' untouched."""
    from flowins.filter import smoother

    g = torch.Generator().manual_seed(0)
    a = torch.randn(5, 6, 6, generator=g, dtype=torch.float64)
    cov = a @ a.transpose(-1, -2) + 6 * torch.eye(6, dtype=torch.float64)
    real = torch.linalg.lu_factor_ex

    def broken(x):
        LU, pivots, info = real(x)
        if x.ndim == 3:  # the batched call: matrices 1 and 3 get pivots outside 1..6
            pivots = pivots.clone()
            pivots[1, 2], pivots[3, 0] = 0, 7
        return LU, pivots, info

    monkeypatch.setattr(smoother.torch.linalg, "lu_factor_ex", broken)
    LU, pivots = smoother._factor_predicted(cov, torch.arange(5.0))
    monkeypatch.undo()
    for i in range(5):
        LU_i, piv_i, _ = torch.linalg.lu_factor_ex(cov[i])
        assert torch.equal(LU[i], LU_i) and torch.equal(pivots[i], piv_i)


@pytest.mark.parametrize("gathered", [True, False])
def test_smoother_gradient_equals_finite_differences_through_runs_and_blocks(gathered, monkeypatch):
    """The smoother is in the training graph: the gradient of a smoothed mean and variance
    with respect to a process noise and a measurement value, through runs of prediction-only
    nodes (each node's columns carried to its next key in place) and several blocks, equals
    central finite differences, with the keys' jumps and gains gathered beforehand or taken
    key by key."""
    from flowins.filter import smoother

    monkeypatch.setattr(smoother, "_BLOCK_BYTES", 4 * 8 * 3 * 3)
    if not gathered:
        monkeypatch.setattr(smoother, "_STACKED_BYTES", 0)
    D = 3
    gen = torch.Generator().manual_seed(8)
    A = [torch.eye(D, dtype=F64) + 0.1 * torch.randn(D, D, generator=gen, dtype=F64) for _ in range(12)]
    Hs = [torch.randn(1, D, generator=gen, dtype=F64) for _ in range(4)]
    P0 = random_spd(gen, D)

    def smoothed(q, z):
        lc = LinearChain(torch.zeros(D, dtype=F64), P0)
        for i, Ai in enumerate(A):
            lc.predict(Ai, q * torch.eye(D, dtype=F64))
            if i % 3 == 2:
                lc.measure(Hs[i // 3], z[i // 3 : i // 3 + 1], 0.1 * torch.eye(1, dtype=F64))
        out = rts_smooth(lc.chain.finish(), normalize=False, marginal=2)
        return out.node_mean[1:4, 0].sum() + out.node_cov[1:4, 1, 1].sum()

    q = torch.tensor(0.05, dtype=F64, requires_grad=True)
    z = torch.tensor([0.3, -0.2, 0.5, 0.1], dtype=F64, requires_grad=True)
    value = smoothed(q, z)
    g_q, g_z = torch.autograd.grad(value, (q, z))
    h = 1e-6
    fd_q = (smoothed(q.detach() + h, z.detach()) - smoothed(q.detach() - h, z.detach())) / (2 * h)
    e = torch.zeros(4, dtype=F64)
    e[1] = h
    fd_z = (smoothed(q.detach(), z.detach() + e) - smoothed(q.detach(), z.detach() - e)) / (2 * h)
    assert abs(float(g_q) - float(fd_q)) <= 1e-6 * max(1.0, abs(float(fd_q)))
    assert abs(float(g_z[1]) - float(fd_z)) <= 1e-6 * max(1.0, abs(float(fd_z)))


@pytest.mark.parametrize("gathered", [True, False])
@pytest.mark.parametrize("blocks", ["one", "many"])
def test_tracks_smoothed_together_equal_each_chains_batch_posterior(blocks, gathered, monkeypatch):
    """``rts_smooth_batch``: chains of different lengths, key counts, one node only and a change of
    frame, smoothed together, each equal to its own dense batch posterior (and the same with the
    nodes in blocks of a few, each handed over as the recursion passes its keys, and with the
    keys' jumps and gains taken key by key instead of gathered beforehand)."""
    from flowins.filter import smoother
    from flowins.filter.smoother import rts_smooth_batch

    gen = torch.Generator().manual_seed(23)
    D = 4
    chains = []
    for runs in ((2, 0, 5), (0,), (1, 1, 1, 1, 1, 1, 1), (9,)):
        lc = LinearChain(torch.randn(D, generator=gen, dtype=F64), random_spd(gen, D))
        for run_length in runs:
            for _ in range(run_length):
                lc.predict(torch.eye(D, dtype=F64) + 0.1 * torch.randn(D, D, generator=gen, dtype=F64),
                           random_spd(gen, D, scale=0.02))
            H = torch.randn(2, D, generator=gen, dtype=F64)
            lc.measure(H, torch.randn(2, generator=gen, dtype=F64), random_spd(gen, 2, scale=0.2))
        chains.append(lc)
    tracks = [lc.chain.finish() for lc in chains]
    assert sorted(int(t.key_nodes().sum()) for t in tracks) == [1, 1, 2, 7]  # unequal key counts (one track of one node)
    if blocks == "many":
        monkeypatch.setattr(smoother, "_BLOCK_BYTES", 2 * 8 * D * D)
    if not gathered:
        monkeypatch.setattr(smoother, "_STACKED_BYTES", 0)
    smoothed = rts_smooth_batch(tracks, normalize=False)
    for lc, track, got in zip(chains, tracks, smoothed):
        mean_true, cov_true, _, _ = lc.batch_posterior()
        assert got.node_mean.shape == (lc.J, D)
        assert_close_scaled(got.node_mean, mean_true, 1e-8)
        assert_close_scaled(got.node_cov, cov_true, 1e-8)
        alone = rts_smooth(track, normalize=False)
        assert_close_scaled(got.node_cov, alone.node_cov, 1e-12)
    with pytest.raises(ValueError, match="differ in size"):
        rts_smooth_batch([tracks[0], LinearChain(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64)).chain.finish()])


@pytest.mark.parametrize("marginal", [None, 5])
def test_rts_through_core_copy_and_dense_transitions_equals_batch_posterior(marginal, monkeypatch):
    """A state of ``CORE_DIM + 21`` entries whose transitions are of each kind the smoother takes
    apart (the identity outside the leading ``CORE_DIM`` block, as propagation's; rows of the
    identity, as a window's augmentation; neither), in runs of one to three nodes between
    updates and over several blocks: the batch posterior, and the kinds as built."""
    from flowins.filter import smoother

    D = CORE_DIM + 21
    monkeypatch.setattr(smoother, "_BLOCK_BYTES", 5 * 8 * D * D)
    gen = torch.Generator().manual_seed(31)
    eye = torch.eye(D, dtype=F64)

    def core():
        A = eye.clone()
        A[:CORE_DIM, :CORE_DIM] += 0.1 * torch.randn(CORE_DIM, CORE_DIM, generator=gen, dtype=F64)
        return A

    def copy():  # the last 7 entries take the first 7; the 7 before them move up by one
        rows = list(range(D))
        rows[D - 7:] = range(7)
        rows[3:9] = range(4, 10)
        return eye[rows]

    def dense():
        return eye + 0.05 * torch.randn(D, D, generator=gen, dtype=F64)

    lc = LinearChain(torch.randn(D, generator=gen, dtype=F64), random_spd(gen, D))
    kinds = []
    for run in ((core,), (copy, core), (core, dense, copy), (dense,), (copy, copy, core), (core, core)):
        for make in run:
            A = make()
            # a copy's new entries are copies: give them no noise of their own, as augmentation does
            Q = random_spd(gen, D, scale=0.02) * (0.0 if make is copy else 1.0)
            lc.predict(A, Q + (1e-9 * eye if make is copy else 0.0))
            kinds.append({core: smoother._CORE, copy: smoother._COPY, dense: smoother._DENSE}[make])
        H = torch.randn(3, D, generator=gen, dtype=F64)
        lc.measure(H, torch.randn(3, generator=gen, dtype=F64), random_spd(gen, 3, scale=0.2))
    track = lc.chain.finish()
    assert smoother._transition_kinds(track.transition[1:])[0].tolist() == kinds
    got = rts_smooth(track, normalize=False, marginal=marginal)
    mean_true, cov_true, _, _ = lc.batch_posterior()
    c = D if marginal is None else marginal
    assert_close_scaled(got.node_mean, mean_true[:, :c], 1e-8)
    assert_close_scaled(got.node_cov, cov_true[:, :c, :c], 1e-8)
