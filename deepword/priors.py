"""1-D Gaussian mixtures on log distance ratios, chosen by BIC, and the prior functions built on them.

Public API used by other stages:

    from deepword.priors import load_priors
    p = load_priors(priors_stage_dir)
    p.wheel_vehicle(ratio)   # ratio (not log ratio), any shape -> values in [0, 1]
    p.wheel_wheel(ratio)

Mode ``prior``: likelihood of log(ratio) under the true-pair mixture divided by that mixture's maximum
density (the ``normaliser``), so 1 at the mode and monotone in the likelihood. Mode ``posterior``:
P(pair | ratio) = pi p_pair / (pi p_pair + (1 - pi) p_non), pi being the share of true pairs among the
train split's candidates. Everything is saved as JSON (no pickle), so any runtime can rebuild it.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

PRIORS_FILE = "priors.json"
MODES = ("prior", "posterior")
_MIN_RATIO = 1e-9  # a ratio of 0 (coincident centres) has log -inf; clip it to a finite log


def log_ratio(ratio) -> np.ndarray:
    """log of Eq. 2 ratios, a ratio of 0 (coincident centres) clipped to a finite value first."""
    return np.log(np.maximum(np.asarray(ratio, dtype=np.float64), _MIN_RATIO))


@dataclass
class Mixture1D:
    """A fitted 1-D Gaussian mixture."""

    weights: list[float]
    means: list[float]
    variances: list[float]

    def log_pdf(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)[..., None]
        w, mu, var = (np.asarray(v, dtype=np.float64) for v in (self.weights, self.means, self.variances))
        comp = np.log(w) - 0.5 * np.log(2 * np.pi * var) - 0.5 * (x - mu) ** 2 / var
        top = comp.max(axis=-1, keepdims=True)
        return (top + np.log(np.exp(comp - top).sum(axis=-1, keepdims=True)))[..., 0]

    def pdf(self, x: np.ndarray) -> np.ndarray:
        return np.exp(self.log_pdf(x))

    def max_density(self) -> float:
        """The mixture's highest density, searched on a fine grid covering every component."""
        mu, sd = np.asarray(self.means), np.sqrt(np.asarray(self.variances))
        grid = np.linspace((mu - 6 * sd).min(), (mu + 6 * sd).max(), 20001)
        return float(max(self.pdf(grid).max(), self.pdf(mu).max()))


@dataclass
class BicFit:
    """The mixture BIC chose, and the BIC of every tried component count."""

    mixture: Mixture1D
    bic: dict[int, float]
    log_likelihood: float  # mean log-likelihood per sample of the chosen mixture


def fit_mixture_bic(x: np.ndarray, components: tuple[int, int], seed: int, n_init: int = 2,
                    reg_covar: float = 1e-4) -> BicFit:
    """Fit GaussianMixture for each count in [lo, hi] (capped by the sample count) and keep the lowest BIC."""
    from sklearn.mixture import GaussianMixture  # deferred: scikit-learn loads only when priors are fitted

    x = np.asarray(x, dtype=np.float64).reshape(-1, 1)
    lo, hi = int(components[0]), int(components[1])
    if lo < 1 or hi < lo:
        raise ValueError(f"priors.components must be [lo, hi] with 1 <= lo <= hi, got {list(components)}")
    if len(x) < 2:
        raise ValueError(f"need at least 2 samples to fit a mixture, got {len(x)}")
    best, bics = None, {}
    for k in range(lo, min(hi, len(x)) + 1):
        gm = GaussianMixture(n_components=k, covariance_type="full", random_state=seed, n_init=n_init,
                             reg_covar=reg_covar).fit(x)
        bics[k] = float(gm.bic(x))
        if best is None or bics[k] < bics[best[0]]:
            best = (k, gm)
    gm = best[1]
    mixture = Mixture1D(weights=[float(v) for v in gm.weights_], means=[float(v) for v in gm.means_[:, 0]],
                        variances=[float(v) for v in gm.covariances_.reshape(-1)])
    return BicFit(mixture, bics, float(gm.score(x)))


@dataclass
class PairPrior:
    """The prior of one pair type: the true-pair mixture, optionally the non-pair mixture, and the mode."""

    mode: str
    pair: Mixture1D
    normaliser: float
    non_pair: Mixture1D | None = None
    pair_fraction: float | None = None

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"priors mode must be one of {MODES}, got {self.mode!r}")
        if self.mode == "posterior" and (self.non_pair is None or self.pair_fraction is None):
            raise ValueError("posterior mode needs the non-pair mixture and the pair fraction")

    def __call__(self, ratio) -> np.ndarray:
        log_r = log_ratio(ratio)
        if self.mode == "prior":
            return np.clip(self.pair.pdf(log_r) / self.normaliser, 0.0, 1.0)
        log_a = math.log(self.pair_fraction) + self.pair.log_pdf(log_r)
        log_b = math.log1p(-self.pair_fraction) + self.non_pair.log_pdf(log_r)
        return np.clip(1.0 / (1.0 + np.exp(np.clip(log_b - log_a, -700, 700))), 0.0, 1.0)

    def to_json(self) -> dict:
        return {"mode": self.mode, "pair": asdict(self.pair), "normaliser": self.normaliser,
                "non_pair": asdict(self.non_pair) if self.non_pair is not None else None,
                "pair_fraction": self.pair_fraction}

    @classmethod
    def from_json(cls, obj: dict) -> PairPrior:
        non_pair = Mixture1D(**obj["non_pair"]) if obj.get("non_pair") else None
        return cls(mode=obj["mode"], pair=Mixture1D(**obj["pair"]), normaliser=float(obj["normaliser"]),
                   non_pair=non_pair, pair_fraction=obj.get("pair_fraction"))


def make_pair_prior(mode: str, pair: Mixture1D, non_pair: Mixture1D | None, n_pairs: int,
                    n_non_pairs: int) -> PairPrior:
    """Assemble a PairPrior; pi is the share of true pairs among all candidates counted on train."""
    fraction = n_pairs / (n_pairs + n_non_pairs) if non_pair is not None else None
    if fraction is not None:
        fraction = min(max(fraction, 1e-6), 1 - 1e-6)
    return PairPrior(mode=mode, pair=pair, normaliser=pair.max_density(), non_pair=non_pair,
                     pair_fraction=fraction)


@dataclass
class Priors:
    """The two pair priors the relation network's adjacency and the `prior` baseline use."""

    wheel_vehicle: PairPrior
    wheel_wheel: PairPrior

    def save(self, out_dir: str | os.PathLike, extra: dict | None = None) -> Path:
        path = Path(out_dir) / PRIORS_FILE
        obj = {"wheel_vehicle": self.wheel_vehicle.to_json(), "wheel_wheel": self.wheel_wheel.to_json()}
        obj.update(extra or {})
        path.write_text(json.dumps(obj, indent=1))
        return path


def load_priors(priors_dir: str | os.PathLike) -> Priors:
    """Rebuild the priors from the priors stage's output directory (or a path to its priors.json)."""
    path = Path(priors_dir)
    if path.is_dir():
        path = path / PRIORS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: priors file not found (run the priors stage first)")
    try:
        obj = json.loads(path.read_text())
        return Priors(PairPrior.from_json(obj["wheel_vehicle"]), PairPrior.from_json(obj["wheel_wheel"]))
    except (KeyError, TypeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a valid priors file ({type(exc).__name__}: {exc})") from None
