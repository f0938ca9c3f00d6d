"""EKF steps against the textbook Kalman filter written out here, and the χ² gate."""
import math

import pytest
import torch

from flowins.filter.ekf import (
    Gate,
    chi2_quantile,
    ekf_update,
    joseph_update,
    left_out_nis,
    linear_predict,
    scalar_update,
)

F64 = torch.float64


def random_spd(gen, n, scale=1.0, floor=0.1):
    A = torch.randn(n, n, generator=gen, dtype=F64)
    P = scale * (A @ A.T / n + floor * torch.eye(n, dtype=F64))
    return 0.5 * (P + P.T)


def textbook_update(m, P, z, H, R):
    """K = P Hᵀ (H P Hᵀ + R)⁻¹, m = m + K (z - H m), P = (I - K H) P (explicit inverse)."""
    S = H @ P @ H.T + R
    K = P @ H.T @ torch.linalg.inv(S)
    m_new = m + K @ (z - H @ m)
    P_new = (torch.eye(P.shape[0], dtype=F64) - K @ H) @ P
    return m_new, 0.5 * (P_new + P_new.T)


def block_diag(blocks):
    return torch.block_diag(*blocks)


# --------------------------------------------------------------------------- update


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_scalar_update_equals_the_textbook_update(batch):
    """The D x D form of the stacked scalar update against the M x M textbook one."""
    gen = torch.Generator().manual_seed(5)
    D, M = 7, 12
    P = torch.stack([random_spd(gen, D) for _ in range(max(1, math.prod(batch)))]).reshape(*batch, D, D)
    m = torch.randn(*batch, D, generator=gen, dtype=F64)
    H = torch.randn(*batch, M, D, generator=gen, dtype=F64)
    z = torch.randn(*batch, M, generator=gen, dtype=F64)
    r = 0.1 + torch.rand(*batch, M, generator=gen, dtype=F64)
    mean, cov, _ = scalar_update(m, P, z - (H @ m.unsqueeze(-1)).squeeze(-1), H, r)
    flat = lambda t, k: t.reshape(-1, *t.shape[len(batch):])  # noqa: E731
    for i in range(max(1, math.prod(batch))):
        mi, Pi = textbook_update(flat(m, 1)[i], flat(P, 2)[i], flat(z, 1)[i], flat(H, 2)[i], torch.diag(flat(r, 1)[i]))
        torch.testing.assert_close(flat(mean, 1)[i], mi, rtol=0, atol=1e-12)
        torch.testing.assert_close(flat(cov, 2)[i], Pi, rtol=0, atol=1e-12)


def test_scalar_update_with_a_singular_covariance_is_as_exact_as_joseph():
    """Right after the pose copy P is singular (p_prev = p), and a frame's points observe the
    state far better than the prior: against a 50-digit textbook update the D x D form is as
    accurate as the M x M Joseph form, and stays positive semi-definite."""
    import mpmath  # a dependency of torch (through sympy)
    gen = torch.Generator().manual_seed(6)
    D, M = 9, 30
    P = random_spd(gen, 6, scale=100.0)
    copy = torch.cat((torch.eye(6, dtype=F64), torch.eye(6, dtype=F64)[:3]))  # the last 3 repeat the first 3
    P = copy @ P @ copy.T  # (9, 9), rank 6
    H = torch.randn(M, D, generator=gen, dtype=F64) * 300.0
    v = torch.randn(M, generator=gen, dtype=F64)
    r = torch.full((M,), 0.25**2, dtype=F64)
    m = torch.zeros(D, dtype=F64)
    with mpmath.workdps(50):
        Pm, Hm, vm = mpmath.matrix(P.tolist()), mpmath.matrix(H.tolist()), mpmath.matrix(v.tolist())
        K = Pm * Hm.T * (Hm * Pm * Hm.T + mpmath.diag([mpmath.mpf(0.25) ** 2] * M)) ** -1
        exact_mean = torch.tensor([float(e) for e in K * vm], dtype=F64)
        Pp = (mpmath.eye(D) - K * Hm) * Pm
        exact_cov = torch.tensor([[float(Pp[i, j]) for j in range(D)] for i in range(D)], dtype=F64)
    mean, cov, failed = scalar_update(m, P, v, H, r)
    assert not bool(failed)
    mean_j, cov_j, _ = joseph_update(m, P, v, H, torch.diag(r))
    err, err_j = float((mean - exact_mean).abs().max()), float((mean_j - exact_mean).abs().max())
    assert err <= 2.0 * err_j + 1e-12 and err < 1e-8  # the mean is ~1e-3: the problem's own conditioning
    assert float((cov - exact_cov).abs().max()) <= 10.0 * float((cov_j - exact_cov).abs().max()) + 1e-15
    assert float(torch.linalg.eigvalsh(cov).min()) > -1e-12 * float(exact_cov.abs().max())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_joseph_update_equals_textbook(seed):
    gen = torch.Generator().manual_seed(seed)
    D, n = 5, 3
    m = torch.randn(D, generator=gen, dtype=F64)
    P = random_spd(gen, D)
    H = torch.randn(n, D, generator=gen, dtype=F64)
    R = random_spd(gen, n, scale=0.3)
    z = torch.randn(n, generator=gen, dtype=F64)
    expected_m, expected_P = textbook_update(m, P, z, H, R)
    got_m, got_P, _ = joseph_update(m, P, z - H @ m, H, R)
    torch.testing.assert_close(got_m, expected_m, rtol=0, atol=1e-10)
    torch.testing.assert_close(got_P, expected_P, rtol=0, atol=1e-10)


@pytest.mark.parametrize("seed", [0, 1])
def test_ekf_update_blocks_equal_textbook_stacked(seed):
    gen = torch.Generator().manual_seed(seed)
    D, M, d = 5, 3, 2
    m = torch.randn(D, generator=gen, dtype=F64)
    P = random_spd(gen, D)
    H = torch.randn(M, d, D, generator=gen, dtype=F64)
    R = torch.stack([random_spd(gen, d, scale=0.5) for _ in range(M)])
    z = torch.randn(M, d, generator=gen, dtype=F64)
    innovation = z - (H @ m)
    result = ekf_update(m, P, innovation=innovation, H=H, noise_cov=R)
    expected_m, expected_P = textbook_update(m, P, z.reshape(-1), H.reshape(M * d, D), block_diag(R))
    torch.testing.assert_close(result.mean, expected_m, rtol=0, atol=1e-10)
    torch.testing.assert_close(result.cov, expected_P, rtol=0, atol=1e-10)
    # NIS of each block against its own innovation covariance
    for i in range(M):
        S_i = H[i] @ P @ H[i].T + R[i]
        nis_i = innovation[i] @ torch.linalg.inv(S_i) @ innovation[i]
        assert abs(float(result.nis[i]) - float(nis_i)) <= 1e-10 * max(1.0, float(nis_i))
    assert torch.equal(result.weight, torch.ones(M, dtype=F64))


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_ekf_update_batches_like_a_loop(batch):
    gen = torch.Generator().manual_seed(7)
    D, M, d = 4, 2, 3
    n = math.prod(batch)
    m = torch.randn(n, D, generator=gen, dtype=F64)
    P = torch.stack([random_spd(gen, D) for _ in range(n)])
    H = torch.randn(n, M, d, D, generator=gen, dtype=F64)
    R = torch.stack([torch.stack([random_spd(gen, d) for _ in range(M)]) for _ in range(n)])
    v = torch.randn(n, M, d, generator=gen, dtype=F64)
    out = ekf_update(
        m.reshape(*batch, D),
        P.reshape(*batch, D, D),
        innovation=v.reshape(*batch, M, d),
        H=H.reshape(*batch, M, d, D),
        noise_cov=R.reshape(*batch, M, d, d),
    )
    assert out.mean.shape == (*batch, D) and out.cov.shape == (*batch, D, D) and out.nis.shape == (*batch, M)
    for i in range(n):
        z = v[i].reshape(-1) + H[i].reshape(M * d, D) @ m[i]
        em, eP = textbook_update(m[i], P[i], z, H[i].reshape(M * d, D), block_diag(R[i]))
        torch.testing.assert_close(out.mean.reshape(n, D)[i], em, rtol=0, atol=1e-10)
        torch.testing.assert_close(out.cov.reshape(n, D, D)[i], eP, rtol=0, atol=1e-10)


def test_ekf_update_rejects_mismatched_shapes():
    m, P = torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
    with pytest.raises(ValueError, match="innovation"):
        ekf_update(m, P, innovation=torch.zeros(3, dtype=F64), H=torch.zeros(3, 4, dtype=F64), noise_cov=torch.eye(3, dtype=F64))
    with pytest.raises(ValueError, match="innovation"):
        ekf_update(
            m,
            P,
            innovation=torch.zeros(1, 3, dtype=F64),
            H=torch.zeros(1, 2, 4, dtype=F64),
            noise_cov=torch.eye(3, dtype=F64).reshape(1, 3, 3),
        )


# --------------------------------------------------------------------------- full linear KF


@pytest.mark.parametrize("seed,D", [(0, 4), (1, 5), (2, 6)])
def test_linear_system_matches_closed_form_kalman_filter(seed, D):
    gen = torch.Generator().manual_seed(seed)
    M, d, steps = 2, 2, 30
    A = torch.eye(D, dtype=F64) + 0.15 * torch.randn(D, D, generator=gen, dtype=F64)
    Q = random_spd(gen, D, scale=0.05)
    H = torch.randn(M, d, D, generator=gen, dtype=F64)
    R = torch.stack([random_spd(gen, d, scale=0.2) for _ in range(M)])
    H_flat, R_flat = H.reshape(M * d, D), block_diag(R)

    # simulate a trajectory and its measurements
    x = torch.randn(D, generator=gen, dtype=F64)
    L_Q, L_R = torch.linalg.cholesky(Q), torch.linalg.cholesky(R_flat)
    zs = []
    for _ in range(steps):
        x = A @ x + L_Q @ torch.randn(D, generator=gen, dtype=F64)
        zs.append(H_flat @ x + L_R @ torch.randn(M * d, generator=gen, dtype=F64))

    m0 = torch.zeros(D, dtype=F64)
    P0 = 2.0 * torch.eye(D, dtype=F64)
    m_ref, P_ref = m0.clone(), P0.clone()
    m, P = m0.clone(), P0.clone()
    gate = Gate(mode="off")
    for k, z in enumerate(zs):
        # independent closed form
        m_ref = A @ m_ref
        P_ref = A @ P_ref @ A.T + Q
        if k % 4 != 3:  # some steps without a measurement
            m_ref, P_ref = textbook_update(m_ref, P_ref, z, H_flat, R_flat)
        # flowins
        m, P = linear_predict(m, P, A, Q)
        if k % 4 != 3:
            innovation = (z - H_flat @ m).reshape(M, d)
            out = ekf_update(m, P, innovation=innovation, H=H, noise_cov=R, gate=gate)
            m, P = out.mean, out.cov
        torch.testing.assert_close(m, m_ref, rtol=0, atol=1e-9)
        torch.testing.assert_close(P, P_ref, rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1])
def test_sequential_update_equals_stacked(seed):
    gen = torch.Generator().manual_seed(seed)
    D, M, d = 6, 5, 2
    m = torch.randn(D, generator=gen, dtype=F64)
    P = random_spd(gen, D)
    H = torch.randn(M, d, D, generator=gen, dtype=F64)
    R = torch.stack([random_spd(gen, d, scale=0.5) for _ in range(M)])
    z = torch.randn(M, d, generator=gen, dtype=F64)
    innovation = z - H @ m
    stacked = ekf_update(m, P, innovation=innovation, H=H, noise_cov=R)
    sequential = ekf_update(m, P, innovation=innovation, H=H, noise_cov=R, sequential=True)
    assert torch.equal(sequential.weight, torch.ones(M, dtype=F64))
    torch.testing.assert_close(sequential.cov, stacked.cov, rtol=0, atol=1e-9)
    torch.testing.assert_close(sequential.mean, stacked.mean, rtol=0, atol=1e-9)


def test_sequential_update_covariance_equals_stacked():
    """The sequential covariance equals the textbook stacked update."""
    gen = torch.Generator().manual_seed(3)
    D, M, d = 6, 5, 2
    m = torch.randn(D, generator=gen, dtype=F64)
    P = random_spd(gen, D)
    H = torch.randn(M, d, D, generator=gen, dtype=F64)
    R = torch.stack([random_spd(gen, d, scale=0.5) for _ in range(M)])
    v = torch.randn(M, d, generator=gen, dtype=F64)
    _, expected_P = textbook_update(m, P, v.reshape(-1) + H.reshape(M * d, D) @ m, H.reshape(M * d, D), block_diag(R))
    sequential = ekf_update(m, P, innovation=v, H=H, noise_cov=R, sequential=True)
    torch.testing.assert_close(sequential.cov, expected_P, rtol=0, atol=1e-9)


# --------------------------------------------------------------------------- chi2


@pytest.mark.parametrize(
    "probability,dof,expected",
    [
        (0.95, 1, 3.841458820694124),
        (0.99, 2, 9.210340371976182),
        (0.999, 3, 16.26623619623813),
        (0.95, 3, 7.814727903251179),
        (0.99, 10, 23.209251158954356),
    ],
)
def test_chi2_quantile_table_values(probability, dof, expected):
    assert abs(chi2_quantile(probability, dof) - expected) <= 1e-8


@pytest.mark.parametrize("probability", [0.5, 0.9, 0.999, 0.999999])
def test_chi2_quantile_closed_forms(probability):
    # dof 2 is the exponential distribution: x = -2 ln(1 - p)
    assert abs(chi2_quantile(probability, 2) - (-2.0 * math.log1p(-probability))) <= 1e-8 * max(1.0, -2 * math.log1p(-probability))
    # dof 1 is a squared standard normal: x = Φ⁻¹((1 + p) / 2)²
    z = float(torch.special.ndtri(torch.tensor((1.0 + probability) / 2.0, dtype=F64)))
    assert abs(chi2_quantile(probability, 1) - z * z) <= 1e-8 * max(1.0, z * z)


@pytest.mark.parametrize("probability,dof", [(0.0, 2), (1.0, 2), (1.5, 2), (-0.1, 2), (0.9, 0), (0.9, -3)])
def test_chi2_quantile_rejects_bad_arguments(probability, dof):
    with pytest.raises(ValueError):
        chi2_quantile(probability, dof)


# --------------------------------------------------------------------------- gate


def test_gate_rejects_bad_configuration():
    with pytest.raises(ValueError, match="mode"):
        Gate(mode="maybe")
    with pytest.raises(ValueError, match="probability"):
        Gate(probability=1.0)


def test_hard_gate_weights_around_threshold():
    dof = 3
    thr = 16.26623619623813  # χ²_3(0.999)
    gate = Gate(mode="hard", probability=0.999)
    nis = torch.tensor([0.0, thr - 1e-6, thr + 1e-6, 1e3], dtype=F64)
    assert torch.equal(gate.weights(nis, dof), torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=F64))
    explicit = Gate(mode="hard", threshold=2.0)
    assert torch.equal(explicit.weights(torch.tensor([1.999, 2.001], dtype=F64), dof), torch.tensor([1.0, 0.0], dtype=F64))


def test_soft_gate_is_the_sigmoid_formula():
    gate = Gate(mode="soft", threshold=5.0, softness=0.7)
    nis = torch.linspace(0.0, 12.0, 25, dtype=F64)
    expected = 1.0 / (1.0 + torch.exp(-(5.0 - nis) / 0.7))
    torch.testing.assert_close(gate.weights(nis, 2), expected, rtol=0, atol=1e-14)
    # threshold from the probability when none is given
    gate_p = Gate(mode="soft", probability=0.95, softness=2.0)
    thr = 3.841458820694124
    torch.testing.assert_close(gate_p.weights(nis, 1), 1.0 / (1.0 + torch.exp(-(thr - nis) / 2.0)), rtol=0, atol=1e-9)


def _gate_problem(seed=11, D=4, M=3, d=2, offset=0.0):
    gen = torch.Generator().manual_seed(seed)
    m = torch.randn(D, generator=gen, dtype=F64)
    P = random_spd(gen, D)
    H = torch.randn(M, d, D, generator=gen, dtype=F64)
    R = torch.stack([random_spd(gen, d, scale=0.3) for _ in range(M)])
    v = torch.randn(M, d, generator=gen, dtype=F64)
    v[0] += offset
    return m, P, H, R, v


def test_off_gate_accepts_everything():
    m, P, H, R, v = _gate_problem(offset=1e4)  # an absurd outlier in block 0
    out = ekf_update(m, P, innovation=v, H=H, noise_cov=R, gate=Gate(mode="off"))
    assert float(out.nis[0]) > 1e6
    assert torch.equal(out.weight, torch.ones(3, dtype=F64))
    M, d, D = H.shape
    em, eP = textbook_update(m, P, v.reshape(-1) + H.reshape(M * d, D) @ m, H.reshape(M * d, D), block_diag(R))
    torch.testing.assert_close(out.mean, em, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out.cov, eP, rtol=0, atol=1e-10)


def test_rejected_blocks_leave_the_gaussian_unchanged_exactly():
    m, P, H, R, v = _gate_problem(offset=1e4)
    v = v * 1e3  # every block is an outlier
    out = ekf_update(m, P, innovation=v, H=H, noise_cov=R, gate=Gate(mode="hard"))
    assert torch.equal(out.weight, torch.zeros(3, dtype=F64))
    assert torch.equal(out.mean, m)
    assert torch.equal(out.cov, P)


def test_hard_gate_drops_only_the_outlier_block():
    m, P, H, R, v = _gate_problem(offset=1e3)
    out = ekf_update(m, P, innovation=v, H=H, noise_cov=R, gate=Gate(mode="hard", probability=0.999))
    assert torch.equal(out.weight, torch.tensor([0.0, 1.0, 1.0], dtype=F64))
    # equals the textbook update with blocks 1 and 2 only
    Hk, Rk = H[1:].reshape(-1, H.shape[-1]), block_diag(R[1:])
    em, eP = textbook_update(m, P, v[1:].reshape(-1) + Hk @ m, Hk, Rk)
    torch.testing.assert_close(out.mean, em, rtol=0, atol=1e-10)
    torch.testing.assert_close(out.cov, eP, rtol=0, atol=1e-10)


def test_weight_w_equals_noise_divided_by_w_squared():
    m, P, H, R, v = _gate_problem(offset=2.0)
    gate = Gate(mode="soft", threshold=3.0, softness=1.5)
    out = ekf_update(m, P, innovation=v, H=H, noise_cov=R, gate=gate)
    w = out.weight
    assert ((w > 0.01) & (w < 0.99)).all(), w  # genuinely fractional weights
    # NIS does not depend on the gate
    S = H @ P @ H.transpose(-1, -2) + R
    nis = torch.stack([v[i] @ torch.linalg.inv(S[i]) @ v[i] for i in range(3)])
    torch.testing.assert_close(out.nis, nis, rtol=1e-12, atol=0)
    torch.testing.assert_close(w, torch.sigmoid((3.0 - nis) / 1.5), rtol=1e-12, atol=0)
    M, d, D = H.shape
    Hk = H.reshape(M * d, D)
    em, eP = textbook_update(m, P, v.reshape(-1) + Hk @ m, Hk, block_diag([R[i] / w[i] ** 2 for i in range(M)]))
    torch.testing.assert_close(out.mean, em, rtol=0, atol=1e-10)
    torch.testing.assert_close(out.cov, eP, rtol=0, atol=1e-10)


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_left_out_nis_is_each_measurement_against_the_update_without_it(batch):
    """``left_out_nis`` from the posterior of all against the naive reference: for each
    measurement the textbook update of the others (each with its noise ``r / w²``, the
    ``w = 0`` ones left out), its residual there and that residual's predicted variance."""
    gen = torch.Generator().manual_seed(3)
    D, M = 6, 9
    n = max(1, math.prod(batch))
    P = torch.stack([random_spd(gen, D) for _ in range(n)]).reshape(*batch, D, D)
    m = torch.randn(*batch, D, generator=gen, dtype=F64)
    H = torch.randn(*batch, M, D, generator=gen, dtype=F64)
    v = 3.0 * torch.randn(*batch, M, generator=gen, dtype=F64)
    r = 0.05 + torch.rand(*batch, M, generator=gen, dtype=F64)
    w = torch.rand(*batch, M, generator=gen, dtype=F64)
    w[..., 0], w[..., 1] = 0.0, 1.0  # one left out of the update, one in it at full weight
    mean, cov, _ = scalar_update(m, P, w * v, w.unsqueeze(-1) * H, r)
    got = left_out_nis(v, H, r, w, m, mean, cov)
    flat = lambda t, k: t.reshape(-1, *t.shape[t.ndim - k:])  # noqa: E731
    Pf, mf, Hf, vf, rf, wf = flat(P, 2), flat(m, 1), flat(H, 2), flat(v, 1), flat(r, 1), flat(w, 1)
    want = torch.empty(n, M, dtype=F64)
    for b in range(n):
        for i in range(M):
            others = [j for j in range(M) if j != i and wf[b, j] > 0]
            Ho = Hf[b, others]
            mo, Po = textbook_update(mf[b], Pf[b], vf[b, others] + Ho @ mf[b], Ho,
                                     torch.diag(rf[b, others] / wf[b, others] ** 2))
            e = vf[b, i] - Hf[b, i] @ (mo - mf[b])
            want[b, i] = e**2 / (Hf[b, i] @ Po @ Hf[b, i] + rf[b, i])
    torch.testing.assert_close(got.reshape(n, M), want, rtol=1e-9, atol=0)
    # under the model it is chi-square with one degree of freedom, not the prior's NIS
    prior = v**2 / (torch.linalg.vecdot(H @ P, H) + r)
    assert not torch.allclose(got, prior, rtol=1e-3)


def test_soft_gate_is_differentiable_in_threshold_and_softness():
    m, P, H, R, v = _gate_problem(offset=2.0)
    threshold = torch.tensor(3.0, dtype=F64, requires_grad=True)
    softness = torch.tensor(1.5, dtype=F64, requires_grad=True)
    direction = torch.linspace(-1.0, 1.0, m.shape[0], dtype=F64)

    def objective(thr, soft):
        gate = Gate(mode="soft", threshold=thr, softness=soft)
        out = ekf_update(m, P, innovation=v, H=H, noise_cov=R, gate=gate)
        return (out.mean * direction).sum() + out.cov.trace()

    g_thr, g_soft = torch.autograd.grad(objective(threshold, softness), (threshold, softness))
    assert torch.isfinite(g_thr) and torch.isfinite(g_soft)
    assert abs(float(g_thr)) > 1e-6 and abs(float(g_soft)) > 1e-6
    h = 1e-6
    with torch.no_grad():
        fd_thr = (objective(threshold + h, softness) - objective(threshold - h, softness)) / (2 * h)
        fd_soft = (objective(threshold, softness + h) - objective(threshold, softness - h)) / (2 * h)
    assert abs(float(g_thr) - float(fd_thr)) <= 1e-6 * max(1.0, abs(float(fd_thr)))
    assert abs(float(g_soft) - float(fd_soft)) <= 1e-6 * max(1.0, abs(float(fd_soft)))


def test_the_update_knows_no_state_layout_and_the_caller_hooks_its_constraint():
    from flowins.state import STATE, STATE_DIM, normalize_quaternions

    gen = torch.Generator().manual_seed(3)
    m = torch.randn(STATE_DIM, generator=gen, dtype=F64)
    P = torch.eye(STATE_DIM, dtype=F64)
    H = torch.zeros(1, 3, STATE_DIM, dtype=F64)
    H[0, :, STATE.p] = torch.eye(3, dtype=F64)
    kwargs = dict(innovation=torch.ones(1, 3, dtype=F64), H=H, noise_cov=torch.eye(3, dtype=F64).reshape(1, 3, 3))
    plain = ekf_update(m, P, **kwargs)
    hooked = ekf_update(m, P, **kwargs, normalize=normalize_quaternions)
    # the position moves half way (P = R = I); the quaternion is untouched without the hook ...
    torch.testing.assert_close(plain.mean[STATE.p], m[STATE.p] + 0.5)
    torch.testing.assert_close(plain.mean[STATE.q], m[STATE.q])
    # ... and unit with it, the rest identical
    torch.testing.assert_close(hooked.mean[STATE.q], m[STATE.q] / m[STATE.q].norm())
    torch.testing.assert_close(hooked.mean[STATE.p], plain.mean[STATE.p])
    # any state size: a 2-dim state has no quaternion to touch
    small = ekf_update(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), innovation=torch.ones(1, 1, dtype=F64),
                       H=torch.tensor([[[1.0, 0.0]]], dtype=F64), noise_cov=torch.ones(1, 1, 1, dtype=F64))
    torch.testing.assert_close(small.mean, torch.tensor([0.5, 0.0], dtype=F64))


# --------------------------------------------------------------------------- innovation likelihood


def joint_measurement_nll(A, Q, m0, P0, H_flat, R_flat, zs, measured):
    """-log p(z_1, ..., z_K) of the linear system written out as one Gaussian: every measured
    z_k = H x_k + v_k with x_k = A^k x_0 + Σ A^(k-j) w_j, built from the stacked covariances."""
    D, n = A.shape[0], H_flat.shape[0]
    steps = [k for k in range(len(zs)) if measured(k)]
    # x_k = Φ_k x_0 + Σ_{j<=k} Ψ_{k,j} w_j
    phis, psis = [], []
    phi = torch.eye(D, dtype=F64)
    for k in range(len(zs)):
        phi = A @ phi
        phis.append(phi)
        psis.append([torch.linalg.matrix_power(A, k - j) for j in range(k + 1)])
    mean = torch.cat([H_flat @ phis[k] @ m0 for k in steps])
    blocks = []
    for k in steps:
        row = []
        for l in steps:
            c = H_flat @ phis[k] @ P0 @ phis[l].T @ H_flat.T
            for j in range(min(k, l) + 1):
                c = c + H_flat @ psis[k][j] @ Q @ psis[l][j].T @ H_flat.T
            if k == l:
                c = c + R_flat
            row.append(c)
        blocks.append(torch.cat(row, 1))
    cov = torch.cat(blocks, 0)
    z = torch.cat([zs[k] for k in steps])
    return -torch.distributions.MultivariateNormal(mean, covariance_matrix=cov).log_prob(z), len(steps) * n


@pytest.mark.parametrize("seed,d,sequential", [(0, 2, False), (1, 1, False), (2, 1, True), (3, 3, True)])
def test_summed_innovation_nll_is_the_joint_likelihood_of_the_linear_system(seed, d, sequential):
    """The prediction-error decomposition: the updates' ½ (NIS + log det S), plus ½ n log 2π,
    summed over a run equals -log p(all measurements) of the system as one Gaussian (one
    block per update; several blocks only with the sequential update)."""
    gen = torch.Generator().manual_seed(seed)
    D, steps = 4, 8
    M = 3 if sequential else 1
    A = torch.eye(D, dtype=F64) + 0.2 * torch.randn(D, D, generator=gen, dtype=F64)
    Q = random_spd(gen, D, scale=0.05)
    H = torch.randn(M, d, D, generator=gen, dtype=F64)
    R = torch.stack([random_spd(gen, d, scale=0.3) for _ in range(M)])
    H_flat, R_flat = H.reshape(M * d, D), block_diag(R)
    m0, P0 = torch.randn(D, generator=gen, dtype=F64), random_spd(gen, D)
    zs = [torch.randn(M * d, generator=gen, dtype=F64) for _ in range(steps)]

    def measured(k):
        return k % 3 != 1

    m, P, total = m0, P0, torch.zeros((), dtype=F64)
    for k, z in enumerate(zs):
        m, P = linear_predict(m, P, A, Q)
        if measured(k):
            out = ekf_update(m, P, innovation=(z - H_flat @ m).reshape(M, d), H=H, noise_cov=R,
                             sequential=sequential, likelihood=True)
            assert out.nll.shape == (M,)
            total = total + out.nll.sum()
            m, P = out.mean, out.cov
    expected, n = joint_measurement_nll(A, Q, m0, P0, H_flat, R_flat, zs, measured)
    torch.testing.assert_close(total + 0.5 * n * math.log(2 * math.pi), expected, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("d", [1, 3])
def test_each_block_nll_is_its_marginal_gaussian_density(d):
    """A stacked update's ``nll`` is, block by block, -log N(v_i; 0, H_i P H_iᵀ + R_i) without
    the constant, and the NIS and the update are the ones without the likelihood."""
    gen = torch.Generator().manual_seed(7)
    D, M = 6, 4
    m, P = torch.randn(2, D, generator=gen, dtype=F64), torch.stack([random_spd(gen, D), random_spd(gen, D)])
    H = torch.randn(2, M, d, D, generator=gen, dtype=F64)
    R = torch.stack([torch.stack([random_spd(gen, d, scale=0.5) for _ in range(M)]) for _ in range(2)])
    v = torch.randn(2, M, d, generator=gen, dtype=F64)
    gate = Gate(mode="soft", threshold=3.0, softness=0.5)
    out = ekf_update(m, P, innovation=v, H=H, noise_cov=R, gate=gate, likelihood=True)
    plain = ekf_update(m, P, innovation=v, H=H, noise_cov=R, gate=gate)
    assert plain.nll is None
    torch.testing.assert_close(out.nis, plain.nis, rtol=1e-12, atol=0)
    assert torch.equal(out.mean, plain.mean) and torch.equal(out.cov, plain.cov)
    for b in range(2):
        for i in range(M):
            S = H[b, i] @ P[b] @ H[b, i].T + R[b, i]
            density = torch.distributions.MultivariateNormal(torch.zeros(d, dtype=F64), covariance_matrix=S)
            expected = -density.log_prob(v[b, i]) - 0.5 * d * math.log(2 * math.pi)
            torch.testing.assert_close(out.nll[b, i], expected, rtol=1e-11, atol=1e-12)


def test_block_nis_and_information_broadcast_over_batch_dimensions_H_lacks():
    """One set of blocks ``H (M, d, D)`` against a batch of covariances ``(B, D, D)`` (and noise
    with a batch of its own): each batch entry's NIS and information equal the entry alone."""
    from flowins.filter.ekf import block_information, block_nis

    gen = torch.Generator().manual_seed(3)
    B, M, d, D = 3, 4, 2, 5
    P = torch.stack([random_spd(gen, D) for _ in range(B)])
    H = torch.randn(M, d, D, generator=gen, dtype=F64)
    R = torch.stack([torch.stack([random_spd(gen, d, scale=0.5) for _ in range(M)]) for _ in range(B)])
    v = torch.randn(M, d, generator=gen, dtype=F64)
    nis = block_nis(P, v, H, R)
    G, b = block_information(v, H, R)
    assert nis.shape == (B, M) and G.shape == (B, D, D) and b.shape == (B, D)
    for i in range(B):
        S = H @ P[i] @ H.transpose(-1, -2) + R[i]
        want = torch.stack([v[m] @ torch.linalg.solve(S[m], v[m]) for m in range(M)])
        torch.testing.assert_close(nis[i], want, rtol=1e-12, atol=0)
        Rinv = torch.linalg.inv(R[i])
        torch.testing.assert_close(G[i], sum(H[m].T @ Rinv[m] @ H[m] for m in range(M)), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(b[i], sum(H[m].T @ Rinv[m] @ v[m] for m in range(M)), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("M, d, sequential", [(3, 1, False), (2, 2, False), (6, 3, False), (3, 2, True)])
def test_whitened_blocks_give_the_textbook_update_and_its_likelihood(M, d, sequential):
    """Blocks handed whitened (``L⁻¹ v``, ``L⁻¹ H``, ``noise_cov`` None, ``R = L Lᵀ``) with
    ``½ log det R`` give the update, NIS and likelihood of the textbook filter with ``R`` (every
    branch: scalars, the Joseph form, the information form for M d > D, one block at a time)."""
    gen = torch.Generator().manual_seed(7 * M + d)
    D = 5
    m = torch.randn(D, generator=gen, dtype=F64)
    P = random_spd(gen, D)
    H = torch.randn(M, d, D, generator=gen, dtype=F64)
    R = torch.stack([random_spd(gen, d, scale=0.5) for _ in range(M)])
    innovation = torch.randn(M, d, generator=gen, dtype=F64)
    L = torch.linalg.cholesky(R)
    white_v = torch.linalg.solve_triangular(L, innovation.unsqueeze(-1), upper=False).squeeze(-1)
    white_H = torch.linalg.solve_triangular(L, H, upper=False)
    half_logdet = torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
    result = ekf_update(m, P, innovation=white_v, H=white_H, noise_cov=None, noise_logdet=half_logdet,
                        likelihood=True, sequential=sequential)
    expected_m, expected_P = textbook_update(m, P, (innovation + H @ m).reshape(-1), H.reshape(M * d, D),
                                             block_diag(R))
    torch.testing.assert_close(result.mean, expected_m, rtol=0, atol=1e-10)
    torch.testing.assert_close(result.cov, expected_P, rtol=0, atol=1e-10)
    if sequential:  # each block against the covariance the blocks before it left: as with R itself
        plain = ekf_update(m, P, innovation=innovation, H=H, noise_cov=R, likelihood=True, sequential=True)
        torch.testing.assert_close(result.nis, plain.nis, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(result.nll, plain.nll, rtol=1e-10, atol=1e-12)
        return
    for i in range(M):
        S_i = H[i] @ P @ H[i].T + R[i]
        nis_i = innovation[i] @ torch.linalg.inv(S_i) @ innovation[i]
        torch.testing.assert_close(result.nis[i], nis_i, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(result.nll[i], 0.5 * (nis_i + torch.logdet(S_i)), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("d, M", [(1, 12), (2, 3), (3, 8)])
def test_a_gated_update_is_one_graph_equal_to_eager(d, M):
    """Scalar blocks (D x D algebra), a few stacked blocks (Joseph form) and many blocks
    (information form) under ``torch.compile(fullgraph=True)`` with a backend that needs no
    compiler: no graph break (no read-back of a flag, no data-dependent branch), the jitter
    ladder as one batched call, the same posterior as eager; a singular prior included."""
    gen = torch.Generator().manual_seed(d * 10 + M)
    D = 9
    P = random_spd(gen, D, scale=4.0).expand(2, D, D).clone()
    copy = torch.cat((torch.eye(6, dtype=F64), torch.eye(6, dtype=F64)[:3]))
    P[1] = copy @ random_spd(gen, 6, scale=4.0) @ copy.T  # rank 6: the first jitter fails
    mean = torch.randn(2, D, generator=gen, dtype=F64)
    H = torch.randn(2, M, d, D, generator=gen, dtype=F64)
    v = torch.randn(2, M, d, generator=gen, dtype=F64)
    R = 0.5 * torch.eye(d, dtype=F64).expand(2, M, d, d)
    gate = Gate(mode="hard", probability=0.99)

    def step(mean, cov, v, H, R):
        return ekf_update(mean, cov, innovation=v, H=H, noise_cov=R, gate=gate)

    torch._dynamo.reset()
    compiled = torch.compile(step, fullgraph=True, backend="eager")
    got, want = compiled(mean, P, v, H, R), step(mean, P, v, H, R)
    assert got.failed.tolist() == want.failed.tolist() == [False, False]
    for a, b in zip(got[:4], want[:4]):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)
