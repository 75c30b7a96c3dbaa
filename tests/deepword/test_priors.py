"""The mixture fit, BIC selection, prior/posterior functions and their JSON round trip."""

import json

import numpy as np
import pytest

from deepword.priors import Mixture1D, PairPrior, Priors, fit_mixture_bic, load_priors, make_pair_prior


def _two_gaussians(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    k = rng.random(n) < 0.3
    return np.where(k, rng.normal(-1.0, 0.2, n), rng.normal(1.5, 0.3, n))


def test_fit_recovers_known_mixture_and_bic_picks_two():
    fit = fit_mixture_bic(_two_gaussians(), (1, 5), seed=0)
    m = fit.mixture
    assert len(m.weights) == 2
    order = np.argsort(m.means)
    np.testing.assert_allclose(np.array(m.means)[order], [-1.0, 1.5], atol=0.05)
    np.testing.assert_allclose(np.array(m.weights)[order], [0.3, 0.7], atol=0.03)
    np.testing.assert_allclose(np.sqrt(np.array(m.variances)[order]), [0.2, 0.3], atol=0.03)
    assert fit.bic[2] < fit.bic[1] and fit.bic[2] < fit.bic[3]


def test_bic_picks_one_for_a_single_gaussian():
    x = np.random.default_rng(1).normal(0.5, 0.4, 2000)
    assert len(fit_mixture_bic(x, (1, 4), seed=0).mixture.weights) == 1


def test_component_range_is_respected_and_validated():
    assert len(fit_mixture_bic(_two_gaussians(), (3, 3), seed=0).mixture.weights) == 3
    with pytest.raises(ValueError, match="components"):
        fit_mixture_bic(_two_gaussians(), (0, 2), seed=0)


def test_log_pdf_matches_a_single_normal():
    m = Mixture1D([1.0], [0.0], [4.0])
    assert m.pdf(np.array(0.0)) == pytest.approx(1 / np.sqrt(2 * np.pi * 4))
    assert m.max_density() == pytest.approx(1 / np.sqrt(2 * np.pi * 4), rel=1e-6)


def test_prior_in_unit_interval_and_monotone_in_likelihood():
    m = Mixture1D([0.4, 0.6], [0.0, 1.2], [0.05, 0.1])
    p = make_pair_prior("prior", m, None, 10, 0)
    ratio = np.exp(np.linspace(-4, 4, 2001))
    v = p(ratio)
    assert v.min() >= 0 and v.max() <= 1
    assert v.max() == pytest.approx(1.0, abs=1e-4)  # the mode reaches 1
    lik = m.pdf(np.log(ratio))
    order = np.argsort(lik)
    assert np.all(np.diff(v[order]) >= -1e-12)  # same order as the likelihood


def test_prior_accepts_any_shape_and_zero_ratio():
    p = make_pair_prior("prior", Mixture1D([1.0], [0.0], [1.0]), None, 1, 0)
    out = p(np.ones((2, 3, 4)))
    assert out.shape == (2, 3, 4) and np.allclose(out, 1.0)
    assert np.isfinite(p(np.array([0.0, -1.0]))).all()


def test_posterior_is_probability_of_pair():
    pair = Mixture1D([1.0], [0.0], [0.1])
    non = Mixture1D([1.0], [2.0], [0.5])
    p = make_pair_prior("posterior", pair, non, n_pairs=100, n_non_pairs=900)
    log_r = np.array([0.0, 2.0])
    a = 0.1 * pair.pdf(log_r)
    b = 0.9 * non.pdf(log_r)
    np.testing.assert_allclose(p(np.exp(log_r)), a / (a + b), rtol=1e-9)
    with pytest.raises(ValueError, match="posterior"):
        PairPrior("posterior", pair, 1.0)
    with pytest.raises(ValueError, match="mode"):
        PairPrior("likelihood", pair, 1.0)


@pytest.mark.parametrize("mode", ["prior", "posterior"])
def test_json_round_trip(tmp_path, mode):
    wv = make_pair_prior(mode, Mixture1D([0.3, 0.7], [0.1, 1.0], [0.2, 0.05]), Mixture1D([1.0], [2.0], [0.4]), 5, 50)
    ww = make_pair_prior(mode, Mixture1D([1.0], [1.3], [0.1]), Mixture1D([1.0], [2.5], [0.3]), 3, 90)
    Priors(wv, ww).save(tmp_path)
    obj = json.loads((tmp_path / "priors.json").read_text())  # plain JSON, no pickle
    assert obj["wheel_vehicle"]["mode"] == mode
    back = load_priors(tmp_path)
    r = np.exp(np.linspace(-2, 4, 50))
    np.testing.assert_allclose(back.wheel_vehicle(r), wv(r))
    np.testing.assert_allclose(back.wheel_wheel(r), ww(r))


def test_load_errors_are_clear(tmp_path):
    with pytest.raises(FileNotFoundError, match="priors file not found"):
        load_priors(tmp_path)
    (tmp_path / "priors.json").write_text("{}")
    with pytest.raises(ValueError, match="not a valid priors file"):
        load_priors(tmp_path)


def test_log_ratio_is_finite_for_coincident_centres():
    from deepword.priors import log_ratio

    out = log_ratio(np.array([0.0, 1.0, np.e]))
    assert np.isfinite(out).all() and out[1] == 0.0 and out[2] == pytest.approx(1.0)
    fit = fit_mixture_bic(np.concatenate([_two_gaussians(500), log_ratio(np.zeros(1))]), (1, 3), seed=0)
    assert np.isfinite(fit.log_likelihood)
