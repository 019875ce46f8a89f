"""auto's half-budget estimate with correlated halves and its mosaic of
tiles: closed forms on synthetic noise and invariants of the layout."""
import numpy as np

from core import auto
from core.filters import box_mean
from core.metrics import REL_EPS


def _correlated_subsets(truth, rho, sigma, seed):
    """Four 1-sample subsets; subset 0 with 1 and 2 with 3 share noise with
    correlation ``rho`` (halves A = 0, 2 and B = 1, 3 then correlate by
    ``rho``), as the samples of one stratified sequence do."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        z1 = rng.standard_normal(truth.shape)
        z2 = rho * z1 + np.sqrt(1 - rho * rho) * rng.standard_normal(truth.shape)
        out += [truth + sigma * z1, truth + sigma * z2]
    return [(c, {}, 1) for c in out]  # A: subsets 0, 2; B: 1, 3


def test_halves_correlation_closed_form():
    assert auto.halves_correlation(1.0) == 0.0
    # Var((A + B) / 2) = Var(A) (1 + r) / 2 must equal Var(A) 2^-e
    for e in (0.8, 1.2, 1.5):
        r = auto.halves_correlation(e)
        assert np.isclose((1 + r) / 2, 2.0 ** -e)
    assert -0.9 <= auto.halves_correlation(50.0) and auto.halves_correlation(float("nan")) == 0.0


def test_mean_estimate_is_unbiased_with_correlated_halves():
    """The sample mean's half-budget relMSE with the exponent that the
    correlation implies matches the closed form Var(A) w = sigma^2 / 2 w
    within 3 %; ignoring the correlation (exponent 1) is off by (1 - r)."""
    truth = np.full((64, 64, 3), 0.5)
    rho, sigma = -0.3, 0.05
    e = 1.0 - np.log2(1.0 + rho)
    crop = (0, 0, 64, 64)
    est, naive = [], []
    for seed in range(4):
        subs = _correlated_subsets(truth, rho, sigma, seed)
        est.append(auto.mean_terms(subs, crop, 64, 64, e).mean())
        naive.append(auto.mean_terms(subs, crop, 64, 64, 1.0).mean())
    w = 1.0 / (0.5 ** 2 + REL_EPS)
    true = w * sigma ** 2 / 2.0
    assert abs(np.mean(est) / true - 1.0) < 0.03
    assert abs(np.mean(naive) / true - (1.0 - rho)) < 0.03


def test_control_variate_is_unbiased_for_an_exact_reconstruction_with_correlated_halves():
    """A reconstruction that returns the truth has relMSE 0; with
    correlated halves its estimate stays within a few standard errors of 0
    (the product of the halves' residuals carries the same correlation as
    their squared difference)."""
    truth = np.full((48, 48, 3), 0.4)
    rho, sigma = -0.25, 0.05
    e = 1.0 - np.log2(1.0 + rho)
    subs = _correlated_subsets(truth, rho, sigma, 3)
    halves = auto._halves(subs, [])
    ca, cb = halves[0].color.mean, halves[1].color.mean
    whole = sum(s[0] for s in subs) / 4.0
    w = 1.0 / (box_mean(whole, 1) ** 2 + REL_EPS)
    # the estimator's terms for R = truth, written out as score_tile forms them
    d = w * ((truth - cb) ** 2 + (truth - ca) ** 2) / 2.0
    d_mean = w * (ca - cb) ** 2
    terms = d - d_mean / 2.0 - w * (ca - truth) * (cb - truth)
    assert abs(terms.mean()) < 3 * terms.std() / np.sqrt(terms.size)
    var_half = d_mean / (2 * (1 - auto.halves_correlation(e)))
    plain = d - var_half
    assert abs(plain.mean()) < 3 * plain.std() / np.sqrt(plain.size)


def test_mosaic_places_each_crops_interior_and_scores_nothing_else():
    h, w = 96, 80
    rng = np.random.default_rng(0)
    frame = rng.random((h, w, 3))
    feats = {"depth": rng.random((h, w, 1))}
    p = auto.Params(tile=16, max_tiles=5)
    crops = auto.cv_regions(h, w, p)
    assert len(crops) == 5
    data = [[(frame[y0:y1, x0:x1], {k: v[y0:y1, x0:x1] for k, v in feats.items()}, 1)] * 4
            for x0, y0, x1, y1 in crops]
    subs, mask = auto.mosaic(crops, data, h, w)
    assert mask.sum() == 5 * 16 * 16
    got = np.sort(subs[0][0][mask].ravel())
    want = np.sort(np.concatenate([frame[y0:y1, x0:x1][auto._interior((x0, y0, x1, y1), h, w)].ravel()
                                   for x0, y0, x1, y1 in crops]))
    assert np.array_equal(got, want)
    assert subs[0][1]["depth"].shape[:2] == mask.shape


def test_one_crop_mosaic_scores_like_the_crop():
    rng = np.random.default_rng(1)
    truth = 0.2 + rng.random((40, 40, 3))
    subs = [(truth * rng.gamma(4.0, 0.25, truth.shape), {}, 1) for _ in range(4)]
    crop = (0, 0, 40, 40)
    m_subs, mask = auto.mosaic([crop], [subs], 40, 40)
    a = auto.score_tile(subs, crop, 40, 40, ["mean"], 1.2)
    b = auto.score_tile(m_subs, None, 40, 40, ["mean"], 1.2, mask=mask)
    assert np.allclose(np.sort(a["mean"]["terms"].ravel()), np.sort(b["mean"]["terms"].ravel()))
    assert np.isclose(a["mean"]["terms"].mean(), auto.mean_terms(subs, crop, 40, 40, 1.2).mean())
