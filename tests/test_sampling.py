"""Direct Bartlett (inverse-)Wishart draws and the numpy categorical draw of the label loop."""

import math

import numpy as np
import pytest
import torch

from dipole_torch.sampling import (
    bartlett_factor,
    broadcast_shape,
    draw_categorical,
    draw_categorical_numpy,
    inverse_wishart,
    wishart,
)

F64 = torch.float64


def spd(d, seed):
    a = torch.randn(d, d, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return a @ a.T + d * torch.eye(d, dtype=F64)


def assert_within(sample, expected, sigmas):
    """Every entry's sample mean within ``sigmas`` Monte-Carlo standard errors of ``expected``
    (standard errors from the sample itself, ``sample: [S, ...]``)."""
    error = sample.std(0) / math.sqrt(sample.shape[0])
    z = (sample.mean(0) - expected).abs() / error
    assert float(z.max()) < sigmas, z


@pytest.mark.parametrize("d, df", [(1, 4.5), (3, 9.0), (5, 12.5)])
def test_inverse_wishart_mean_and_variance(d, df):
    # E[Σ] = Ψ / (ν − p − 1); Var(Σ_ii) = 2 ψ_ii² / ((ν − p − 1)² (ν − p − 3)) (finite here:
    # ν > p + 3). 20 000 draws, 4.5 standard errors (a false alarm about 1 in 10^4 per entry).
    psi = spd(d, seed=d)
    draws = inverse_wishart(
        df, torch.linalg.cholesky(psi).expand(20000, d, d), torch.Generator().manual_seed(0)
    )
    assert draws.shape == (20000, d, d)
    assert torch.equal(draws, draws.transpose(-1, -2))
    assert bool((torch.linalg.eigvalsh(draws) > 0).all())
    assert_within(draws, psi / (df - d - 1), 4.5)
    variance = 2 * psi.diagonal() ** 2 / ((df - d - 1) ** 2 * (df - d - 3))
    diag = draws.diagonal(dim1=-2, dim2=-1)
    assert_within((diag - psi.diagonal() / (df - d - 1)) ** 2, variance, 4.5)


@pytest.mark.filterwarnings("ignore:Singular sample detected")  # torch's Wishart, see prior.py
def test_inverse_wishart_agrees_with_torch_wishart():
    # Σ⁻¹ ~ Wishart(ν, Ψ⁻¹): the precision's mean ν Ψ⁻¹, against torch.distributions' own
    # Wishart draws of it (both within 4.5 standard errors of the exact mean).
    d, df = 4, 8.0
    psi = spd(d, seed=7)
    precision = torch.linalg.inv(
        inverse_wishart(
            df, torch.linalg.cholesky(psi).expand(20000, d, d), torch.Generator().manual_seed(1)
        )
    )
    expected = df * torch.linalg.inv(psi)
    assert_within(precision, expected, 4.5)
    torch.manual_seed(2)
    reference = torch.distributions.Wishart(torch.tensor(df, dtype=F64), precision_matrix=psi)
    assert_within(reference.sample((20000,)), expected, 4.5)


def test_wishart_mean_and_variance():
    # E[W] = ν V, Var(W_ij) = ν (v_ij² + v_ii v_jj).
    d, df = 3, 6.5
    v = spd(d, seed=3)
    draws = wishart(
        df, torch.linalg.cholesky(v).expand(20000, d, d), torch.Generator().manual_seed(3)
    )
    assert_within(draws, df * v, 4.5)
    variance = df * (v**2 + v.diagonal()[:, None] * v.diagonal()[None, :])
    assert_within((draws - df * v) ** 2, variance, 4.5)


def test_batched_degrees_of_freedom_and_scales():
    # One draw per (df, Ψ) pair, each batch element with its own mean: the Σ step's shape.
    d = 2
    df = torch.tensor([5.0, 40.0], dtype=F64)
    psi = torch.stack((spd(d, 1), 10.0 * spd(d, 2)))
    tril = torch.linalg.cholesky(psi)
    draws = inverse_wishart(df.repeat(10000), tril.repeat(10000, 1, 1), torch.Generator())
    draws = draws.reshape(10000, 2, d, d)
    assert_within(draws, psi / (df - d - 1)[:, None, None], 4.5)


def test_bartlett_factor_is_lower_triangular_with_chi_diagonal():
    # A_ii² ~ χ²(ν − i): mean ν − i.
    df = torch.tensor(7.5, dtype=F64).expand(20000)
    a = bartlett_factor(df, 4, torch.Generator().manual_seed(4))
    assert torch.equal(a, a.tril())
    assert_within(a.diagonal(dim1=-2, dim2=-1) ** 2, 7.5 - torch.arange(4, dtype=F64), 4.5)


def test_draws_come_from_the_generator_alone():
    tril = torch.linalg.cholesky(spd(3, 0)).expand(5, 3, 3)
    torch.manual_seed(11)
    expected = torch.rand(2)
    torch.manual_seed(11)
    a = inverse_wishart(6.0, tril, torch.Generator().manual_seed(9))
    b = inverse_wishart(6.0, tril, torch.Generator().manual_seed(9))
    assert torch.equal(torch.rand(2), expected)  # global RNG untouched
    assert torch.equal(a, b)
    assert not torch.equal(a, inverse_wishart(6.0, tril, torch.Generator().manual_seed(10)))


def test_numpy_categorical_draw_matches_the_torch_one():
    # Same inverse-CDF search: same label for the same uniform, zero-probability slots never
    # picked at u = 0 or u → 1.
    g = torch.Generator().manual_seed(5)
    logits = 3.0 * torch.randn(2000, 7, generator=g, dtype=F64)
    logits[logits < -3.0] = -math.inf
    logits[:, 3] = 0.0  # at least one finite entry per row
    u = torch.rand(2000, generator=g, dtype=F64)
    labels = draw_categorical(logits, u)
    numpy_labels = [
        draw_categorical_numpy(row.numpy(), float(v)) for row, v in zip(logits, u, strict=True)
    ]
    assert labels.tolist() == numpy_labels
    inf = math.inf
    assert draw_categorical_numpy(np.array([-inf, 0.0, 0.0]), 0.0) == 1
    assert draw_categorical_numpy(np.array([0.0, 0.0, -inf, -inf]), 1.0 - 2.0**-53) == 1


def test_a_categorical_draw_skips_zero_probability_labels_at_both_ends_of_u():
    # u = 0 lands on the first possible label, not a leading impossible one; a u that
    # rounds to 1 in the logits' dtype (float32 here) on the last possible one, not a
    # trailing impossible one.
    inf = math.inf
    for dtype in (torch.float32, F64):
        logits = torch.tensor([[-inf, 0.0, 0.0, -inf]], dtype=dtype)
        assert draw_categorical(logits, torch.tensor([0.0], dtype=F64)).tolist() == [1]
        near_one = torch.tensor([1.0 - 2.0**-30], dtype=F64)
        assert draw_categorical(logits, near_one).tolist() == [2]


def test_numpy_categorical_draw_refuses_a_row_without_a_possible_label():
    """Every logit −inf (or NaN): a FloatingPointError that says so, not a label drawn from
    a CDF of NaN."""
    inf = math.inf
    for row in ([-inf, -inf, -inf], [math.nan, -inf]):
        with pytest.raises(FloatingPointError, match="every label has probability 0"):
            draw_categorical_numpy(np.array(row), 0.5)


@pytest.mark.parametrize(
    "shapes",
    [((2,), (3, 1), (1, 1, 1)), ((), (4,)), ((5, 1, 3), (4, 1)), ((0,), (1,)), ((2, 3),)],
)
def test_broadcast_shape_equals_torchs(shapes):
    assert broadcast_shape(*shapes) == tuple(torch.broadcast_shapes(*shapes))


def test_broadcast_shape_names_shapes_that_do_not_broadcast():
    with pytest.raises(ValueError, match=r"shapes \[2, 3\], \[4\] do not broadcast"):
        broadcast_shape((2, 3), (4,))
